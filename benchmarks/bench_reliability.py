"""Regenerate docs/results/reliability.md: kill `evaluate`, `map build` and `slam` at random moments.

    .venv/bin/python -m benchmarks.bench_reliability

On a generated route (no shared data needed), each command is first run to
completion (the reference) and timed; then, for a seeded set of kill times
spread over that duration, the command is started on the outputs of the
previous attempt, killed with SIGKILL at that moment, every file it left is
checked to be whole and valid (metrics.json parses, every .npy loads, a map
file loads and checks its CRC, CSV lines are complete), and the command is run
again to completion and compared with the reference (S.npy equal, map scores
equal, loop closures equal).  A case *survives* when both hold.
"""

from __future__ import annotations

import csv
import json
import os
import platform
import signal
import subprocess
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import RESULTS, TOPOLOC

KILLS_PER_COMMAND = 8
SEED = 20261123


def _commands(route: Path, vocab: Path, out: Path) -> dict[str, list[str]]:
    noon, dusk, morning = route / "noon", route / "dusk", route / "morning"
    return {
        "evaluate": [str(TOPOLOC), "evaluate", "--method", "coocmap", "--map", str(noon), "--query", str(dusk),
                     "--vocab", str(vocab), "--tolerance", "0:2", "--out", str(out / "run"), "--quiet"],
        "map build": [str(TOPOLOC), "map", "build", "--method", "fabmap2", "--map", str(noon), "--map",
                      str(morning), "--vocab-train", str(morning), "--vocab-words", "300", "--out",
                      str(out / "route.tlm"), "--quiet"],
        "slam": [str(TOPOLOC), "slam", str(route / "loop"), "--vocab-train", str(morning), "--vocab-words", "300",
                 "--out", str(out / "slam"), "--min-gap", "5", "--quiet"],
    }


def _check_files(out: Path) -> list[str]:
    """Problems with the files a killed run left (empty list: all whole and valid)."""
    from topoloc.errors import TopolocError
    from topoloc.maps import Map

    problems = []
    for f in out.rglob("*"):
        if not f.is_file() or any(part.startswith(".") for part in f.relative_to(out).parts):
            continue  # hidden staging or temporary files are never results
        try:
            if f.suffix == ".json":
                json.loads(f.read_text())
            elif f.suffix == ".npy":
                np.load(f, allow_pickle=False)
            elif f.suffix == ".tlm":
                Map.load(f)
            elif f.suffix == ".csv":
                text = f.read_text()
                rows = list(csv.reader(text.splitlines()))
                if (text and not text.endswith("\n")) or any(len(r) != len(rows[0]) for r in rows):
                    raise ValueError("incomplete line")
        except (ValueError, OSError, TopolocError) as exc:
            problems.append(f"{f.name}: {exc}")
    return problems


def _result(name: str, out: Path, route: Path) -> Any:
    """What a finished run produced, to compare with the reference."""
    if name == "evaluate":
        return np.load(out / "run" / "S.npy")
    if name == "map build":
        from topoloc.maps import Map

        return Map.load(out / "route.tlm").similarity(route / "dusk")
    return (out / "slam" / "loop_closures.csv").read_text()


def _same(a: Any, b: Any) -> bool:
    return bool(np.array_equal(a, b)) if isinstance(a, np.ndarray) else a == b


