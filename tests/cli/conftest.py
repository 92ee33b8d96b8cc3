"""Shared CLI fixtures: the tiny route as folders with a saved vocabulary, and one-line-error checks."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from topoloc.cli.main import app


class Cli:
    """Runs ``topoloc`` in-process; ``ok`` expects exit 0, ``error`` one line ``topoloc: error: ...`` and exit 2."""

    def __init__(self) -> None:
        self.runner = CliRunner()

    def ok(self, args: list[str]) -> str:
        r = self.runner.invoke(app, args)
        assert r.exit_code == 0, r.output + (r.stderr or "") + repr(r.exception)
        return r.stdout

    def error(self, args: list[str], needle: str) -> str:
        r = self.runner.invoke(app, args)
        assert r.exit_code == 2, (r.output, r.exception)
        err = r.stderr.strip().splitlines()[-1] if r.stderr.strip() else ""
        assert err.startswith("topoloc: error:") and needle in err, err
        return err


@pytest.fixture()
def cli() -> Cli:
    return Cli()


@pytest.fixture(scope="module")
def rf(tiny_route: dict[str, Any], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The tiny route's folders (``map``, ``query``, ``morning``), its vocabulary file and a cache folder."""
    root = tmp_path_factory.mktemp("cli_route")
    voc = root / "vocab.tlv"
    tiny_route["vocabulary"].save(voc)
    return {"root": root, "vocab": voc, "map": tiny_route["map"].root, "query": tiny_route["query"].root,
            "morning": tiny_route["training"].root, "cache": root / "cache"}
