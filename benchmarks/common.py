"""Shared helpers of the benchmark scripts: where the data is, running evaluate, tables."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from topoloc.evaluation.report import build_report

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("TOPOLOC_DATA", REPO.parent / "shared" / "data")).resolve()
RESULTS = REPO / "docs" / "results"
TOPOLOC = Path(sys.executable).parent / "topoloc"
GP = DATA / "gardens_point"
WEBCAM = DATA / "webcam_daynight"
WEBCAM_TOURS = sorted((WEBCAM / "map").glob("tour_*"))

# The papers train their vocabularies on images apart from the evaluation data:
# gardens_point runs use a vocabulary trained on webcam_daynight's map tours and
# webcam_daynight runs one trained on all three gardens_point traverses.
VOCAB_FOR_GP = [WEBCAM / "map"]
VOCAB_FOR_WEBCAM = [GP]

GP_PAIRS = [("day_left", "day_right"), ("day_right", "night_right"), ("day_left", "night_right")]


def require_data() -> None:
    if not GP.is_dir() or not WEBCAM.is_dir():
        raise SystemExit(f"shared data not found under {DATA} (set TOPOLOC_DATA)")


def run(method: str, maps: list[Path], query: Path, out: Path, *, vocab_train: list[Path],
        tolerance: str, params: dict[str, str] | None = None, sequence: int = 0,
        ground_truth: Path | None = None, options: list[str] | None = None) -> Path:
    """One `topoloc evaluate` run in its own process (so peak memory is per run); returns its folder.

    ``options`` are further `topoloc evaluate` arguments (e.g. ``["--preprocess", "clahe"]``).
    """
    cmd = [str(TOPOLOC), "evaluate", "--method", method, "--query", str(query), "--out", str(out),
           "--tolerance", tolerance, "--quiet"]
    for m in maps:
        cmd += ["--map", str(m)]
    for v in vocab_train:
        cmd += ["--vocab-train", str(v)]
    for k, v in (params or {}).items():
        cmd += ["--param", f"{k}={v}"]
    if sequence:
        cmd += ["--sequence", str(sequence)]
    if ground_truth is not None:
        cmd += ["--ground-truth", str(ground_truth)]
    cmd += options or []
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    m = json.loads((out / "metrics.json").read_text())
    print(f"{out.name}: AUC {m['auc']:.3f} R@1 {m['recall_at_1']:.3f} ms/q {m['ms_per_query']:.2f}", flush=True)
    return out


def anchors_table() -> str:
    a = json.loads((REPO / "benchmarks" / "anchors.json").read_text())
    lines = ["| system | " + " | ".join(f"{c} AUC / R@1" for c in a["columns"]) + " |\n",
             "| --- |" + " --- |" * len(a["columns"]) + "\n"]
    for row in a["rows"]:
        cells = " | ".join(f"{auc:g} / {r1:g}" for auc, r1 in row["auc_r1"])
        lines.append(f"| {row['system']} | {cells} |\n")
    return f"{a['source']}\n\n" + "".join(lines)


def report(run_dirs: list[Path], out: Path, title: str) -> Path:
    return build_report(run_dirs, out, title=title)


def report_table(run_dirs: list[Path], out: Path, title: str) -> str:
    """Write the side-by-side report of ``run_dirs`` under ``out``; return just its markdown table."""
    return report(run_dirs, out, title).read_text().split("\n", 2)[2].split("\nRuns:")[0]


def gardens_section(run_dirs: list[Path], name: str, title: str) -> str:
    """Table of gardens_point runs, their PR-curve PNG (under ``docs/results/<name>``) and the anchors."""
    return (report_table(run_dirs, RESULTS / name, title) + f"\n![PR curves]({name}/pr_curves.png)\n\n"
            + "### Anchors on the same data\n\n" + anchors_table())
