"""Regenerate docs/results/verification.md (+ .json, verification_pr.png): every method with and without verification.

    .venv/bin/python -m benchmarks.bench_verification [--parts quality,knobs,consistency,slam,speed,localize]
        [--rows gp_day,...] [--methods coocmap,...] [--runs DIR]

Parts (development data, ``../shared/data``; every setting a default, XFeat features):

- ``quality``: one ``topoloc evaluate --no-verify --features xfeat`` run per (row,
  method), then the verification stage of ``evaluate`` (:func:`topoloc.spec.setup.build_verifier`,
  with the default :class:`~topoloc.spec.VerificationSpec`) applied to its ``S``
  (or to :func:`~topoloc.evaluation.timing.apply_sequence` of it for the
  ``--sequence 10`` row): AUC, R@100P, R@1 without and with, the fraction of
  queries verified and the stage's ms per query.  For Cooc-Map on the day and
  the night-sequence rows the same run is also made with ``topoloc evaluate
  --verify`` and its ``S`` compared with the benchmark's (``cli_equal``).
  Rows: gardens_point day_left -> day_right (tolerance 0:8), day_left + day_right
  -> night_right single images and ``--sequence 10``, and the webcams (12 map
  tours -> queries, 0:0; Cooc-Map, bag of words and FAB-MAP 2.0 only, as in
  ``learned_features.md``).  SeqSLAM matches sequences itself: no sequence row,
  no webcam row (its queries are not a sequence).
- ``knobs``: RANSAC iterations per candidate (1,000 the default, 2,000 and 500) for Cooc-Map on the
  day, night and webcam rows: quality and the stage's ms per query.
- ``consistency``: temporal consistency (DLoopDetector's, Sec. VI-B): a frame's
  verified answer counts as confirmed when the previous frame's answer lies within
  its peak; the confidence of an unconfirmed answer drops below every confirmed
  one.  Measured on the gardens_point rows (the webcam queries are not a stream).
- ``slam``: ``topoloc slam rtabmap_loop`` (online FAB-MAP, its default SIFT features, the
  vocabulary trained on the webcams) with ``--verify`` and ``--no-verify``: loop
  closures accepted and rejected by verification.  rtabmap_loop has no ground truth:
  the route is walked twice (frames ~1-45 revisited by ~46-84), so a closure of image
  k with image j is counted *on the route* when j is within 12 of k - 45 or the walk's
  end meets its start (k >= 80, j <= 8).
- ``speed``: the stage alone on 640 px gardens_point day frames (Cooc-Map's ``S``):
  ms per frame, quiet and beside 3 busy processes, paced at 10 Hz
  (``benchmarks.bench_load``'s ``busy`` and ``paced``).
- ``localize``: ``topoloc map build --method coocmap`` of day_left, then ``topoloc
  localize`` of the 100 day_right frames with ``--verify`` and ``--no-verify``:
  frames/s end to end with prefetch and ms per stage, quiet and beside 3 busy processes.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import tempfile
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_load import busy, paced
from benchmarks.common import GP, RESULTS, TOPOLOC, WEBCAM, WEBCAM_TOURS, machine_line, require_data, run
from topoloc.datasets.groundtruth import GroundTruth
from topoloc.datasets.traverse import load_traverse
from topoloc.evaluation.metrics import compute_metrics
from topoloc.evaluation.timing import apply_sequence
from topoloc.spec import FeatureSpec, VerificationSpec
from topoloc.spec.setup import build_verifier, make_resources
from topoloc.verification import Verifier, confirmed, demote_unconfirmed

FEATURES = "xfeat"
SEQUENCE = 10
METHODS = ("coocmap", "bow", "fabmap2", "fabmap", "landmarks", "voting", "seqslam")
WEBCAM_METHODS = ("coocmap", "bow", "fabmap2")
#: row -> (map tours, query, tolerance, sequence, description)
ROWS: dict[str, tuple[list[Path], Path, str, int, str]] = {
    "gp_day": ([GP / "day_left"], GP / "day_right", "0:8", 0, "gardens_point day_left -> day_right"),
    "gp_night": ([GP / "day_left", GP / "day_right"], GP / "night_right", "0:8", 0,
                 "gardens_point day_left + day_right -> night_right, single images"),
    "gp_night_seq10": ([GP / "day_left", GP / "day_right"], GP / "night_right", "0:8", SEQUENCE,
                       "gardens_point day_left + day_right -> night_right, --sequence 10"),
    "webcam": (WEBCAM_TOURS, WEBCAM / "queries", "0:0", 0, "webcam_daynight 12 map tours -> queries"),
}
CLI_CHECKS = (("coocmap", "gp_day"), ("coocmap", "gp_night_seq10"))
OUT_MD = RESULTS / "verification.md"
OUT_JSON = RESULTS / "verification.json"
OUT_PNG = RESULTS / "verification_pr.png"


def _scores(S: np.ndarray, gt: GroundTruth) -> dict[str, Any]:
    m = compute_metrics(S, gt)
    return {"auc": round(float(m.auc), 3), "r100p": round(float(m.recall_at_100_precision), 2),
            "r1": round(float(m.recall_at_k[1]), 3), "precision": m.precision.tolist(), "recall": m.recall.tolist()}


def methods_of(row: str) -> tuple[str, ...]:
    if row == "webcam":
        return WEBCAM_METHODS
    if ROWS[row][3]:
        return tuple(m for m in METHODS if m != "seqslam")
    return METHODS


def _base_run(method: str, row: str, runs: Path) -> Path:
    maps, query, tol, _, _ = ROWS[row]
    # The sequence row verifies the sequence S of the single-image run of the same frames.
    folder = runs / f"{method}_{'gp_night' if row == 'gp_night_seq10' else row}"
    if not (folder / "metrics.json").is_file():
        run(method, maps, query, folder, vocab_train=[], tolerance=tol,
            options=["--features", FEATURES, "--no-verify"])
    return folder


def _verifier(row: str, place_ids: np.ndarray) -> tuple[Verifier, list[Any]]:
    maps, query, _, seq, _ = ROWS[row]
    res, _ = make_resources(FeatureSpec(method=FEATURES).config(), None)
    tours = [load_traverse(m) for m in maps]
    # As evaluate builds it: the sequence row verifies each frame's best place only.
    v = build_verifier(VerificationSpec(enabled=True), place_ids, tours, res, sequence=seq)
    assert v is not None
    return v, res.features(load_traverse(query))


def quality(rows: Sequence[str], methods: Sequence[str], runs: Path) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for row in rows:
        for method in methods_of(row):
            if method not in methods:
                continue
            d = _base_run(method, row, runs)
            S = np.load(d / "S.npy")
            if ROWS[row][3]:
                S = apply_sequence(S, ROWS[row][3])[0].astype(np.float32)
            gt = GroundTruth(np.load(d / "gt_hard.npy"), np.load(d / "gt_soft.npy"))
            v, qf = _verifier(row, np.load(d / "places.npy"))
            block = v.verify(S, qf)
            cell = {"without": _scores(S, gt), "with": _scores(block.S, gt),
                    "verified_fraction": round(float(block.verified.mean()), 3),
                    "ms_median": round(float(np.median(block.ms)), 2),
                    "ms_p95": round(float(np.percentile(block.ms, 95)), 2),
                    "ms_method": round(float(json.loads((d / "metrics.json").read_text())["ms_per_query"]), 2)}
            if (method, row) in CLI_CHECKS:
                cell["cli_equal"] = _cli_check(method, row, runs, block.S)
            out.setdefault(row, {})[method] = cell
            print(f"{row} {method}: without {cell['without']['r100p']} / {cell['without']['r1']}  with "
                  f"{cell['with']['r100p']} / {cell['with']['r1']}  {cell['ms_median']} ms", flush=True)
    return out


def _cli_check(method: str, row: str, runs: Path, S_bench: np.ndarray) -> bool:
    """``topoloc evaluate --verify`` of the same row gives the benchmark's verified S."""
    maps, query, tol, seq, _ = ROWS[row]
    d = run(method, maps, query, runs / f"cli_{method}_{row}", vocab_train=[], tolerance=tol, sequence=seq,
            options=["--features", FEATURES, "--verify"])
    return bool(np.allclose(np.load(d / "S.npy"), S_bench, rtol=0, atol=1e-6))


