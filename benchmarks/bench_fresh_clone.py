"""Regenerate docs/results/fresh_clone.md (+ .json) and the README's quick-start figures, measured on a fresh clone.

    .venv/bin/python -m benchmarks.bench_fresh_clone              # the install and the demo (a few minutes)
    .venv/bin/python -m benchmarks.bench_fresh_clone --tests      # the README's test command (about 15 minutes)
    .venv/bin/python -m benchmarks.bench_fresh_clone --page-only  # the page and the README's figures from the JSON

This is the one source of the README's figures of its two commands. The committed tree (``HEAD``) is
cloned into a temporary folder and the README's commands, read from that clone's README (the Quick
start's ``bash`` blocks), are run there, each timed on the wall clock, as on a new user's machine:

* **packages from the registry only**: no pip configuration file (``PIP_CONFIG_FILE`` set to the null
  device, so no local wheel folder, extra index or constraint of this machine), no ``PIP_*`` setting
  that names a package source, no pip cache; pip's installation report (``PIP_REPORT``, the command
  unchanged) names where every package came from, and a run where one came from anywhere but an
  ``https`` index is refused, not recorded;
* **nothing of an earlier run**: an empty home folder (no matplotlib font cache, no ``~/.config/pip``),
  an empty topoloc cache (``TOPOLOC_CACHE_DIR``), no compiled code (numba caches its kernels beside
  the package's sources, new in a clone), no ``TOPOLOC_*``, ``NUMBA_*``, ``PYTHONPATH`` or virtual
  environment of the shell that runs this.

Part ``demo`` (the Quick start, ``python3 -m venv .venv && .venv/bin/pip install -e . && .venv/bin/topoloc demo``):

1. the install, everything before the demo, and the bytes the machine's network interfaces received
   meanwhile (the whole machine's traffic: an upper bound of the download);
2. the environment: its size (every file under ``.venv``, apparent bytes), its largest distributions
   (their files as their ``RECORD`` lists them), whether PyTorch is in it and which OpenCV distributions;
3. the shipped XFeat network files (``xfeat.onnx``, ``xfeat.npz``) as the installed package holds them;
4. ``topoloc demo``: its first run (compiles Cooc-Map's numba kernels, caches them on disk); two later
   runs in new processes, the demo's outputs (its feature cache among them) removed before each, so
   that what carries over is the compiled kernels (and the operating system's file cache); one more
   with numba's cache files removed first: what the disk cache saves a process;
5. issue #47's targets: the environment <= 1.1 GB, the install and the first demo <= 90 s.

Part ``tests`` (``--tests``, the README's test command): its install, the environment it makes, and
``pytest`` in the clone (no ``../shared/data`` beside it, so the real-data tests skip, as on a new
user's machine).

Each part keeps its own commit, date and load; a run of one part keeps the other's figures. The README
states each figure once, between ``<!-- fresh-clone:NAME -->`` markers this script rewrites from the
JSON (``tests/test_readme.py`` checks that they agree). The load average is recorded around every
step: the figures are only as quiet as the machine was (run it under ``flock -x /work/notes/cpu.lock``
where others share it).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from benchmarks.common import RESULTS, machine_line

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
JSON = RESULTS / "fresh_clone.json"
PAGE = RESULTS / "fresh_clone.md"
COMMAND = ".venv/bin/python -m benchmarks.bench_fresh_clone"
#: Issue #47's targets for the Quick start: its environment (decimal megabytes, 1.1 GB) and its install + first demo.
TARGET_ENV_MB = 1100.0
TARGET_INSTALL_DEMO_S = 90.0
LATER_RUNS = 2
NETWORK_FILES = ("xfeat.onnx", "xfeat.npz")
#: The README's figures, each between its pair of markers.
MARKERS = ("demo", "environment", "weights", "tests")
NOT_MEASURED = "(not measured yet)"
LINK = "[fresh_clone.md](docs/results/fresh_clone.md)"
# pip settings that only tune the client (certificate of this network, timeout) are a machine's, not a package
# source: a new user behind the same network has them. Every other PIP_* setting is left out.
_PIP_KEPT = ("PIP_CERT", "PIP_DEFAULT_TIMEOUT", "PIP_CLIENT_CERT", "PIP_PROXY")


# ---- the README's commands ------------------------------------------------------------------------------------------

def readme_commands(text: str) -> dict[str, tuple[str, str]]:
    """The Quick start's two commands, each split where its install ends: ``{"demo"|"tests": (install, run)}``."""
    start, stop = text.find("## Quick start"), text.find("\n## ", text.find("## Quick start") + 1)
    if start < 0:
        raise SystemExit("README.md has no '## Quick start' section")
    blocks = re.findall(r"```bash\n(.*?)\n```", text[start:stop if stop > 0 else None], re.S)
    out: dict[str, tuple[str, str]] = {}
    for block in blocks:
        cmd = " ".join(line.strip() for line in block.splitlines() if line.strip() and not line.startswith("#"))
        install, sep, run = cmd.rpartition(" && ")
        if not sep:
            continue
        part = "demo" if run.endswith("topoloc demo") else "tests" if "pytest" in run else None
        if part and part not in out:
            out[part] = (install, run)
    missing = {"demo", "tests"} - set(out)
    if missing:
        raise SystemExit(f"README.md's Quick start has no command for {', '.join(sorted(missing))}")
    return out


