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
    "errors": 0, "io": 0, "_params": 0, "_parallel": 0, "_version": 0, "cluster": 0, "progress": 0,
    # 1 inputs: images, traverses, features, vocabularies, geometry, synthetic data
    "datasets": 1, "features": 1, "vocabulary": 1, "geometry": 1, "synth": 1,
    # 2 algorithm packages: arrays in, arrays out
    "bow": 2, "confidence": 2, "ranking": 2, "coocmap": 2, "fabmap": 2, "landmarks": 2, "seqslam": 2, "sequence": 2,
    "voting": 2, "verification": 2,
    # 3 resources: the per-image inputs a recogniser reads (features, words, vocabulary), cached or in memory
    "resources": 3,
    # 4 recognisers (adapters to the Resources protocol), their registry and test helpers
    "methods": 4, "testing": 4,
    # 5 run specifications: a command's settings, validated once, turned into a recogniser and its resources
    "spec": 5,
    # 6 pipelines: evaluation, saved maps and localisation, benchmarks, demo, match drawings
    "evaluation": 6, "bench": 6, "demo": 6, "maps": 6, "drawing": 6,
    # 7 the command line
    "cli": 7,
    # 7 the ROS node: an adapter of the saved maps to a running ROS graph, run by the command line
    "ros": 7,
    # 8 the entry point above every layer: python -m topoloc (the command line, ros-node among its commands)
    "__main__": 8,
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
        if module == "topoloc":  # the package's __init__ imports every layer: nothing inside may climb to it
            bad.append(f"{path.relative_to(PACKAGE.parent)}:{line} imports topoloc itself (above every layer)")
            continue
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


# -- algorithm packages neither draw nor write files ---------------------------------------

#: Calls that write files, whatever the object (``Path.write_text``, ``fig.savefig``, ``cv2.imwrite``...).
WRITING_CALLS = {"open", "write_text", "write_bytes", "savefig", "imwrite", "tofile", "savetxt", "savez",
                 "savez_compressed", "mkdir", "to_csv", "touch"}
#: topoloc's own writers: importing one is writing.
WRITERS = {"write_container", "atomic_write_bytes", "write_map_file"}
DRAWING_MODULES = ("matplotlib", "PIL", "seaborn", "plotly")


