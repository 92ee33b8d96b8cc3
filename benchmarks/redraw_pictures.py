"""Redraw the pictures of docs/results from the stored runs, without running any method again.

    .venv/bin/python -m benchmarks.redraw_pictures

Each ``docs/results/runs/*/pr.png`` is drawn again from its ``pr.csv`` and
``metrics.json`` (as ``topoloc evaluate`` draws it), and each side-by-side
report folder ``docs/results/*/`` whose ``report.md`` lists its runs is
written again by ``topoloc report`` (``report.md`` and ``pr_curves.png``) with
the same title.  Use it after a change to how pictures or reports are drawn.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from topoloc.evaluation.plots import plot_pr_curves
from topoloc.evaluation.report import build_report, load_run, run_title

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"


def redraw_run(run: Path) -> None:
    m, precision, recall = load_run(run)
    plot_pr_curves([(f"{m['method']} (AUC {m['auc']:.2f})", precision, recall)], run / "pr.png",
                   title=run_title(m))


def redraw_report(folder: Path) -> bool:
    text = (folder / "report.md").read_text()
    title = text.splitlines()[0].removeprefix("# ").strip()
    runs = re.search(r"^Runs: (.*)$", text, re.M)
    if runs is None:
        return False
    dirs = [Path(d) for d in re.findall(r"`([^`]+)`", runs.group(1))]
    # Reports written on another machine name the runs by its paths: find them under docs/results/runs.
    dirs = [d if d.is_dir() else RESULTS / "runs" / d.name for d in dirs]
    if not all((d / "metrics.json").is_file() for d in dirs):
        return False
    build_report(dirs, folder, title=title)
    return True


def main() -> None:
    runs = sorted(p.parent for p in (RESULTS / "runs").glob("*/pr.csv"))
    for run in runs:
        redraw_run(run)
    folders = sorted(p.parent for p in RESULTS.glob("*/report.md") if p.parent.name != "runs")
    done = [f.name for f in folders if redraw_report(f)]
    print(json.dumps({"runs": len(runs), "reports": done}))


if __name__ == "__main__":
    main()