# ---- the new user's shell -------------------------------------------------------------------------------------------

def new_user_env(base: dict[str, str], home: Path, cache: Path, report: Path) -> dict[str, str]:
    """``base`` as a new user's shell: packages from the registry only, an empty home and cache, no setting of ours."""
    dropped = ("TOPOLOC_", "NUMBA_", "PIP_", "XDG_", "MPL")
    env = {k: v for k, v in base.items()
           if (not k.startswith(dropped) or k in _PIP_KEPT) and k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
    # This checkout's environment is not a new user's: its folders leave PATH.
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep)
                                  if p and not Path(p).resolve().is_relative_to(ROOT))
    env.update({"HOME": str(home), "TOPOLOC_CACHE_DIR": str(cache), "PIP_CONFIG_FILE": os.devnull,
                "PIP_NO_CACHE_DIR": "1", "PIP_DISABLE_PIP_VERSION_CHECK": "1", "PIP_REPORT": str(report)})
    return env


def package_sources(report: dict[str, Any], clone: Path) -> dict[str, Any]:
    """Where pip's installation ``report`` took each package from; refused unless from an https index or the clone.

    The project itself comes from the clone (``pip install -e .``); everything else must be downloaded
    from a package index over https, never a local file, folder or ``file://`` index.
    """
    hosts: dict[str, int] = {}
    local: list[str] = []
    for item in report.get("install", []):
        url = item.get("download_info", {}).get("url", "")
        parsed = urlparse(url)
        if parsed.scheme == "file" and Path(parsed.path).resolve() == clone.resolve():
            continue  # the project, installed from its clone
        if parsed.scheme == "https" and not item.get("is_direct"):
            hosts[parsed.netloc] = hosts.get(parsed.netloc, 0) + 1
        else:
            local.append(f"{item.get('metadata', {}).get('name', '?')} from {url or 'an unknown place'}")
    if local:
        raise SystemExit("not a registry-only install: " + "; ".join(local))
    return {"downloaded": sum(hosts.values()), "hosts": hosts}