KNOB_ITERS = (500, 1000, 2000)


def knobs(rows: Sequence[str], runs: Path) -> dict[str, Any]:
    """Cooc-Map's verified quality and stage time by the RANSAC iterations allowed per candidate."""
    out: dict[str, Any] = {}
    for row in rows:
        if row == "gp_night_seq10":
            continue
        d = _base_run("coocmap", row, runs)
        S = np.load(d / "S.npy")
        gt = GroundTruth(np.load(d / "gt_hard.npy"), np.load(d / "gt_soft.npy"))
        v, qf = _verifier(row, np.load(d / "places.npy"))
        v.verify(S[:, :3], qf[:3])  # the map tours' features read once
        for iters in KNOB_ITERS:
            v.max_iters = iters
            block = v.verify(S, qf)
            sc = _scores(block.S, gt)
            out.setdefault(row, {})[str(iters)] = {k: sc[k] for k in ("auc", "r100p", "r1")} | {
                "ms_median": round(float(np.median(block.ms)), 2)}
    return out


def consistency(rows: Sequence[str], runs: Path) -> dict[str, Any]:
    """Temporal consistency on top of verification: unconfirmed answers below every confirmed one."""
    out: dict[str, Any] = {}
    for row in rows:
        if row == "webcam":
            continue
        for method in ("coocmap", "bow", "landmarks"):
            d = _base_run(method, row, runs)
            S = np.load(d / "S.npy")
            if ROWS[row][3]:
                S = apply_sequence(S, ROWS[row][3])[0].astype(np.float32)
            gt = GroundTruth(np.load(d / "gt_hard.npy"), np.load(d / "gt_soft.npy"))
            v, qf = _verifier(row, np.load(d / "places.npy"))
            Sv = v.verify(S, qf).S
            ok = confirmed(Sv)
            Sc = demote_unconfirmed(Sv, ok)
            out.setdefault(row, {})[method] = {"verified": _scores(Sv, gt), "verified_and_confirmed": _scores(Sc, gt),
                                               "confirmed_fraction": round(float(ok.mean()), 3)}
    return out


