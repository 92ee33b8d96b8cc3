"""Build and run openFABMAP 2.0 beside topoloc's FAB-MAP 2.0 on the same words (benchmarks only).

openFABMAP (https://github.com/arrenglover/openfabmap, BSD; measured at commit
:data:`OPENFABMAP_COMMIT`) is compiled at benchmark time from a local copy of its repository,
named by ``bench_fabmap_openfabmap --openfabmap-src FOLDER`` or the environment variable
``OPENFABMAP_SRC``: a source folder (holding ``src/`` and ``include/``, as ``git clone`` makes
it) or a git directory whose ``HEAD`` is exported.  Nothing is looked for elsewhere: without
either, the benchmark stops (and its test skips) with a line saying how to get it.  Its
``fabmap.cpp`` and ``inference.cpp`` are
compiled with ``benchmarks/openfabmap_driver.cpp`` (``g++ -O3``, as its CMake Release build,
OpenCV core from ``pkg-config opencv4`` or ``/usr/include/opencv4``) into
``~/.cache/topoloc/openfabmap/``; none of its code enters this repository.

:func:`run_openfabmap` hands the driver a Chow-Liu tree, training, map and query words and
returns its per-query milliseconds and best matches.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from topoloc.fabmap.model import FabMapModel

DRIVER = Path(__file__).with_name("openfabmap_driver.cpp")
SRC_ENV = "OPENFABMAP_SRC"
#: The public repository and the commit the results in docs/results/fabmap_openfabmap.md were measured on.
OPENFABMAP_REPO = "https://github.com/arrenglover/openfabmap"
OPENFABMAP_COMMIT = "47fef64e2cb6407604cbce415a44a9b9e6219da8"
HOW_TO_GET = (f"git clone {OPENFABMAP_REPO} && git -C openfabmap checkout {OPENFABMAP_COMMIT[:12]}, then "
              f"set {SRC_ENV}=openfabmap (or --openfabmap-src openfabmap)")
CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "topoloc" / "openfabmap"


class OpenFabMapUnavailable(RuntimeError):
    """openFABMAP could not be found or built; the message says why."""


def _cflags() -> list[str]:
    try:
        out = subprocess.run(["pkg-config", "--cflags", "--libs", "opencv4"], capture_output=True, text=True,
                             check=True).stdout.split()
        return out if "-lopencv_core" in out else [*out, "-lopencv_core"]
    except (OSError, subprocess.CalledProcessError):
        if Path("/usr/include/opencv4/opencv2/core.hpp").is_file():
            return ["-I/usr/include/opencv4", "-lopencv_core"]
    raise OpenFabMapUnavailable("OpenCV core headers not found (Debian: apt-get install libopencv-core-dev)")


def _export_source(src: Path, into: Path) -> None:
    if (src / "src" / "fabmap.cpp").is_file():
        shutil.copytree(src / "src", into / "src")
        shutil.copytree(src / "include", into / "include")
        return
    if (src / "HEAD").is_file():  # a bare git directory (the mirror)
        archive = subprocess.run(["git", f"--git-dir={src}", "archive", "HEAD", "src", "include"],
                                 capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
        return
    raise OpenFabMapUnavailable(f"no openFABMAP sources (src/fabmap.cpp, or a git directory) at {src}: {HOW_TO_GET}")


def build_openfabmap(src: str | Path | None = None) -> Path:
    """The compiled driver (built once per driver version and source, then reused); raises OpenFabMapUnavailable.

    ``src``: the openFABMAP sources (default ``$OPENFABMAP_SRC``; see the module docstring).
    """
    given = src if src is not None else os.environ.get(SRC_ENV)
    if not given:
        raise OpenFabMapUnavailable(f"openFABMAP sources not given: {HOW_TO_GET}")
    src = Path(given).expanduser()
    if not src.exists():
        raise OpenFabMapUnavailable(f"no openFABMAP sources at {src}: {HOW_TO_GET}")
    key = hashlib.sha256(DRIVER.read_bytes() + str(src.resolve()).encode()).hexdigest()[:12]
    exe = CACHE / f"openfabmap_driver_{key}"
    if exe.is_file():
        return exe
    flags = _cflags()
    CACHE.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        _export_source(src, t)
        cmd = ["g++", "-O3", "-DNDEBUG", "-fopenmp", "-std=c++14", f"-I{t / 'include'}",
               str(t / "src" / "fabmap.cpp"), str(t / "src" / "inference.cpp"), str(DRIVER),
               "-o", str(exe) + ".part", *flags]
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0:
            raise OpenFabMapUnavailable("openFABMAP did not compile: " + done.stderr.strip()[-500:])
    os.replace(str(exe) + ".part", exe)
    return exe


def tree_rows(model: FabMapModel) -> np.ndarray:
    """The model's Chow-Liu tree in openFABMAP's layout, shape (4, V).

    Rows: parent, ``p(z_q = 1)``, ``p(z_q = 1 | z_p = 1)``, ``p(z_q = 1 | z_p = 0)``; at the root
    openFABMAP stores the word as its own parent with both conditionals equal to the marginal, as
    topoloc's model does.
    """
    return np.stack([model.parents.astype(np.float64), model.p_z, model.p_z_given_parent[1],
                     model.p_z_given_parent[0]])


def _write_images(f: object, images: Sequence[np.ndarray]) -> None:
    lines = [f"{len(images)}"]
    lines += [f"{len(w)} " + " ".join(map(str, np.asarray(w, np.int64).tolist())) for w in images]
    f.write("\n".join(lines) + "\n")  # type: ignore[attr-defined]


def run_openfabmap(model: FabMapModel, training: Sequence[np.ndarray], map_images: Sequence[np.ndarray],
                   queries: Sequence[np.ndarray], *, reps: int = 3,
                   likelihoods: bool = False) -> dict[str, np.ndarray]:
    """openFABMAP 2.0 (sampled new-place term, Chow-Liu) on these words.

    The detector model is topoloc's: ``PzGe = 1 - p_fn``, ``PzGNe = p_fp``.

    Returns
    -------
    dict
        ``ms`` (per query, the fastest of ``reps`` calls), ``best`` (map image of highest
        likelihood), ``log_lik_best`` (relative to the empty place), ``p_new`` and ``p_best``;
        with ``likelihoods``, also ``log_lik`` of every map image, shape (n_map, n_queries).
    """
    exe = build_openfabmap()
    with tempfile.TemporaryDirectory() as tmp:
        inp, out, lik = Path(tmp) / "in.txt", Path(tmp) / "out.txt", Path(tmp) / "lik.txt"
        with inp.open("w") as f:
            f.write(f"{model.n_words} {1.0 - model.p_fn!r} {model.p_fp!r} {reps}\n")
            for row in tree_rows(model):
                f.write(" ".join(repr(float(x)) for x in row) + "\n")
            for images in (training, map_images, queries):
                _write_images(f, images)
        cmd = [str(exe), str(inp), str(out), *([str(lik)] if likelihoods else [])]
        subprocess.run(cmd, check=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
        a = np.loadtxt(out, ndmin=2)
        res = {"ms": a[:, 0], "best": a[:, 1].astype(np.int64), "log_lik_best": a[:, 2], "p_new": a[:, 3],
               "p_best": a[:, 4]}
        if likelihoods:
            res["log_lik"] = np.loadtxt(lik, ndmin=2).T
    return res
