"""Imports only point down: a module may import its own package, or packages of lower layers.

The layers are those of ``docs/architecture.md``; this test walks every import
statement of the package (including imports inside functions) and fails on one
that points up, naming the file and line.  A new top-level module or package
must be given a layer here (and in the document) before it can be imported.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "topoloc"

LAYERS: dict[str, int] = {
    # 0 foundation: no topoloc imports but each other
    "errors": 0, "io": 0, "_params": 0, "_parallel": 0, "cluster": 0, "progress": 0,
    # 1 inputs: images, traverses, features, vocabularies, geometry, synthetic data
    "datasets": 1, "features": 1, "vocabulary": 1, "geometry": 1, "synth": 1,
    # 2 algorithm packages: arrays in, arrays out
    "bow": 2, "confidence": 2, "coocmap": 2, "fabmap": 2, "landmarks": 2, "seqslam": 2, "sequence": 2, "voting": 2,
    # 3 recognisers (adapters to the Resources protocol), their registry and test helpers
    "methods": 3, "testing": 3,
    # 4 pipelines: evaluation, saved maps and localisation, benchmarks, demo
    "evaluation": 4, "bench": 4, "demo": 4, "maps": 4,
    # 5 the command line
    "cli": 5,
}
ALGORITHMS = {name for name, layer in LAYERS.items() if layer == 2}


def _unit(module: str) -> str:
    """``topoloc.a.b`` -> ``a`` (the top-level package or module the layer belongs to)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _imports(path: Path) -> list[tuple[int, str]]:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    return _imports_of(path.read_text(), ".".join(rel.parts))


def _imports_of(source: str, module: str) -> list[tuple[int, str]]:
    """``(line, absolute module name)`` of every topoloc import in ``source``, the module ``module``.

    ``module`` names a file (``topoloc.coocmap.model``, ``topoloc.coocmap.__init__``), so its
    package, against which relative imports resolve, is all but its last part.
    """
    tree = ast.parse(source)
    package = module.split(".")[:-1]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names if a.name.startswith("topoloc")]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative import: resolve against this module's package
                base = package[: len(package) - node.level + 1]
                name = ".".join([*base, node.module] if node.module else base)
            else:
                name = node.module or ""
            if name.startswith("topoloc"):
                out.append((node.lineno, name))
    return sorted(out)


def _sources() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if p != PACKAGE / "__init__.py")


def test_every_unit_has_a_layer() -> None:
    units = {p.relative_to(PACKAGE).parts[0].removesuffix(".py") for p in _sources()}
    missing = sorted(units - set(LAYERS))
    assert not missing, f"give these a layer in tests/test_layers.py and docs/architecture.md: {missing}"


@pytest.mark.parametrize("path", _sources(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_point_down(path: Path) -> None:
    me = path.relative_to(PACKAGE).parts[0].removesuffix(".py")
    bad = []
    for line, module in _imports(path):
        target = _unit(module)
        if not target or target == me:
            continue
        if LAYERS[target] > LAYERS[me]:
            bad.append(f"{path.relative_to(PACKAGE.parent)}:{line} imports {module} "
                       f"(layer {LAYERS[target]} above {me}'s {LAYERS[me]})")
    assert not bad, "\n".join(bad)


def test_algorithm_packages_know_nothing_of_adapters_pipelines_or_cli() -> None:
    # The rule above, stated the way the architecture document states it.
    for path in _sources():
        if path.relative_to(PACKAGE).parts[0] in ALGORITHMS:
            for line, module in _imports(path):
                assert _unit(module) not in {"methods", "evaluation", "bench", "cli", "testing"}, (
                    f"{path}:{line} imports {module}")


def test_the_walker_sees_imports_inside_functions_and_relative_imports() -> None:
    # A test that cannot fail is no test: check the walker on known imports.
    source = ("import numpy\nimport topoloc.io\ndef f():\n    from topoloc.methods.base import PlaceRecognizer\n"
              "from .matching import eliminate\nfrom .. import errors\n")
    found = _imports_of(source, "topoloc.coocmap.model")
    assert found == [(2, "topoloc.io"), (4, "topoloc.methods.base"), (5, "topoloc.coocmap.matching"),
                     (6, "topoloc")]
    assert _unit("topoloc.methods.base") == "methods" and LAYERS["methods"] > LAYERS["coocmap"]