def slam(tmp: Path) -> dict[str, Any]:
    import csv

    from benchmarks.common import DATA

    out: dict[str, Any] = {}
    for flag in ("--no-verify", "--verify"):
        d = tmp / f"slam{flag}"
        subprocess.run([str(TOPOLOC), "slam", "-q", str(DATA / "rtabmap_loop"), "--out", str(d), "--vocab-train",
                        str(WEBCAM / "map"), flag], check=True, stdout=subprocess.DEVNULL)
        with (d / "loop_closures.csv").open() as fh:
            rows = list(csv.DictReader(fh))
        on_route = sum(1 for r in rows if abs(int(r["matched_image"]) - (int(r["image"]) - 45)) <= 12
                       or (int(r["image"]) >= 80 and int(r["matched_image"]) <= 8))
        params = json.loads((d / "slam.json").read_text())["params"]
        out[flag.strip("-").replace("-", "_")] = {
            "closures": len(rows), "on_route": on_route,
            "rejected": len(params.get("rejected_by_verification", [])),
            "places": json.loads((d / "slam.json").read_text()).get("n_places")}
    return out


def speed(runs: Path) -> dict[str, Any]:
    d = _base_run("coocmap", "gp_day", runs)
    S = np.load(d / "S.npy")
    v, qf = _verifier("gp_day", np.load(d / "places.npy"))
    v.verify(S[:, :5], qf[:5])  # the map tour's features read once, as a localiser's first frame does

    def one(j: int) -> None:
        v.verify(S[:, j:j + 1], qf[j:j + 1])

    out: dict[str, Any] = {"frame": list(qf[0].image_shape), "keypoints_median": int(np.median([len(f) for f in qf]))}
    for n_busy in (0, 3):
        with busy(n_busy):
            t = paced(one, list(range(S.shape[1])), 10.0)
        out[f"busy{n_busy}"] = {"median_ms": round(float(np.median(t)), 2),
                                "p95_ms": round(float(np.percentile(t, 95)), 2)}
    out["ratio_median"] = round(out["busy3"]["median_ms"] / out["busy0"]["median_ms"], 2)
    out["ratio_p95"] = round(out["busy3"]["p95_ms"] / out["busy0"]["p95_ms"], 2)
    return out


