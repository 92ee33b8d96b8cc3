"""Regenerate docs/results/daynight.md (+ .json): every method with and without sequence matching, night and winter.

    .venv/bin/python -m benchmarks.bench_daynight [--methods coocmap,bow,...] [--rows gp_night,...] [--keep-runs]

For every (row, method) one ``topoloc evaluate`` run with the method's defaults
(single images, written under docs/results/runs/daynight_<method>_<row>, with its
``S.npy``) gives the *single image* cell; the sequence cells are
:func:`topoloc.evaluation.timing.apply_sequence` of that ``S`` -- the function
``evaluate --sequence N --sequence-mode MODE`` applies to the same ``S`` -- with
``N = 10`` in both modes, scored by :func:`topoloc.evaluation.metrics.compute_metrics`.
``seqslam`` is a sequence search of its own (its row has no ``--sequence``
cells); ``seqslam-single`` is its single-image difference.  Rows (all development
data, ``../shared/data``):

- ``gp_night``: gardens_point day_right -> night_right (tolerance 0:8)
- ``gp_night_left``: gardens_point day_left -> night_right
- ``gp_night_2tours``: gardens_point day_left + day_right -> night_right
- ``nordland``: nordland_64x32 summer -> winter (tolerance 0:2; 64x32 frames hold too
  few keypoints for the keypoint methods, whose cells are n/a)

Vocabulary: webcam_daynight/map for gardens_point (``benchmarks.common.VOCAB_FOR_GP``).
``--keep-runs`` reuses a run folder that already holds ``metrics.json`` and ``S.npy``
(for adding methods to a table); without it every run is made anew.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from benchmarks.common import DATA, PAIRS, RESULTS, compare_sentence, load_anchors, require_data, run
from topoloc.datasets.groundtruth import GroundTruth
from topoloc.evaluation.metrics import compute_metrics
from topoloc.evaluation.timing import apply_sequence

METHODS = ("coocmap", "bow", "fabmap", "fabmap2", "landmarks", "voting", "seqslam", "seqslam-single")
#: Methods that work on 64x32 frames (no keypoints): the others are n/a on nordland.
PIXEL_METHODS = ("seqslam", "seqslam-single")
#: Methods whose own search already matches sequences.
OWN_SEQUENCE = ("seqslam",)
NORD = DATA / "nordland_64x32"
ROWS: dict[str, tuple[list[Path], Path, list[Path], str, str]] = {
    "gp_night": (*PAIRS["gp_night"], "gardens_point day_right -> night_right (tolerance 0:8)"),
    "gp_night_left": ([DATA / "gardens_point" / "day_left"], DATA / "gardens_point" / "night_right",
                      PAIRS["gp_night"][2], "0:8", "gardens_point day_left -> night_right (tolerance 0:8)"),
    "gp_night_2tours": (*PAIRS["gp_night_2tours"], "gardens_point day_left + day_right -> night_right (tolerance 0:8)"),
    "nordland": ([NORD / "summer"], NORD / "winter", [], "0:2", "nordland_64x32 summer -> winter (tolerance 0:2)"),
}
#: Column of benchmarks/anchors.json for a single-tour gardens_point row.
ANCHOR_COLUMN = {"gp_night": "day_right -> night_right", "gp_night_left": "day_left -> night_right"}
LENGTH = 10
VARIANTS = (("single", 0, ""), ("constant", LENGTH, "constant"), ("acceleration", LENGTH, "acceleration"))
KEYS = ("auc", "recall_at_100_precision", "recall_at_1")


def run_dir(method: str, row: str) -> Path:
    return RESULTS / "runs" / f"daynight_{method}_{row}"


def single_image_run(method: str, row: str, *, keep: bool = False) -> Path:
    """The run of ``method`` on ``row`` (single images, the method's defaults), made unless ``keep`` finds it."""
    maps, query, vocab, tol, _ = ROWS[row]
    d = run_dir(method, row)
    if keep and (d / "metrics.json").is_file() and (d / "S.npy").is_file():
        return d
    return run(method, maps, query, d, vocab_train=vocab, tolerance=tol)


def load_run(d: Path) -> tuple[np.ndarray, GroundTruth]:
    """The run's ``S`` and ground truth."""
    return np.load(d / "S.npy"), GroundTruth(np.load(d / "gt_hard.npy"), np.load(d / "gt_soft.npy"))


def _scores(S: np.ndarray, gt: GroundTruth) -> dict[str, float]:
    m = compute_metrics(S, gt)
    return {"auc": m.auc, "recall_at_100_precision": m.recall_at_100_precision, "recall_at_1": m.recall_at_1}


def measure(methods: list[str], rows: list[str], *, keep: bool) -> dict[str, dict[str, dict[str, dict[str, float]]]]:
    """``{row: {method: {variant: {metric: value}}}}``; a variant that does not apply is absent."""
    out: dict[str, dict[str, dict[str, dict[str, float]]]] = {}
    for row in rows:
        for method in methods:
            if row == "nordland" and method not in PIXEL_METHODS:
                continue
            d = single_image_run(method, row, keep=keep)
            S, gt = load_run(d)
            cell: dict[str, dict[str, float]] = {}
            for name, n, mode in VARIANTS:
                if n and method in OWN_SEQUENCE:
                    continue
                cell[name] = _scores(apply_sequence(S, n, mode)[0] if n else S, gt)
            stored = json.loads((d / "metrics.json").read_text())
            assert abs(cell["single"]["auc"] - stored["auc"]) < 1e-9, "single-image metrics differ from the run's own"
            out.setdefault(row, {})[method] = cell
    return out


def _cell(v: dict[str, float] | None) -> str:
    return "n/a" if v is None else f"{v['auc']:.3f} / {v['recall_at_100_precision']:.2f} / {v['recall_at_1']:.2f}"


def _values(v: dict[str, float]) -> tuple[float, ...]:
    return tuple(float(v[k]) for k in KEYS)


def _anchor_rows(row: str) -> list[tuple[str, tuple[float | None, ...]]]:
    """(system, (AUC, R@100P, R@1)) of every anchor on ``row``'s frames (single-tour gardens_point rows)."""
    a = load_anchors()
    if row not in ANCHOR_COLUMN:
        return []
    k = a["columns"].index(ANCHOR_COLUMN[row])
    out: list[tuple[str, tuple[float | None, ...]]] = []
    for r in a["rows"]:
        auc, r1 = r["auc_r1"][k]
        r100p = (r.get("r100p") or [None] * len(a["columns"]))[k]
        if (auc, r100p, r1) != (None, None, None):  # a system no source gives a number for on these frames
            out.append((r["name"], (auc, r100p, r1)))
    return out


def _where_it_loses(row: str, methods: dict[str, dict[str, dict[str, float]]]) -> list[str]:
    """Sentences from the numbers: each method with sequence matching against without, and the best of the row."""
    lines = []
    for method, cells in methods.items():
        for name in ("constant", "acceleration"):
            if name in cells:
                lines.append("- " + compare_sentence(f"`{method} --sequence {LENGTH} --sequence-mode {name}`",
                                                     f"`{method}` on single images", "these frames",
                                                     _values(cells[name]), _values(cells["single"])) + "\n")
    flat = [(f"`{m}`" + ("" if v == "single" else f" with `--sequence {LENGTH} --sequence-mode {v}`"), cell)
            for m, cells in methods.items() for v, cell in cells.items()]
    if flat:
        who, best = max(flat, key=lambda t: (t[1]["recall_at_100_precision"], t[1]["auc"]))
        lines.append(f"- The highest R@100P on this row (ties: the higher AUC) is {who}'s: "
                     f"AUC / R@100P / R@1 {_cell(best)}.\n")
        for system, theirs in _anchor_rows(row):
            lines.append("- " + compare_sentence(who, system, "these frames", _values(best), theirs, digits=2) + "\n")
    return lines


def render(results: dict[str, dict[str, dict[str, dict[str, float]]]]) -> str:
    lines = [
        "# Day -> night and summer -> winter along a route, with and without sequence matching\n\n",
        "Generated by `.venv/bin/python -m benchmarks.bench_daynight`; do not edit by hand. ",
        "Every cell is AUC / R@100P / R@1. `single` is one `topoloc evaluate` run with the method's defaults "
        f"(single images); `constant` and `acceleration` are `--sequence {LENGTH} --sequence-mode ...` applied to "
        "that run's `S` by the function `evaluate` uses (`topoloc.evaluation.timing.apply_sequence`, with the "
        "sequence confidence of `topoloc.sequence.confidence`: the margin of the best path over the best path "
        "outside its stretch of the route). `seqslam` matches sequences itself (no `--sequence` cells); "
        "`seqslam-single` is its single-image difference. n/a: keypoint methods on nordland_64x32 (64x32 "
        "frames, too few keypoints). Vocabulary for gardens_point: webcam_daynight/map. All rows are the "
        "development split (`../shared/data`), the data the sequence confidence and the stream default were "
        "chosen on. The single-tour gardens_point rows list the SeqSLAM and openFABMAP anchors quoted in "
        "`benchmarks/anchors.json` (not measured here; '-' where no source gives a number).\n\n",
    ]
    for row, methods in results.items():
        lines += [f"## {row}: {ROWS[row][4]}\n\n",
                  "| method | single | constant | acceleration |\n| --- | --- | --- | --- |\n"]
        for method, cells in methods.items():
            lines.append(f"| {method} | {_cell(cells.get('single'))} | {_cell(cells.get('constant'))} | "
                         f"{_cell(cells.get('acceleration'))} |\n")
        for system, (auc, r100p, r1) in _anchor_rows(row):
            def f(x: float | None) -> str:
                return "-" if x is None else f"{x:.2f}"
            lines.append(f"| anchor: {system} | {f(auc)} / {f(r100p)} / {f(r1)} | | |\n")
        lines += ["\n### Where each loses (written from the numbers above)\n\n", *_where_it_loses(row, methods), "\n"]
    return "".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--methods", default=",".join(METHODS), help="comma-separated methods")
    ap.add_argument("--rows", default=",".join(ROWS), help=f"comma-separated rows of {', '.join(ROWS)}")
    ap.add_argument("--keep-runs", action="store_true", help="reuse run folders that hold metrics.json and S.npy")
    ap.add_argument("--render", action="store_true", help="only rewrite daynight.md from daynight.json")
    args = ap.parse_args()
    stored = RESULTS / "daynight.json"
    if not args.render:
        require_data()
        rows = [r.strip() for r in args.rows.split(",") if r.strip()]
        bad = [r for r in rows if r not in ROWS]
        if bad:
            raise SystemExit(f"unknown rows {bad}: choose from {', '.join(ROWS)}")
        methods = [m.strip() for m in args.methods.split(",") if m.strip()]
        results = measure(methods, rows, keep=args.keep_runs)
        # Cells measured now replace those of an earlier call; the others are kept, in the order of METHODS.
        earlier = json.loads(stored.read_text()) if stored.is_file() else {}
        merged = {row: {**earlier.get(row, {}), **results.get(row, {})} for row in ROWS}
        order = {m: k for k, m in enumerate(METHODS)}
        stored.write_text(json.dumps({row: {m: cells[m] for m in sorted(cells, key=lambda m: order.get(m, 99))}
                                      for row, cells in merged.items() if cells}, indent=1) + "\n")
    (RESULTS / "daynight.md").write_text(render(json.loads(stored.read_text())))
    print(f"wrote {RESULTS / 'daynight.md'}")


if __name__ == "__main__":
    main()
