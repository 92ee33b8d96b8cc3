"""SeqSLAM speed and accuracy: writes docs/results/seqslam_speed.json.

    .venv/bin/python -m benchmarks.bench_seqslam [--quick]

(a) nordland_64x32 summer -> winter, all 1,788 frames, tolerance 0:2, default
    parameters: AUC and R@1 with the metrics of PROTOCOL.md, and milliseconds
    per query for the difference matrix + contrast enhancement + sequence
    search (the whole of ``SeqSLAM.score``; median over repeated runs divided by
    the number of queries), with the three stages timed on their own too.
    Variants: OpenSeqSLAM's coarse quantisation, the acceleration-tolerant
    search (Cooc-Map II-F), and the single-image baseline.
(b) a synthetic 10,000 x 10,000 difference matrix (a route along the diagonal
    in noise): contrast enhancement, constant-velocity search and acceleration
    search, each timed on its own.
(c) gardens_point (100 frames, tolerance 0:8), defaults and without contrast
    enhancement, for reference.

Image preprocessing (reading, downsampling, patch normalisation) is feature
extraction in the protocol and is reported separately as ``ms_features``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import time
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from benchmarks.common import DATA, RESULTS
from topoloc.datasets.groundtruth import ground_truth_from_places
from topoloc.datasets.traverse import Traverse, load_traverse
from topoloc.evaluation.metrics import compute_metrics
from topoloc.methods.seq_slam import SeqSLAM, SingleImageSeqSLAM, difference_matrix
from topoloc.resources import CachedResources
from topoloc.sequence import acceleration_search, constant_velocity_search, contrast_enhance

ANCHORS = {
    "source": "issue text (measured by its author on nordland_64x32 summer -> winter, "
              "1,788 frames, tolerance 0:2, default parameters); not measured here",
    "OpenSeqSLAM (MATLAB in Octave)": {"auc": 0.63, "recall_at_1": 0.64, "ms_per_query": 50},
    "OpenSeqSLAM C++ port": {"auc": 0.61, "recall_at_1": 0.62, "ms_per_query_search": 6},
    "pySeqSLAM": {"auc": 0.66, "recall_at_1": 0.67, "ms_per_query": 60},
}


def timed(fn: Callable[[], Any], repeats: int) -> tuple[float, list[float], Any]:
    """Median seconds of ``repeats`` calls of ``fn`` (after one warm-up call)."""
    out = fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times, out


def metrics(S: np.ndarray, map_t: Traverse, query: Traverse, hard: int, soft: int) -> dict[str, float]:
    gt = ground_truth_from_places(np.unique(map_t.places), query.places, hard, soft)
    return {k: round(v, 4) for k, v in compute_metrics(S, gt).as_dict().items()}


def nordland(repeats: int) -> dict[str, Any]:
    root = DATA / "nordland_64x32"
    summer, winter = load_traverse(root / "summer"), load_traverse(root / "winter")
    n_q = len(winter)
    out: dict[str, Any] = {"map": str(root / "summer"), "query": str(root / "winter"),
                           "n_places": len(summer), "n_queries": n_q, "tolerance": "0:2"}
    variants: list[tuple[str, type[SeqSLAM], dict[str, Any]]] = [
        ("seqslam (defaults)", SeqSLAM, {}),
        ("seqslam uniqueness=10 (Rwindow margin as S)", SeqSLAM, {"uniqueness": 10}),
        ("seqslam levels_per_std=1 (OpenSeqSLAM rounding)", SeqSLAM, {"levels_per_std": 1.0}),
        ("seqslam search=acceleration (Cooc-Map II-F)", SeqSLAM, {"search": "acceleration"}),
        ("seqslam search=acceleration step_penalty=0.5", SeqSLAM,
         {"search": "acceleration", "step_penalty": 0.5}),
        ("seqslam-single (no sequence search)", SingleImageSeqSLAM, {}),
    ]
    runs = []
    for label, cls, params in variants:
        res = CachedResources()
        method = cls(**params).fit([summer], resources=res)
        t0 = time.perf_counter()
        items = method.encode(winter, resources=res)
        encode_s = time.perf_counter() - t0
        def score(m: SeqSLAM = method, it: list[np.ndarray] = items) -> np.ndarray:
            return m.score(it)

        med, times, S = timed(score, repeats)
        row = {
            "variant": label,
            "params": method.get_params(),
            **metrics(S, summer, winter, 0, 2),
            "ms_per_query": round(1e3 * med / n_q, 4),
            "score_seconds_runs": [round(t, 4) for t in times],
            "ms_features": round(res.ms_features_median(), 4),
            "encode_seconds_total": round(encode_s, 3),
        }
        runs.append(row)
        print(f"nordland {label}: AUC {row['auc']:.3f} R@1 {row['recall_at_1']:.3f} "
              f"{row['ms_per_query']:.3f} ms/query", flush=True)
    out["runs"] = runs

    # Stage breakdown for the defaults.
    res = CachedResources()
    m = SeqSLAM().fit([summer], resources=res)
    Q = np.stack(m.encode(winter, resources=res))
    t_diff, _, D = timed(lambda: m.place_differences(Q), repeats)
    t_enh, _, E = timed(lambda: contrast_enhance(D, window=10), repeats)
    t_search, _, _ = timed(lambda: constant_velocity_search(E), repeats)
    t_acc, _, _ = timed(lambda: acceleration_search(E), repeats)
    out["stages_ms_per_query"] = {
        "difference_matrix": round(1e3 * t_diff / n_q, 4),
        "contrast_enhancement": round(1e3 * t_enh / n_q, 4),
        "constant_velocity_search": round(1e3 * t_search / n_q, 4),
        "acceleration_search": round(1e3 * t_acc / n_q, 4),
    }
    print(f"nordland stages (ms/query): {out['stages_ms_per_query']}", flush=True)
    return out


def synthetic(n: int, repeats: int) -> dict[str, Any]:
    rng = np.random.default_rng(0)
    D = rng.uniform(0.5, 1.0, (n, n)).astype(np.float32)
    # A route through noise at ~1 place per query with a stop and a speed-up.
    steps = rng.choice([0, 1, 1, 1, 1, 1, 1, 2], size=n - 1)
    pos = np.minimum(np.r_[0, np.cumsum(steps)], n - 1)
    D[pos, np.arange(n)] = rng.uniform(0.0, 0.6, n)
    out: dict[str, Any] = {"shape": [n, n], "dtype": "float32"}
    t_enh, _, E = timed(lambda: contrast_enhance(D), max(1, repeats // 2))
    t_cv, cv_runs, C = timed(lambda: constant_velocity_search(E), repeats)
    out["contrast_enhancement_s"] = round(t_enh, 3)
    out["constant_velocity_search_s"] = round(t_cv, 3)
    out["constant_velocity_search_runs_s"] = [round(t, 3) for t in cv_runs]
    out["constant_velocity_within_2"] = round(
        float((np.abs(np.argmin(C, axis=0) - pos) <= 2).mean()), 4)
    del C
    t_acc, _, A = timed(lambda: acceleration_search(E), 1)
    out["acceleration_search_s"] = round(t_acc, 3)
    out["acceleration_within_2"] = round(float((np.abs(np.argmin(A, axis=0) - pos) <= 2).mean()), 4)
    print(f"synthetic {n}x{n}: {out}", flush=True)
    return out


def difference_only(n: int, n_pix: int) -> dict[str, Any]:
    """The L1 difference matrix on its own at a larger scale (uint8 vectors)."""
    rng = np.random.default_rng(1)
    db = rng.integers(0, 256, (n, n_pix), dtype=np.uint8)
    q = rng.integers(0, 256, (n // 10, n_pix), dtype=np.uint8)
    t, _, _ = timed(lambda: difference_matrix(db, q), 1)
    return {"n_db": n, "n_queries": n // 10, "n_pixels": n_pix,
            "ms_per_query": round(1e3 * t / (n // 10), 4)}


def gardens_point() -> list[dict[str, Any]]:
    gp = DATA / "gardens_point"
    rows = []
    for mp, qn in [("day_left", "day_right"), ("day_right", "night_right"),
                   ("day_left", "night_right")]:
        m, q = load_traverse(gp / mp), load_traverse(gp / qn)
        variants: list[dict[str, Any]] = [{}, {"enhance_window": 0}]
        for params in variants:
            res = CachedResources()
            meth = SeqSLAM(**params).fit([m], resources=res)
            S = meth.score(meth.encode(q, resources=res))
            rows.append({"map": mp, "query": qn, "params": params, **metrics(S, m, q, 0, 8)})
            print(f"gardens_point {mp}->{qn} {params}: AUC {rows[-1]['auc']:.3f} "
                  f"R@1 {rows[-1]['recall_at_1']:.3f}", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats, 3,000 x 3,000 synthetic")
    args = ap.parse_args()
    repeats = 2 if args.quick else 7
    if not (DATA / "nordland_64x32").is_dir():
        raise SystemExit(f"nordland_64x32 not found under {DATA} (set TOPOLOC_DATA)")
    result: dict[str, Any] = {
        "machine": {
            "cpus": os.cpu_count(),
            "processor": platform.processor() or platform.machine(),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "opencv": cv2.__version__,
            "opencv_threads": cv2.getNumThreads(),
            # Other work on the machine inflates timings; recorded so that
            # runs can be compared.
            "load_average_1min_at_start": round(os.getloadavg()[0], 2),
        },
        "timing_note": "ms_per_query = median wall time of SeqSLAM.score over repeats "
                       "(difference matrix + contrast enhancement + search) / n_queries; "
                       "image preprocessing is ms_features, excluded as in PROTOCOL.md",
        "anchors": ANCHORS,
    }
    result["nordland"] = nordland(repeats)
    result["synthetic_search"] = synthetic(3000 if args.quick else 10_000, 1 if args.quick else 3)
    result["difference_matrix_scale"] = difference_only(10_000, 2048)
    result["gardens_point"] = gardens_point()
    result["machine"]["load_average_1min_at_end"] = round(os.getloadavg()[0], 2)
    result["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / "seqslam_speed.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