def localize(tmp: Path) -> dict[str, Any]:
    tlm = tmp / "gp.tlm"
    subprocess.run([str(TOPOLOC), "map", "build", "-q", "--method", "coocmap", "--map", str(GP / "day_left"),
                    "--features", FEATURES, "--out", str(tlm)], check=True, stdout=subprocess.DEVNULL)
    # One run first, untimed: Cooc-Map's compiled matcher is built (and cached) by the first process that uses it.
    subprocess.run([str(TOPOLOC), "localize", "-q", str(tlm), str(GP / "day_right"), "--verify", "--out",
                    str(tmp / "warm.jsonl")], check=True, capture_output=True)
    out: dict[str, Any] = {}
    for n_busy in (0, 3):
        for flag in ("--no-verify", "--verify"):
            with busy(n_busy):
                r = subprocess.run([str(TOPOLOC), "localize", "-q", str(tlm), str(GP / "day_right"), flag,
                                    "--out", str(tmp / "loc.jsonl")], check=True, capture_output=True, text=True)
            summary = json.loads(r.stdout.strip().splitlines()[-1])
            out[f"busy{n_busy}{flag.replace('--', '_').replace('-', '_')}"] = {
                k: summary.get(k) for k in ("fps", "ms_features_mean", "ms_matching_mean", "ms_verify_mean",
                                            "verified", "ms_cpu_mean")}
    return out


def _thin_curves(part: dict[str, Any], points: int = 200) -> None:
    """PR curves kept at most ``points`` points each (thousands per webcam cell), enough to draw them again."""
    for cells in part.values():
        for cell in cells.values():
            for scores in cell.values():
                if isinstance(scores, dict) and "recall" in scores:
                    n = len(scores["recall"])
                    keep = np.unique(np.linspace(0, n - 1, min(n, points)).round().astype(int)) if n else []
                    for key in ("precision", "recall"):
                        scores[key] = [round(float(scores[key][i]), 4) for i in keep]


# --------------------------------------------------------------------------------------------- page
def _cell(c: dict[str, Any]) -> str:
    return f"{c['auc']:.3f} / {c['r100p']:.2f} / {c['r1']:.2f}"