def _writes_or_draws(source: str) -> list[str]:
    """``line: what`` for each import of a drawing library, file-writing call or writer import in ``source``."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [f"{node.lineno}: imports {a.name}" for a in node.names if a.name.startswith(DRAWING_MODULES)]
        elif isinstance(node, ast.ImportFrom):
            if (node.module or "").startswith(DRAWING_MODULES):
                out.append(f"{node.lineno}: imports {node.module}")
            out += [f"{node.lineno}: imports {a.name}" for a in node.names if a.name in WRITERS]
        elif isinstance(node, ast.Call):
            f = node.func
            name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""
            # np.save / numpy.save; a method called save on anything else is not known to write.
            numpy_save = (isinstance(f, ast.Attribute) and f.attr == "save" and isinstance(f.value, ast.Name)
                          and f.value.id in {"np", "numpy"})
            if name in WRITING_CALLS or name in WRITERS or numpy_save:
                out.append(f"{node.lineno}: calls {name}()")
    return out


@pytest.mark.parametrize("path", [p for p in _sources() if p.relative_to(PACKAGE).parts[0] in ALGORITHMS],
                         ids=lambda p: str(p.relative_to(PACKAGE)))
def test_algorithm_packages_neither_draw_nor_write_files(path: Path) -> None:
    # Layer 2 takes arrays and returns arrays; files and figures are made by the layers that run it.
    found = _writes_or_draws(path.read_text())
    assert not found, f"{path.relative_to(PACKAGE.parent)}: " + "; ".join(found)


def test_the_writing_check_sees_writes_and_drawing() -> None:
    source = ("import matplotlib.pyplot as plt\nimport numpy as np\nfrom topoloc.io.container import write_container\n"
              "def f(p, a):\n    np.save(p, a)\n    open(p, 'w')\n    p.write_text('x')\n    plt.savefig(p)\n"
              "    model.save(p)\n")
    assert _writes_or_draws(source) == ["1: imports matplotlib.pyplot", "3: imports write_container",
                                        "5: calls save()", "6: calls open()", "7: calls write_text()",
                                        "8: calls savefig()"]


# -- no import cycles between modules ------------------------------------------------------


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _module_edges(source: str, module: str, is_package: bool, modules: set[str]) -> set[str]:
    """The topoloc modules ``source`` (module ``module``) imports, imports inside functions included.

    ``from a.b import c`` is an import of ``a.b.c`` where that is a module, else of ``a.b``.
    Imports under ``if TYPE_CHECKING:`` count too: a circle that only annotations close still ties
    the two modules together (issue #41); name such a type with a protocol instead.
    """
    def known(name: str) -> str:
        parts = name.split(".")
        while parts and ".".join(parts) not in modules:
            parts.pop()
        return ".".join(parts)

    tree = ast.parse(source)
    package = module.split(".") if is_package else module.split(".")[:-1]
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {known(a.name) for a in node.names if a.name.startswith("topoloc")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join([*package[: len(package) - node.level + 1], *([node.module] if node.module else [])])
            else:
                base = node.module or ""
            if base.startswith("topoloc"):
                out |= {f"{base}.{a.name}" if f"{base}.{a.name}" in modules else known(base) for a in node.names}
    return out - {module, ""}


def _import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected groups of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                cycles.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return cycles


def test_no_two_modules_import_each_other() -> None:
    # A cycle makes import order matter and hides which module depends on which; within a
    # package the layer rule above cannot see one, so it is checked module by module.
    files = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph = {name: _module_edges(p.read_text(), name, p.name == "__init__.py", set(files))
             for name, p in files.items()}
    assert not _import_cycles(graph), "import cycles: " + "; ".join(" <-> ".join(c) for c in _import_cycles(graph))


def test_the_cycle_check_finds_cycles_through_functions_and_type_checking() -> None:
    modules = {"topoloc.a", "topoloc.a.x", "topoloc.a.y", "topoloc.b"}
    x = _module_edges("def f():\n    from topoloc.a import y\n", "topoloc.a.x", False, modules)
    y = _module_edges("from .x import f\nfrom typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                      "    from topoloc.b import B\n", "topoloc.a.y", False, modules)
    assert x == {"topoloc.a.y"} and y == {"topoloc.a.x", "topoloc.b"}
    assert _import_cycles({"topoloc.a.x": x, "topoloc.a.y": y, "topoloc.b": {"topoloc.a.y"}}) == [
        ["topoloc.a.x", "topoloc.a.y", "topoloc.b"]]


def test_no_two_packages_import_each_other() -> None:
    # Within one layer (evaluation and maps, say) the layer rule cannot see a pair of packages that import
    # each other; one of them climbs.  evaluation imports maps (a saved map to evaluate), maps nothing of
    # evaluation (issue #41).
    graph: dict[str, set[str]] = {}
    for path in _sources():
        if path.name == "__main__.py":
            continue  # an entry point (python -m topoloc.ros runs the command line): nothing imports it
        me = path.relative_to(PACKAGE).parts[0].removesuffix(".py")
        graph.setdefault(me, set()).update(t for _, m in _imports(path) if (t := _unit(m)) and t != me)
    assert not _import_cycles(graph), "packages importing each other: " + "; ".join(
        " <-> ".join(c) for c in _import_cycles(graph))


def test_the_ros_package_never_imports_the_command_line() -> None:
    # The command line runs the node (topoloc ros-node); the node's package runs nothing of the command line,
    # __main__ included (issue #49: python -m topoloc.ros imported the command line from below it).
    bad = [f"{p.relative_to(PACKAGE.parent)}:{line} imports {m}" for p in (PACKAGE / "ros").rglob("*.py")
           for line, m in _imports(p) if _unit(m) == "cli"]
    assert not bad, "\n".join(bad)


def test_the_climb_check_sees_an_import_of_the_package_itself() -> None:
    assert _imports_of("def f():\n    from topoloc import __version__\n", "topoloc.maps.map") == [(2, "topoloc")]