def main() -> None:
    from topoloc.synth import RouteConfig, generate_route

    rng = np.random.default_rng(SEED)
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        route = work / "route"
        generate_route(route, config=RouteConfig(n_places=16, width=256, height=192, seed=2),
                       tours=[("noon", 12.0), ("dusk", 18.0), ("morning", 9.0)])
        loop = route / "loop"
        loop.mkdir()
        for k, p in enumerate(sorted((route / "noon").glob("*.jpg")) * 2):
            os.link(p, loop / f"{k:05d}.jpg")  # the route driven twice: loop closures in the second lap
        vocab = work / "vocab.tlv"
        subprocess.run([str(TOPOLOC), "vocab", "train", str(route / "morning"), "--words", "300", "--out",
                        str(vocab)], check=True, capture_output=True, env={**os.environ, "TOPOLOC_CACHE_DIR":
                                                                            str(work / "cache")})
        env = {**os.environ, "TOPOLOC_CACHE_DIR": str(work / "cache")}
        for name in ("evaluate", "map build", "slam"):
            ref_dir = work / f"ref_{name.replace(' ', '_')}"
            # Warm the caches once, then time an uninterrupted run.
            subprocess.run(_commands(route, vocab, ref_dir)[name], check=True, capture_output=True, env=env)
            t0 = time.perf_counter()
            subprocess.run(_commands(route, vocab, ref_dir)[name], check=True, capture_output=True, env=env)
            duration = time.perf_counter() - t0
            reference = _result(name, ref_dir, route)
            out = work / f"kill_{name.replace(' ', '_')}"
            subprocess.run(_commands(route, vocab, out)[name], check=True, capture_output=True, env=env)
            for when in np.sort(rng.uniform(0.05, 1.0, KILLS_PER_COMMAND) * duration):
                proc = subprocess.Popen(_commands(route, vocab, out)[name], stdout=subprocess.DEVNULL,
                                        stderr=subprocess.DEVNULL, env=env)
                time.sleep(float(when))
                finished_before = proc.poll() is not None
                if not finished_before:
                    proc.send_signal(signal.SIGKILL)
                proc.wait()
                problems = _check_files(out)
                rerun = subprocess.run(_commands(route, vocab, out)[name], capture_output=True, env=env)
                same = rerun.returncode == 0 and _same(_result(name, out, route), reference)
                rows.append({"command": name, "kill_after_s": round(float(when), 2),
                             "run_s": round(duration, 2), "killed": not finished_before,
                             "files_whole": not problems, "problems": problems, "rerun_same": same})
                print(json.dumps(rows[-1]), flush=True)
    tried = len(rows)
    survived = sum(r["files_whole"] and r["rerun_same"] for r in rows)
    summary = {"machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
               "date": datetime.now(UTC).isoformat(timespec="seconds"), "seed": SEED, "cases": rows,
               "tried": tried, "survived": survived}
    (RESULTS / "reliability.json").write_text(json.dumps(summary, indent=1) + "\n")
    text = [
        "# Reliability: runs killed at random moments\n\n",
        "Generated by `.venv/bin/python -m benchmarks.bench_reliability`; do not edit by hand "
        f"({summary['machine']}, {summary['date']}, seed {SEED}). Raw: [reliability.json](reliability.json).\n\n",
        "Each command runs on a generated 16-place route; it is killed with SIGKILL at a seeded moment "
        "within its uninterrupted duration, the files it left are checked (JSON parses, `.npy` loads, the map "
        "file loads with its checksums, CSV lines are complete; hidden staging files are ignored), then it is "
        "run again and its result compared with an uninterrupted run's.\n\n",
        f"**{survived} of {tried} cases survived** (files whole and rerun identical).\n\n",
        "| command | killed after s | uninterrupted run s | killed before it finished | files whole "
        "| rerun identical |\n",
        "| --- | --- | --- | --- | --- | --- |\n",
    ]
    for r in rows:
        text.append(f"| {r['command']} | {r['kill_after_s']} | {r['run_s']} | {r['killed']} | {r['files_whole']} "
                    f"| {r['rerun_same']} |\n")
    bad = [r for r in rows if r["problems"]]
    if bad:
        text.append("\nProblems found:\n\n"
                    + "".join(f"- {r['command']}: {'; '.join(r['problems'])}\n" for r in bad))
    (RESULTS / "reliability.md").write_text("".join(text))
    print(f"{survived} of {tried} survived; wrote {RESULTS / 'reliability.md'}")


if __name__ == "__main__":
    main()