def pr_figure(q: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in ROWS if r in q]
    fig, axes = plt.subplots(1, len(rows), figsize=(4.2 * len(rows), 4), squeeze=False)
    for ax, row in zip(axes[0], rows, strict=True):
        for k, (method, cell) in enumerate(q[row].items()):
            color = f"C{k}"
            ax.plot(cell["without"]["recall"], cell["without"]["precision"], "--", color=color, lw=1)
            ax.plot(cell["with"]["recall"], cell["with"]["precision"], "-", color=color, lw=1.5, label=method)
        ax.set_title(row, fontsize=10)
        ax.set_xlabel("recall")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("precision")
    axes[0][0].legend(fontsize=8, loc="lower left")
    fig.suptitle("with verification (solid) and without (dashed), XFeat, default settings", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def render(res: dict[str, Any]) -> str:
    lines = [
        "# Verified answers: every method with and without geometric verification",
        "",
        "Written by `.venv/bin/python -m benchmarks.bench_verification` (issue 40); do not edit by hand.",
        f"Measured {res['date']} on {res['machine']}.",
        "",
        "Verification (`--verify`, `docs/protocol.md`, \"Verification\") re-checks the best places of each "
        "query's three highest distinct peaks by mutual nearest-neighbour matches of XFeat features and a "
        "fundamental matrix fitted with USAC MAGSAC++ (tolerance 0.15% of the image diagonal), and ranks a "
        "verified answer by its inliers above every unverified one.  Every setting is a default and the "
        "features are XFeat (the default); the data are the development split (`../shared/data`), on which "
        "the defaults were chosen: three candidates (part `quality`), verification on by default.",
        "",
    ]
    q = res.get("quality")
    if q:
        lines += ["## Quality (AUC / R@100P / R@1)", "",
                  "| row | method | without verification | with verification | verified | stage ms/query (median, p95) "
                  "| method ms/query |", "| --- | --- | --- | --- | --- | --- | --- |"]
        for row, cells in q.items():
            for method, c in cells.items():
                lines.append(f"| {row} | {method} | {_cell(c['without'])} | {_cell(c['with'])} | "
                             f"{c['verified_fraction']:.0%} | {c['ms_median']:.1f}, {c['ms_p95']:.1f} | "
                             f"{c['ms_method']:.1f} |")
        lines += ["", "Rows: " + "; ".join(f"`{r}` {ROWS[r][4]}" for r in q) + ".", ""]
        checks = [f"{m} {r}: {'equal' if q[r][m].get('cli_equal') else 'DIFFERENT'}"
                  for m, r in CLI_CHECKS if r in q and m in q[r] and "cli_equal" in q[r][m]]
        if checks:
            lines += ["`topoloc evaluate --verify` against this benchmark's verified S: " + ", ".join(checks) + ".",
                      ""]
        lines += ["Stage times above were taken while the rest of the benchmark ran (load: see `speed` for the "
                  "stage timed on its own).", "", "![PR curves](verification_pr.png)", ""]
    kn = res.get("knobs")
    if kn:
        lines += ["## RANSAC iterations per candidate (Cooc-Map; AUC / R@100P / R@1, stage ms/query median)", "",
                  "| row | " + " | ".join(f"{i} iterations" for i in KNOB_ITERS) + " |",
                  "| --- |" + " --- |" * len(KNOB_ITERS)]
        for row, cells in kn.items():
            lines.append(f"| {row} | " + " | ".join(
                f"{_cell(cells[str(i)])}, {cells[str(i)]['ms_median']:.1f} ms" for i in KNOB_ITERS) + " |")
        lines += ["", "Measured one after the other in one process (the rest of the benchmark was not running).", ""]
    c = res.get("consistency")
    if c:
        lines += ["## Temporal consistency (AUC / R@100P / R@1)", "",
                  "An answer is *confirmed* when the previous frame's answer lies within its peak "
                  "(DLoopDetector's temporal consistency with one frame); unconfirmed answers rank below "
                  "every confirmed one.", "",
                  "| row | method | verified | verified and confirmed | confirmed |", "| --- | --- | --- | --- | --- |"]
        for row, cells in c.items():
            for method, x in cells.items():
                lines.append(f"| {row} | {method} | {_cell(x['verified'])} | {_cell(x['verified_and_confirmed'])} | "
                             f"{x['confirmed_fraction']:.0%} |")
        lines.append("")
    s = res.get("speed")
    if s:
        lines += ["## Speed of the stage", "",
                  f"Cooc-Map's S of gardens_point day_left -> day_right, frames {s['frame'][1]} x {s['frame'][0]}, "
                  f"median {s['keypoints_median']} XFeat keypoints; one frame verified per period at 10 Hz.", "",
                  "| load | median ms | p95 ms |", "| --- | --- | --- |",
                  f"| quiet | {s['busy0']['median_ms']} | {s['busy0']['p95_ms']} |",
                  f"| 3 busy processes | {s['busy3']['median_ms']} | {s['busy3']['p95_ms']} |", "",
                  f"Beside 3 busy processes: {s['ratio_median']}x the quiet median, {s['ratio_p95']}x the p95.", ""]
    sl = res.get("slam")
    if sl:
        lines += ["## `topoloc slam` (online FAB-MAP) on rtabmap_loop", "",
                  "| verification | loop closures | on the route | rejected by verification | places |",
                  "| --- | --- | --- | --- | --- |"]
        for key, x in sl.items():
            lines.append(f"| {key.replace('_', '-')} | {x['closures']} | {x['on_route']} | {x['rejected']} | "
                         f"{x['places']} |")
        lines.append("")
    loc = res.get("localize")
    if loc:
        lines += ["## `topoloc localize` end to end", "",
                  "Cooc-Map map of day_left, the 100 day_right frames, prefetch on (default).", "",
                  "| load | verification | frames/s | ms features | ms matching | ms verify | verified | ms CPU |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        for key, x in loc.items():
            load = "quiet" if key.startswith("busy0") else "3 busy"
            lines.append(f"| {load} | {'off' if key.endswith('_no_verify') else 'on'} | {x['fps']} | "
                         f"{x['ms_features_mean']} | {x['ms_matching_mean']} | {x.get('ms_verify_mean') or '-'} | "
                         f"{x.get('verified') if x.get('verified') is not None else '-'} | {x['ms_cpu_mean']} |")
        lines.append("")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--parts", default="quality,knobs,consistency,slam,speed,localize")
    ap.add_argument("--rows", default=",".join(ROWS))
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--runs", type=Path, default=None, help="Keep (and reuse) the evaluate runs here.")
    args = ap.parse_args(argv)
    parts = args.parts.split(",")
    rows = args.rows.split(",")
    known = {"quality", "knobs", "consistency", "slam", "speed", "localize"}
    unknown = sorted(set(rows) - set(ROWS)) + sorted(set(parts) - known)
    if unknown:
        raise SystemExit(f"unknown part or row: {', '.join(unknown)}")
    require_data()
    RESULTS.mkdir(parents=True, exist_ok=True)
    old = json.loads(OUT_JSON.read_text()) if OUT_JSON.is_file() else {}
    res: dict[str, Any] = {**old, "date": datetime.now(UTC).isoformat(timespec="seconds"), "machine": machine_line()}
    tmp = Path(tempfile.mkdtemp(prefix="bench_verification_"))
    runs = args.runs or tmp
    runs.mkdir(parents=True, exist_ok=True)
    os.environ["TOPOLOC_FEATURES"] = FEATURES
    try:
        t0 = time.perf_counter()
        if "quality" in parts:
            fresh = quality(rows, args.methods.split(","), runs)
            _thin_curves(fresh)
            # Rows not run this time keep their last measurement; the figure needs every row's curves.
            res["quality"] = {r: {**old.get("quality", {}).get(r, {}), **fresh.get(r, {})}
                              for r in ROWS if r in fresh or r in old.get("quality", {})}
            pr_figure(res["quality"], OUT_PNG)
        if "knobs" in parts:
            res["knobs"] = knobs(rows, runs)
        if "consistency" in parts:
            fresh = consistency(rows, runs)
            _thin_curves(fresh)
            res["consistency"] = {**old.get("consistency", {}), **fresh}
        if "slam" in parts:
            res["slam"] = slam(tmp)
        if "speed" in parts:
            res["speed"] = speed(runs)
        if "localize" in parts:
            res["localize"] = localize(tmp)
        res["seconds"] = round(time.perf_counter() - t0, 1)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    OUT_JSON.write_text(json.dumps(res, indent=1) + "\n")
    OUT_MD.write_text(render(res) + "\n")
    print(f"wrote {OUT_MD}, {OUT_JSON}")


if __name__ == "__main__":
    main()
