"""What both ROS nodes' tests do alike: read a probe's record, stop a process, run topoloc, compare with localize."""

from __future__ import annotations

import json
import signal
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from topoloc.cli.main import app


def records(path: Path, kind: str | None = None) -> list[dict[str, Any]]:
    """The probe's JSON lines (``topoloc.ros.record``) of ``kind`` (every kind: None); none before it wrote any."""
    if not path.exists():
        return []
    lines = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [r for r in lines if kind is None or r.get("kind") == kind]


def stop(proc: subprocess.Popen[str], sig: int = signal.SIGTERM, timeout: float = 30.0) -> int:
    """Stop ``proc`` as a user does (``sig``); its exit status."""
    if proc.poll() is None:
        proc.send_signal(sig)
    return proc.wait(timeout=timeout)


def ok(args: list[str]) -> str:
    """``topoloc ARGS``, which must succeed; its standard output."""
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output + repr(result.exception)
    return result.stdout


def assert_answers_equal_localize(answers: list[dict[str, Any]], route: dict[str, Any], topics: dict[str, str],
                                  n: int, keys: tuple[str, ...], seconds: Callable[[dict[str, Any]], float]) -> None:
    """Each node's answers (``/topoloc_K/answer`` for K of ``topics``) are ``localize``'s lines of the bag's topic,
    frame for frame: the ``keys`` equal, positions given, the frame's own stamp (``seconds(stamp)``) and frame id."""
    for k, topic in topics.items():
        lines_file = route["root"] / f"localize_{k}.jsonl"
        ok(["localize", str(route["map"]), str(route["bag"]), "--topic", topic, "--out", str(lines_file), "-q"])
        expected = [json.loads(line) for line in lines_file.read_text().splitlines()]
        got = [a for a in answers if a["topic"] == f"/topoloc_{k}/answer"]
        assert len(got) == len(expected) == n
        for a, e in zip(got, expected, strict=True):
            assert {key: a.get(key) for key in keys} == {key: e.get(key) for key in keys}
            assert "x" in a  # the map has positions
            assert seconds(a["stamp"]) == pytest.approx(e["time"], abs=1e-6)
            assert a["frame_id"] == "camera"