def _received_bytes() -> int | None:
    """Bytes received so far by the machine's network interfaces (all but loopback), or None where unknown."""
    try:
        lines = Path("/proc/net/dev").read_text().splitlines()[2:]
    except OSError:
        return None
    return sum(int(rest.split()[0]) for name, _, rest in (line.partition(":") for line in lines)
               if name.strip() != "lo")


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def _timed(name: str, cmd: str, cwd: Path, env: dict[str, str], timeout: float, *,
           check: bool = True) -> dict[str, Any]:
    """Run ``cmd`` in bash as the README writes it; its wall-clock seconds and the load around it."""
    before = _load()
    t0 = time.perf_counter()
    r = subprocess.run(["bash", "-c", cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    seconds = time.perf_counter() - t0
    row = {"step": name, "command": cmd, "seconds": round(seconds, 1), "exit": r.returncode,
           "load_before": before, "load_after": _load(), "tail": (r.stdout + r.stderr).strip().splitlines()[-3:]}
    print(json.dumps(row), flush=True)
    if r.returncode and check:
        raise SystemExit(f"{name} failed (exit {r.returncode}): {(r.stdout + r.stderr)[-2000:]}")
    return row


def _tree_bytes(path: Path) -> int:
    """Apparent bytes of the regular files under ``path`` (links not followed)."""
    return sum(p.lstat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())


# Run by the clone's environment: every distribution's bytes (the files its RECORD lists), its version, and where
# the shipped network files lie (as the installed package finds them).
_INSPECT = """
import importlib.metadata as md, importlib.util, json, os
sizes = {}
for d in md.distributions():
    n = 0
    for f in d.files or []:
        try:
            n += os.path.getsize(d.locate_file(f))
        except OSError:
            pass
    sizes[d.metadata["Name"]] = [n, d.version]
spec = importlib.util.find_spec("topoloc.features.xfeat")
print(json.dumps({"distributions": sizes, "xfeat": os.path.dirname(spec.origin)}))
"""


def environment(venv: Path, env: dict[str, str], n: int = 10) -> dict[str, Any]:
    """The environment ``venv``: its size, largest distributions, PyTorch or not, its OpenCV distributions."""
    out = subprocess.run([str(venv / "bin" / "python"), "-c", _INSPECT], env=env, capture_output=True, text=True,
                         check=True).stdout
    found = json.loads(out)
    dists = {name.lower(): (size, version) for name, (size, version) in found["distributions"].items()}
    largest = sorted(dists.items(), key=lambda kv: -kv[1][0])[:n]
    xfeat = Path(found["xfeat"])
    return {"mb": round(_tree_bytes(venv) / 1e6, 1), "distributions": len(dists),
            "largest": [{"name": k, "version": v, "mb": round(b / 1e6, 1)} for k, (b, v) in largest],
            "torch": "torch" in dists, "opencv": sorted(k for k in dists if k.startswith("opencv")),
            "network_files": {f: (xfeat / f).stat().st_size if (xfeat / f).is_file() else None
                              for f in NETWORK_FILES}}


def _numba_cache(clone: Path) -> list[Path]:
    return [p for p in (clone / "src").rglob("*") if p.suffix in (".nbi", ".nbc")]


# ---- the measurement ------------------------------------------------------------------------------------------------

def measure(part: str) -> dict[str, Any]:
    """Clone HEAD, run the README's command of ``part`` ("demo" or "tests") there; every figure and how it was made."""
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout.strip()
    dirty = bool(subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                                capture_output=True, text=True).stdout.strip())
    record: dict[str, Any] = {"commit": head, "tree_had_uncommitted_changes": dirty, "machine": machine_line()}
    with tempfile.TemporaryDirectory(prefix="topoloc-fresh-") as tmp:
        clone, home, cache, report = (Path(tmp) / "topoloc", Path(tmp) / "home", Path(tmp) / "cache",
                                      Path(tmp) / "pip-report.json")
        home.mkdir()
        subprocess.run(["git", "clone", "--quiet", "--no-checkout", str(ROOT), str(clone)], check=True)
        subprocess.run(["git", "-C", str(clone), "checkout", "--quiet", head], check=True)
        install, run = readme_commands((clone / "README.md").read_text())[part]
        env = new_user_env(dict(os.environ), home, cache, report)
        steps: list[dict[str, Any]] = []
        received = _received_bytes()
        steps.append(_timed("install", install, clone, env, 3600))
        after = _received_bytes()
        record["received_mb"] = (round((after - received) / 1e6, 1) if after is not None and received is not None
                                 else None)
        record["sources"] = package_sources(json.loads(report.read_text()), clone)
        record["environment"] = environment(clone / ".venv", env)
        if part == "demo":
            steps.append(_timed("first run", run, clone, env, 1800))
            record["numba_cache_files"] = len(_numba_cache(clone))
            for _ in range(LATER_RUNS):
                shutil.rmtree(clone / "demo_out")
                steps.append(_timed("later run", run, clone, env, 1800))
            shutil.rmtree(clone / "demo_out")
            for p in _numba_cache(clone):
                p.unlink()
            steps.append(_timed("later run, numba's cache removed", run, clone, env, 1800))
        else:
            # The ROS node's tests skip without ROS 1 (Debian's packages, not the registry's): said beside the figure.
            record["ros"] = shutil.which("roscore", path=env["PATH"]) is not None
            steps.append(_timed("tests", run, clone, env, 7200, check=False))
    now = datetime.now(UTC)
    record.update({"time": now.isoformat(timespec="seconds"), "date": now.date().isoformat(), "steps": steps})
    return record


def merged(old: dict[str, Any] | None, part: str, record: dict[str, Any]) -> dict[str, Any]:
    """The JSON with ``part`` replaced by ``record``, the other part's figures kept as they were."""
    parts = dict((old or {}).get("parts", {}))
    parts[part] = record
    return {"parts": {k: parts[k] for k in ("demo", "tests") if k in parts}}


# ---- the figures ----------------------------------------------------------------------------------------------------

def _step(record: dict[str, Any], name: str) -> list[dict[str, Any]]:
    return [s for s in record["steps"] if s["step"] == name]


def _median(values: list[float]) -> float:
    return round(float(statistics.median(values)), 1)


def _load_of(record: dict[str, Any]) -> float:
    return max(max(s["load_before"], s["load_after"]) for s in record["steps"])


def _beside(load: float) -> str:
    # Above about one busy process per core the machine was shared: said beside the figure.
    return "" if load < 2.5 else f", beside other jobs (load up to {load:.1f})"


def demo_figures(record: dict[str, Any]) -> dict[str, Any]:
    """The demo part's figures: seconds of each step (later runs: their median) and issue #47's targets."""
    install = _step(record, "install")[0]["seconds"]
    first = _step(record, "first run")[0]["seconds"]
    later = _median([s["seconds"] for s in _step(record, "later run")])
    uncached = _step(record, "later run, numba's cache removed")
    env_mb = record["environment"]["mb"]
    return {"install_s": install, "first_s": first, "later_s": later,
            "uncached_s": uncached[0]["seconds"] if uncached else None, "install_demo_s": round(install + first, 1),
            "env_mb": env_mb, "env_met": env_mb <= TARGET_ENV_MB,
            "install_demo_met": install + first <= TARGET_INSTALL_DEMO_S, "load": _load_of(record)}


def tests_figures(record: dict[str, Any]) -> dict[str, Any]:
    """The tests part's figures: seconds of its install and of pytest, and pytest's counts from its summary line."""
    tests = _step(record, "tests")[0]
    summary = tests["tail"][-1] if tests["tail"] else ""
    counts = {word: int(n) for n, word in re.findall(r"(\d+) (passed|skipped|failed|errors?)\b", summary)}
    return {"install_s": _step(record, "install")[0]["seconds"], "tests_s": tests["seconds"], "exit": tests["exit"],
            "counts": counts, "load": _load_of(record)}


def _mb(n: int | None) -> str:
    return "missing" if n is None else f"{n / 1e6:.1f} MB"


def readme_sentences(summary: dict[str, Any]) -> dict[str, str]:
    """The README's text between each pair of ``fresh-clone`` markers; a part not measured yet says so."""
    parts = summary.get("parts", {})
    out = dict.fromkeys(MARKERS, NOT_MEASURED)
    if "demo" in parts:
        d = parts["demo"]
        f, e, cores = demo_figures(d), d["environment"], d["machine"].split(", ")[1]
        compiled = ("it compiles Cooc-Map's numba kernels and caches them on disk beside their sources"
                    if d["numba_cache_files"] else "no compiled kernel was cached on disk")
        out["demo"] = (f"on a fresh clone, every package downloaded from the registry (no local wheels, no pip "
                       f"cache), the install took {f['install_s']:.0f} s and the demo's first run "
                       f"{f['first_s']:.0f} s ({compiled}), a later run in a new process {f['later_s']:.0f} s; {cores}"
                       f"{_beside(f['load'])}, measured on {d['date']}: {LINK}")
        largest = ", ".join(f"{p['name']} {p['mb']:.0f} MB" for p in e["largest"][:4])
        opencv = (f"one OpenCV ({e['opencv'][0]})" if len(e["opencv"]) == 1
                  else f"{len(e['opencv'])} OpenCV distributions ({', '.join(e['opencv'])})")
        out["environment"] = (f"{e['mb']:.0f} MB, {e['distributions']} distributions, "
                              f"{'with' if e['torch'] else 'no'} PyTorch, {opencv}; the largest: {largest}; "
                              f"measured on {d['date']}")
        files = e["network_files"]
        out["weights"] = " and ".join(f"`{name}` ({_mb(files.get(name))})" for name in NETWORK_FILES) + \
            f", sizes measured on {d['date']}"
    if "tests" in parts:
        t = parts["tests"]
        f, cores = tests_figures(t), t["machine"].split(", ")[1]
        counts = ", ".join(f"{n} {word}" for word, n in f["counts"].items()) or f"exit status {f['exit']}"
        out["tests"] = (f"on a fresh clone, every package downloaded from the registry, without the shared data"
                        f"{'' if t['ros'] else ' and ROS'}, "
                        f"its install took {f['install_s']:.0f} s and its tests {f['tests_s'] / 60:.1f} min "
                        f"({counts}), {cores}{_beside(f['load'])}, measured on {t['date']}: {LINK}")
    return out


def rewrite_readme(summary: dict[str, Any], text: str) -> str:
    """``text`` (the README) with each marked figure replaced by the measured one."""
    for name, sentence in readme_sentences(summary).items():
        pattern = re.compile(rf"(<!-- fresh-clone:{name} -->).*?(<!-- /fresh-clone:{name} -->)", re.S)
        if not pattern.search(text):
            raise SystemExit(f"README.md has no <!-- fresh-clone:{name} --> marker")
        text = pattern.sub(lambda m, s=sentence: f"{m.group(1)}{s}{m.group(2)}", text)
    return text


# ---- the page -------------------------------------------------------------------------------------------------------

def _met(ok: bool) -> str:
    return "met" if ok else "**NOT met**"


def _part_header(r: dict[str, Any]) -> str:
    src = r["sources"]
    hosts = ", ".join(f"{h} ({n})" for h, n in src["hosts"].items()) or "none"
    received = (f"; the machine's network interfaces received {r['received_mb']:.0f} MB during the install "
                "(all of the machine's traffic: at most that was downloaded)" if r.get("received_mb") else "")
    return (f"{r['machine']}, {r['time']}, commit `{r['commit'][:10]}`"
            f"{', with uncommitted changes' if r['tree_had_uncommitted_changes'] else ''}. "
            f"Packages: {src['downloaded']} downloaded, from {hosts}, none from a local file or folder{received}.\n\n")


def _steps_table(r: dict[str, Any]) -> list[str]:
    lines = ["| step | command | s | load before | load after |\n| --- | --- | --- | --- | --- |\n"]
    lines += [f"| {s['step']} | `{s['command']}` | {s['seconds']} | {s['load_before']} | {s['load_after']} |\n"
              for s in r["steps"]]
    return lines


def _environment_lines(e: dict[str, Any]) -> list[str]:
    return [f"\nThe environment: {e['mb']:.0f} MB (every file under `.venv`), {e['distributions']} distributions, "
            f"PyTorch {'installed' if e['torch'] else 'not installed'}, OpenCV: {', '.join(e['opencv']) or 'none'}. "
            "Its largest distributions (the files their `RECORD` lists):\n\n",
            "| distribution | version | MB |\n| --- | --- | --- |\n",
            *[f"| {p['name']} | {p['version']} | {p['mb']} |\n" for p in e["largest"]]]


def page(summary: dict[str, Any]) -> str:
    parts = summary.get("parts", {})
    lines = [
        "# The README's commands on a fresh clone\n\n",
        f"Generated by `{COMMAND}` (the Quick start: install and demo) and `{COMMAND} --tests` (the test "
        "command); do not edit by hand. Raw: [fresh_clone.json](fresh_clone.json); how each figure is made: "
        "`benchmarks/bench_fresh_clone.py`. The README states these figures, each once.\n\n",
        "The committed tree is cloned into an empty folder and the README's commands run there as a new user runs "
        "them: every package downloaded from the registry (no pip configuration, so no local wheel folder, extra "
        "index or constraint; no pip cache; pip's installation report checked: a package from anywhere else "
        "refuses the run), an empty home folder and topoloc cache, no compiled code of an earlier run, no "
        "`TOPOLOC_*` or `NUMBA_*` setting. Wall-clock seconds; the 1-minute load average before and after each "
        "step says how quiet the machine was (above about 2.5 on 2 cores it was shared, and every step slower).\n\n",
    ]
    if "demo" in parts:
        d = parts["demo"]
        f, e = demo_figures(d), d["environment"]
        lines += ["## The Quick start: install and demo\n\n", _part_header(d)]
        lines += _steps_table(d)
        lines.append(f"\nThe later runs start in a new process with the demo's outputs (its feature cache among them) "
                     f"removed, so what carries over from the first is the {d['numba_cache_files']} numba cache "
                     "files it wrote beside the sources (and the operating system's file cache); the last run "
                     "removes those too.")
        if f["uncached_s"] is not None:
            lines.append(f" Numba's disk cache saves a later process {f['uncached_s'] - f['later_s']:.0f} s "
                         f"({f['uncached_s']:.0f} s without it, {f['later_s']:.0f} s with it).")
        lines.append("\n")
        lines += _environment_lines(e)
        lines.append("\nXFeat's network files as the installed package holds them: "
                     + ", ".join(f"`{n}` {_mb(e['network_files'].get(n))}" for n in NETWORK_FILES) + ".\n\n")
        busy = " (measured beside other jobs: a quiet machine is faster)" if f["load"] >= 2.5 else ""
        lines += ["### Issue #47's targets\n\n",
                  f"- the environment <= {TARGET_ENV_MB / 1000:.1f} GB: {f['env_mb']:.0f} MB, {_met(f['env_met'])}.\n",
                  f"- the install and the first demo <= {TARGET_INSTALL_DEMO_S:.0f} s on 2 cores: "
                  f"{f['install_s']:.0f} + {f['first_s']:.0f} = {f['install_demo_s']:.0f} s, "
                  f"{_met(f['install_demo_met'])}{busy}.\n\n"]
    if "tests" in parts:
        t = parts["tests"]
        lines += ["## The test command\n\n", _part_header(t)]
        lines += _steps_table(t)
        lines.append(f"\npytest's summary: `{t['steps'][-1]['tail'][-1] if t['steps'][-1]['tail'] else ''}`\n")
        lines += _environment_lines(t["environment"])
        lines.append("\n")
    lines.append("## What the README says of them\n\n")
    lines += [f"- {name}: {text}\n" for name, text in readme_sentences(summary).items()]
    return "".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tests", action="store_true",
                        help="Time the README's test command instead of the install and the demo.")
    parser.add_argument("--page-only", action="store_true", help="Write the page and README from the JSON.")
    args = parser.parse_args(argv)
    readme_commands(README.read_text())  # the README names both commands before minutes are spent
    if args.page_only:
        summary = json.loads(JSON.read_text())
    else:
        part = "tests" if args.tests else "demo"
        summary = merged(json.loads(JSON.read_text()) if JSON.is_file() else None, part, measure(part))
        JSON.write_text(json.dumps(summary, indent=1) + "\n")
    PAGE.write_text(page(summary))
    README.write_text(rewrite_readme(summary, README.read_text()))
    print(f"wrote {PAGE} and the README's figures", file=sys.stderr)
    tests = summary.get("parts", {}).get("tests")
    if args.tests and tests["steps"][-1]["exit"]:  # recorded as it was, and said
        raise SystemExit(f"the README's test command failed (exit {tests['steps'][-1]['exit']}): see {PAGE}")


if __name__ == "__main__":
    if shutil.which("git") is None:
        raise SystemExit("git is needed to clone the tree")
    main()
