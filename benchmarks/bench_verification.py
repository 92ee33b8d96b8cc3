"""Regenerate docs/results/verification.md (+ .json, verification_pr.png): what `verified` means, measured.

    .venv/bin/python -m benchmarks.bench_verification
        [--parts quality,offmap,floor,caps,evidence,confidence,speed,localize,slam]
        [--rows gp_day,...] [--methods coocmap,...]

Every setting is a default (XFeat features, the vocabulary trained on the map's tours, verification's own
defaults) and the data are the development split (``../shared/data``), on which the defaults were chosen.
Each run is made in this process through the functions ``topoloc evaluate`` uses (``build_method``,
``make_resources``, ``build_verifier``, ``learn_confusion``); for Cooc-Map on gp_day the same run is also
made with ``topoloc evaluate --verify`` and its S compared with the benchmark's.

Parts:

- ``quality``: per development set and method, AUC / R@100P / R@1 without and with verification, the
  fraction verified, **verified-right** (verified and within the tolerance, over all queries), the
  wrong answers verified, and the **hard negatives** verified: each query verified against its best
  place outside the tolerance (its ``S`` column set to ``-inf`` inside the tolerance, the map whole).
  On the same pairs (each query with the method's best place, and with that best place outside the
  tolerance) GV-Bench's plain rule, RANSAC inliers above a threshold, is scored by its best recall at
  100% precision, beside the recall and precision of verification's decision on the same pairs.
  Sets: gardens_point by day and at night (two day tours, single images and ``--sequence 10``), the
  webcams, michigan_seasons (each visit against the eleven others) and the crowded map
  (``../shared/crowded_map``: gardens_point day_left among 831 places of the other routes, night queries).
- ``offmap``: frames of no mapped place (the other development datasets, blank, noise) against a
  gardens_point map and a webcam map, and half-frame glitches (half a mapped frame torn, grey or noise):
  answers verified, and answers a calibrated map accepts (``map calibrate`` with its defaults, then
  ``localize`` as it runs by default).
- ``floor``: the support floor (``--min-support``; the default 25 was chosen here) swept, Cooc-Map:
  verified-right, wrong and hard negatives verified per set, off-map frames verified.
- ``caps``: the same at 500, 1000 and 2000 features per image (``--max-features``) on gardens_point by day, at
  night (two day tours, and the one day tour of the crowded map), with the floor a cap-proportional rule
  would give: whether the floor should follow the feature cap.
- ``evidence``: whether anything beside the support tells right answers from wrong ones where the floor
  refuses them: Cooc-Map's answers, hard negatives and off-map frames verified at the lowest floor of part
  ``floor`` but below the default one, with the spread of their supporting matches over the query image,
  the share of them one homography explains, and whether the frame before confirms the answer; for each, the
  right answers past the bar every wrong one stays behind.
- ``confidence``: the confidence model fitted on every set's answers pooled, the frames of no mapped
  place among them (all wrong; the defaults in ``topoloc.verification.decision``), its reliability
  (confidence against the fraction right, by bins), and the same fitted leaving each set out, scored on
  the set left out.  The answers come from the ``quality`` (Cooc-Map) and ``offmap`` parts of this run, or
  of the last run (kept in the JSON) when only ``confidence`` is asked for.
- ``speed``: the stage alone on 640 px gardens_point day frames, quiet and beside 3 busy processes,
  one frame per period at 10 Hz.
- ``localize``: ``topoloc localize`` of the 100 day_right frames against a day_left map, with and without
  verification, quiet and beside 3 busy processes.
- ``slam``: ``topoloc slam rtabmap_loop`` with and without verification of its loop closures.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import shutil
import subprocess
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from benchmarks.bench_load import busy, paced
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
    write_results,
)
from topoloc.datasets.groundtruth import GroundTruth
from topoloc.datasets.traverse import Traverse, load_traverse
from topoloc.evaluation.metrics import compute_metrics
from topoloc.evaluation.timing import apply_sequence
from topoloc.maps.acceptance import floor_before_it_was_recorded
from topoloc.maps.confusion import learn_confusion
from topoloc.methods.base import PlaceRecognizer
from topoloc.resources import Resources
from topoloc.spec import FeatureSpec, GroundTruthSpec, VerificationSpec, VocabularySpec
from topoloc.spec.setup import build_method, build_verifier, make_resources
from topoloc.verification import DEFAULT_CANDIDATES, ConfidenceModel, VerifiedBlock, Verifier, confirmed, decision
from topoloc.verification.pairs import inlier_threshold

FEATURES = "xfeat"
SEQUENCE = 10
METHODS = ("coocmap", "bow", "fabmap2", "fabmap", "landmarks", "voting", "seqslam")
MICHIGAN = DATA / "michigan_seasons"
#: row -> (map tours, query, tolerance, sequence, description, methods)
ROWS: dict[str, tuple[list[Path], Path, str, int, str, tuple[str, ...]]] = {
    "gp_day": ([GP / "day_left"], GP / "day_right", "0:8", 0, "gardens_point day_left -> day_right", METHODS),
    "gp_night": ([GP / "day_left", GP / "day_right"], GP / "night_right", "0:8", 0,
                 "gardens_point day_left + day_right -> night_right, single images", METHODS),
    "gp_night_seq10": ([GP / "day_left", GP / "day_right"], GP / "night_right", "0:8", SEQUENCE,
                       "gardens_point day_left + day_right -> night_right, --sequence 10",
                       tuple(m for m in METHODS if m != "seqslam")),
    "webcam": (WEBCAM_TOURS, WEBCAM / "queries", "0:0", 0, "webcam_daynight 12 map tours -> queries",
               ("coocmap", "bow", "fabmap2")),
    "michigan": ([], MICHIGAN, "0:0", 0, "michigan_seasons, each visit against the eleven others",
                 ("coocmap", "bow")),
    "crowded": ([], GP, "0:8", 0, "crowded map (gardens_point day_left among 831 places of other routes) -> "
                "night_right", ("coocmap", "bow")),
    "crowded_alone": ([GP / "day_left"], GP / "night_right", "0:8", 0,
                      "gardens_point day_left alone -> night_right: the crowded map's own places and queries, without "
                      "the other routes' places (what the crowding costs)", ("coocmap", "bow")),
}
#: Rows that repeat another's queries (as a sequence, or on part of its map): left out of the confidence's fit
#: and of the floor table, which would count their answers twice.
REPEATS = ("gp_night_seq10", "crowded_alone")
OUT_MD = RESULTS / "verification.md"
OUT_JSON = RESULTS / "verification.json"
OUT_PNG = RESULTS / "verification_pr.png"
FLOORS = (12, 15, 20, 25, 30)


def _scores(S: np.ndarray, gt: GroundTruth) -> dict[str, Any]:
    m = compute_metrics(S, gt)
    return {"auc": round(float(m.auc), 3), "r100p": round(float(m.recall_at_100_precision), 2),
            "r1": round(float(m.recall_at_k[1]), 3), "precision": m.precision.tolist(), "recall": m.recall.tolist()}


# ------------------------------------------------------------------------------------------------ one run
@dataclass
class Run:
    """One method fitted on one map, its queries scored and verified."""

    method: PlaceRecognizer
    resources: Resources
    verifier: Verifier
    S: np.ndarray
    gt: GroundTruth
    features: list[Any]
    query: Traverse


def fit_run(method_name: str, maps: Sequence[Path | Traverse], query: Path | Traverse, tolerance: str,
            sequence: int = 0, spec: VerificationSpec | None = None, max_features: int | None = None) -> Run:
    """As ``topoloc evaluate --verify`` with defaults (``--max-features`` where given): fit, score, the verification
    stage with the map's confusion."""
    tours = [m if isinstance(m, Traverse) else load_traverse(m) for m in maps]
    q = query if isinstance(query, Traverse) else load_traverse(query)
    method = build_method(method_name, {})
    features = FeatureSpec(method=FEATURES, **({} if max_features is None else {"max_features": max_features}))
    res, _ = make_resources(features.config(), VocabularySpec(),
                            needs_vocabulary=f"method {method_name!r}" if method.uses_vocabulary else "", tours=tours)
    method.fit(tours, resources=res)
    S = np.asarray(method.score(method.encode(q, resources=res)), np.float32)
    if sequence:
        S = apply_sequence(S, sequence)[0].astype(np.float32)
    gt = GroundTruthSpec(tolerance=tolerance).make(method.place_ids_, q, maps=tours)
    v = build_verifier(spec or VerificationSpec(), method.place_ids_, tours, res, sequence=sequence)
    learn_confusion(method, tours, res, v).install(v)
    return Run(method, res, v, S, gt, res.features(q, timed=False), q)


def _only(S: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``S`` with every place but one per column set to -inf (a fixed (query, place) pair)."""
    out = np.full_like(S, -np.inf)
    cols = np.arange(S.shape[1])
    out[rows, cols] = S[rows, cols]
    return out


def judge_answers(run: Run) -> tuple[VerifiedBlock, VerifiedBlock, np.ndarray]:
    """A run's answers verified, its hard negatives verified (each query against its best place outside the
    tolerance), and whether each answer lies within the tolerance."""
    S, gt, v, qf = run.S, run.gt, run.verifier, run.features
    block = v.verify(S, qf)
    hard = v.verify(np.where(gt.soft, -np.inf, S), qf)
    return block, hard, gt.soft[block.answer, np.arange(S.shape[1])]


def judge(run: Run) -> dict[str, Any]:
    """Verification of a run: its answers, its hard negatives and the fixed pairs GV-Bench scores."""
    S, gt, v, qf = run.S, run.gt, run.verifier, run.features
    block, hard, within = judge_answers(run)
    cols = np.arange(S.shape[1])
    has = gt.hard.any(axis=0)
    best = S.argmax(axis=0)
    outside = np.where(gt.soft, -np.inf, S).argmax(axis=0)
    fixed_best = v.verify(_only(S, best), qf)
    fixed_out = v.verify(_only(S, outside), qf)
    plain = np.array([v.check(qf[j], int(best[j]))[0].inliers for j in cols] +
                     [v.check(qf[j], int(outside[j]))[0].inliers for j in cols])
    label = np.r_[gt.soft[best, cols], np.zeros(len(cols), bool)]
    ours = np.r_[fixed_best.verified, fixed_out.verified]
    return {"block": block, "hard": hard, "within": within, "has_place": has,
            "pairs": {"plain": plain, "label": label, "ours": ours},
            "answers": {"strength": block.strength, "verified": block.verified, "right": within}}


def r100p(score: np.ndarray, label: np.ndarray) -> float:
    """Best recall at 100% precision of ranking pairs by ``score`` (ties above the threshold count)."""
    if not label.any():
        return 0.0
    wrong = score[~label]
    top = wrong.max() if len(wrong) else -np.inf
    return float((score[label] > top).sum() / label.sum())


def pairs_summary(label: np.ndarray, ours: np.ndarray, plain: np.ndarray) -> dict[str, Any]:
    """Verification's recall and precision on fixed pairs, and the plain inlier count's recall at 100% precision."""
    hit = int((ours & label).sum())
    return {"n": len(label), "positive": int(label.sum()), "ours_recall": round(hit / max(int(label.sum()), 1), 3),
            "ours_precision": round(hit / int(ours.sum()), 3) if ours.any() else None,
            "plain_r100p": round(r100p(np.asarray(plain, float), label), 3)}


def row_cell(run: Run, j: dict[str, Any]) -> dict[str, Any]:
    block: VerifiedBlock = j["block"]
    n = block.S.shape[1]
    v = block.verified
    pairs = j["pairs"]
    lab, ours = pairs["label"], pairs["ours"]
    return {"without": _scores(run.S, run.gt), "with": _scores(block.S, run.gt),
            "queries": n, "verified": int(v.sum()), "verified_right": int((v & j["within"]).sum()),
            "verified_wrong": int((v & ~j["within"]).sum()),
            "hard_verified": int(j["hard"].verified.sum()),
            "ms_median": round(float(np.median(block.ms)), 2), "ms_p95": round(float(np.percentile(block.ms, 95)), 2),
            "pairs": pairs_summary(lab, ours, pairs["plain"])}


def merge_cells(cells: list[dict[str, Any]], runs: list[Run], judged: list[dict[str, Any]]) -> dict[str, Any]:
    """Michigan's twelve folds as one row: counts summed, the protocol's metrics over the folds' columns joined."""
    S = np.concatenate([r.S for r in runs], axis=1) if len({r.S.shape[0] for r in runs}) == 1 else None
    out: dict[str, Any] = {k: sum(c[k] for c in cells) for k in ("queries", "verified", "verified_right",
                                                                 "verified_wrong", "hard_verified")}
    if S is not None:
        gt = GroundTruth(np.concatenate([r.gt.hard for r in runs], axis=1),
                         np.concatenate([r.gt.soft for r in runs], axis=1))
        out["without"] = _scores(S, gt)
        out["with"] = _scores(np.concatenate([j["block"].S for j in judged], axis=1), gt)
    ms = np.concatenate([j["block"].ms for j in judged])
    out["ms_median"], out["ms_p95"] = round(float(np.median(ms)), 2), round(float(np.percentile(ms, 95)), 2)
    lab = np.concatenate([j["pairs"]["label"] for j in judged])
    ours = np.concatenate([j["pairs"]["ours"] for j in judged])
    plain = np.concatenate([j["pairs"]["plain"] for j in judged]).astype(float)
    out["pairs"] = pairs_summary(lab, ours, plain)
    return out


def crowded(tmp: Path) -> tuple[Path, Path]:
    d = tmp / "crowd"
    if not (d / "map").is_dir():
        subprocess.run([str(DATA.parent / "crowded_map"), str(d)], check=True, stdout=subprocess.DEVNULL,
                       env={**os.environ, "TOPOLOC_DATA": str(DATA)})
    return d / "map", d / "q"


def runs_of(row: str, method: str, tmp: Path, spec: VerificationSpec | None = None,
            max_features: int | None = None) -> list[Run]:
    maps, query, tol, seq, _, _ = ROWS[row]
    if row == "michigan":
        visits = sorted(p for p in MICHIGAN.glob("m*") if p.is_dir())
        return [fit_run(method, [v for v in visits if v != q], q, tol, 0, spec, max_features) for q in visits]
    if row == "crowded":
        cmap, cq = crowded(tmp)
        return [fit_run(method, [cmap], cq, tol, 0, spec, max_features)]
    return [fit_run(method, maps, query, tol, seq, spec, max_features)]


def quality(rows: Sequence[str], methods: Sequence[str], tmp: Path,
            pooled: dict[str, list[dict[str, np.ndarray]]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for row in rows:
        for method in ROWS[row][5]:
            if method not in methods:
                continue
            t0 = time.perf_counter()
            runs = runs_of(row, method, tmp)
            judged = [judge(r) for r in runs]
            cells = [row_cell(r, j) for r, j in zip(runs, judged, strict=True)]
            cell = cells[0] if len(cells) == 1 else merge_cells(cells, runs, judged)
            if (row, method) == ("gp_day", "coocmap"):
                cell["cli_equal"] = _cli_check(row, judged[0]["block"].S, tmp)
            if method == "coocmap":
                pooled[row] = [j["answers"] for j in judged]
            out.setdefault(row, {})[method] = cell
            print(f"{row} {method}: verified-right {cell['verified_right']}/{cell['queries']} wrong "
                  f"{cell['verified_wrong']} hard {cell['hard_verified']}  ({time.perf_counter() - t0:.0f} s)",
                  flush=True)
    return out


def _cli_check(row: str, S_bench: np.ndarray, tmp: Path) -> bool:
    """``topoloc evaluate --verify`` of the same row gives the benchmark's verified S."""
    maps, query, tol, _, _, _ = ROWS[row]
    out = tmp / f"cli_{row}"
    cmd = [str(TOPOLOC), "evaluate", "-q", "--method", "coocmap", "--query", str(query), "--out", str(out),
           "--tolerance", tol, "--features", FEATURES, "--verify", *[a for m in maps for a in ("--map", str(m))]]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return bool(np.allclose(np.load(out / "S.npy"), S_bench, rtol=0, atol=1e-6))


# ------------------------------------------------------------------------------------------------ off the map
def _frames(folder: Path, every: int = 1) -> list[np.ndarray]:
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".png"))[::every]
    return [cv2.imread(str(p), cv2.IMREAD_COLOR) for p in files]


def foreign_sets(exclude: str) -> dict[str, Traverse]:
    """Frames of no place of a gardens_point (``exclude="gp"``) or webcam (``"webcam"``) map."""
    sets = {"corridor": _frames(DATA / "corridor" / "query"), "rtabmap_loop": _frames(DATA / "rtabmap_loop"),
            "michigan": [f for v in sorted(MICHIGAN.glob("m*")) for f in _frames(v)],
            "nordland": _frames(DATA / "nordland_64x32" / "winter", every=20)}
    if exclude != "webcam":
        sets["webcam"] = _frames(WEBCAM / "queries", every=5)
    if exclude != "gp":
        sets["gardens_point"] = _frames(GP / "night_right") + _frames(GP / "day_right", every=2)
    rng = np.random.default_rng(0)
    h, w = (360, 640)
    sets["blank"] = [np.full((h, w, 3), v, np.uint8) for v in (0, 30, 128, 220, 255)]
    sets["noise"] = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(10)] + [
        cv2.GaussianBlur(rng.integers(0, 256, (h, w, 3), dtype=np.uint8), (0, 0), s) for s in (1, 2, 3, 5, 8)
        for _ in range(2)]
    return {k: Traverse.from_images(v, name=k) for k, v in sets.items()}


def glitches(query: Traverse, n: int = 30) -> Traverse:
    """Half-frame glitches of mapped frames: the lower half grey, noise, or torn (shifted by a third)."""
    rng = np.random.default_rng(1)
    idx = np.linspace(0, len(query) - 1, min(n, len(query))).round().astype(int)
    out = []
    for k, i in enumerate(idx):
        im = query.read(int(i), gray=False).copy()
        hh = im.shape[0] // 2
        if k % 3 == 0:
            im[hh:] = 128
        elif k % 3 == 1:
            im[hh:] = rng.integers(0, 256, im[hh:].shape, dtype=np.uint8)
        else:
            im[hh:] = np.roll(im, im.shape[1] // 3, axis=1)[hh:]
        out.append(im)
    return Traverse.from_images(out, places=query.places[idx], name="glitches")


def offmap(tmp: Path, pooled: dict[str, list[dict[str, np.ndarray]]]) -> dict[str, Any]:
    from topoloc.maps import Map

    out: dict[str, Any] = {}
    for name, maps, query, tol, exclude in (("gardens_point", [GP / "day_left"], GP / "night_right", "0:8", "gp"),
                                            ("webcam", WEBCAM_TOURS, WEBCAM / "queries", "0:0", "webcam")):
        run = fit_run("coocmap", maps, query, tol)
        cells: dict[str, Any] = {}
        for set_name, t in foreign_sets(exclude).items():
            S = np.asarray(run.method.score(run.method.encode(t, resources=run.resources)), np.float32)
            b = run.verifier.verify(S, run.resources.features(t, timed=False))
            cells[set_name] = {"frames": len(t), "verified": int(b.verified.sum()),
                               "max_support": int(b.support.max()) if len(b.support) else 0}
            # Every answer to a frame of no mapped place is wrong: the confidence is fitted on them too.
            pooled.setdefault(f"offmap_{name}", []).append(
                {"strength": b.strength, "verified": b.verified, "right": np.zeros(len(t), bool)})
        g = glitches(load_traverse(query))
        S = np.asarray(run.method.score(run.method.encode(g, resources=run.resources)), np.float32)
        b = run.verifier.verify(S, run.resources.features(g, timed=False))
        gt = GroundTruthSpec(tolerance=tol).make(run.method.place_ids_, g)
        wrong = ~gt.soft[b.answer, np.arange(len(g))]
        cells["glitches"] = {"frames": len(g), "verified": int(b.verified.sum()),
                             "verified_wrong": int((b.verified & wrong).sum())}
        out[name] = cells
        print(f"offmap {name}: " + ", ".join(f"{k} {c['verified']}/{c['frames']}" for k, c in cells.items()),
              flush=True)
    # A calibrated map, then localize as it runs by default (the calibrated sequence and verification): the
    # benchmarks' TOPOLOC_VERIFY=0 (benchmarks.common) lifted, or the map would be calibrated and run unverified.
    acc: dict[str, Any] = {}
    with environ(TOPOLOC_VERIFY="auto"):
        m = Map.build(method="coocmap", tours=[GP / "day_left"], features=FeatureSpec(method=FEATURES))
        cal = m.calibrate_on(GP / "day_right")
        for set_name, t in foreign_sets("gp").items():
            lines = m.localize_many([t.read(k, gray=False) for k in range(len(t))])
            acc[set_name] = {"frames": len(lines), "accepted": sum(bool(x["accepted"]) for x in lines),
                             "verified": sum(bool(x.get("verified")) for x in lines)}
    out["calibrated"] = {"map": "gardens_point day_left, coocmap, `map calibrate --query day_right` (defaults)",
                         "calibration": {k: cal.get(k) for k in ("threshold", "threshold_on", "precision", "recall",
                                                                  "sequence", "verify")},
                         "sets": acc}
    print("calibrated: " + ", ".join(f"{k} {c['accepted']}/{c['frames']}" for k, c in acc.items()), flush=True)
    return out


# ------------------------------------------------------------------------------------------------ the floor
def _floor_cells(base: dict[str, list[Run]], offmap_run: Run, foreign_S: dict[str, tuple[np.ndarray, list[Any]]],
                 value: int) -> dict[str, Any]:
    """Verified-right, wrong and hard negatives verified per row, and off-map frames verified, at the floor
    ``value`` (the runs' confusion kept: only the rule changes)."""
    rule = VerificationSpec(min_support=value).rule()
    cells: dict[str, Any] = {}
    for row, runs in base.items():
        vr = wrong = hard = n = 0
        for r in runs:
            r.verifier.rule = rule
            b, h, within = judge_answers(r)
            vr += int((b.verified & within).sum())
            wrong += int((b.verified & ~within).sum())
            hard += int(h.verified.sum())
            n += b.S.shape[1]
        cells[row] = {"verified_right": round(vr / n, 3), "wrong": wrong, "hard": hard}
    offmap_run.verifier.rule = rule
    cells["offmap"] = sum(int(offmap_run.verifier.verify(S, f).verified.sum()) for S, f in foreign_S.values())
    return cells


def _foreign_scores(run: Run) -> dict[str, tuple[np.ndarray, list[Any]]]:
    """The frames of no place of a gardens_point map (:func:`foreign_sets`) scored by ``run``'s method, with their
    features."""
    return {k: (np.asarray(run.method.score(run.method.encode(t, resources=run.resources)), np.float32),
                run.resources.features(t, timed=False)) for k, t in foreign_sets("gp").items()}


def floor(rows: Sequence[str], tmp: Path) -> dict[str, Any]:
    """Cooc-Map's verified-right, wrong and hard negatives verified, and off-map frames verified, by the floor."""
    out: dict[str, Any] = {}
    base: dict[str, list[Run]] = {row: runs_of(row, "coocmap", tmp) for row in rows if row not in REPEATS}
    gp_run = fit_run("coocmap", [GP / "day_left"], GP / "night_right", "0:8")
    foreign_S = _foreign_scores(gp_run)
    for value in FLOORS:
        out[str(value)] = _floor_cells(base, gp_run, foreign_S, value)
        print(f"floor {value}: {out[str(value)]}", flush=True)
    return out


#: Features per image (``--max-features``) the floor is measured at in part ``caps``, and the rows measured.
CAPS = (500, 1000, 2000)
CAP_ROWS = ("gp_day", "gp_night", "crowded_alone")
#: ... and the floors (beside the one in proportion to the cap).
CAP_FLOORS = (20, 25, 30)


def caps(tmp: Path) -> dict[str, Any]:
    """The floor table at other feature caps: whether the support chance reaches follows ``--max-features``.

    At each cap every method's input changes (features, the vocabulary trained on them, the map's confusion);
    the floors are :data:`CAP_FLOORS` and the one a floor in proportion to the cap would give (25 x cap / 1000).
    Off-map frames are checked against the map of ``crowded_alone`` (gardens_point day_left).
    """
    out: dict[str, Any] = {}
    for cap in CAPS:
        base = {row: runs_of(row, "coocmap", tmp, max_features=cap) for row in CAP_ROWS}
        offmap_run = base["crowded_alone"][0]
        foreign_S = _foreign_scores(offmap_run)
        proportional = floor_before_it_was_recorded(cap)  # the rule the floor followed before this part
        cells = {str(v): _floor_cells(base, offmap_run, foreign_S, v) for v in sorted({*CAP_FLOORS, proportional})}
        out[str(cap)] = {"proportional": proportional, "floors": cells}
        print(f"features {cap}: {cells}", flush=True)
    return out


# ------------------------------------------------------------------------------------------------ evidence
#: Cells per side of the grid over the query image that part ``evidence`` counts supporting matches in.
GRID = 6
#: Evidence part ``evidence`` measures, and whether more of it speaks for a right answer.
EVIDENCE = {"cells": True, "homography": False, "confirmed": True}


def pair_evidence(pairs: np.ndarray, shapes: np.ndarray) -> dict[str, float]:
    """How a pair's supporting matches lie: what a rule could add to their number.

    Parameters
    ----------
    pairs : ndarray, shape (n, 4)
        The supporting matches: query x, y, map image x, y (pixels; ``VerifiedBlock.matches``).
    shapes : ndarray, shape (4,)
        The query's and the map image's (height, width).

    Returns
    -------
    dict
        ``cells``: the fraction of a ``GRID`` x ``GRID`` grid over the query image holding a supporting match
        (their spread); ``homography``: the fraction of them one homography explains (RANSAC, twice the
        epipolar tolerance of :func:`topoloc.verification.pairs.inlier_threshold`; COLMAP calls a pair whose
        homography explains most of its inliers planar, a degenerate geometry).
    """
    hq, wq = int(shapes[0]), int(shapes[1])
    n = len(pairs)
    cx = np.clip((pairs[:, 0] / max(wq, 1) * GRID).astype(int), 0, GRID - 1)
    cy = np.clip((pairs[:, 1] / max(hq, 1) * GRID).astype(int), 0, GRID - 1)
    cells = len(np.unique(cy * GRID + cx)) / GRID ** 2
    share = 1.0
    if n >= 5:
        t = 2 * inlier_threshold((int(shapes[2]), int(shapes[3])))
        _, mask = cv2.findHomography(pairs[:, :2].astype(np.float64), pairs[:, 2:].astype(np.float64), cv2.RANSAC,
                                     t, maxIters=2000)
        share = float(mask.sum()) / n if mask is not None else 0.0
    return {"cells": round(cells, 4), "homography": round(share, 4)}


def _band(block: VerifiedBlock, right: np.ndarray, kind: str, row: str) -> list[dict[str, Any]]:
    """The answers of ``block`` verified at the lowest floor but below the default one, with their evidence."""
    ok = confirmed(block.S)
    return [{"set": row, "kind": kind, "right": bool(right[j]), "support": int(block.support[j]),
             "confirmed": float(ok[j]), **pair_evidence(block.matches[j], block.match_shapes[j])}
            for j in np.flatnonzero(block.verified & (block.support < decision.MIN_SUPPORT))]


def evidence_rules(items: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Per piece of evidence (:data:`EVIDENCE`): the bar every wrong item stays behind, and the right items past it
    per set (what a rule adding that evidence would verify with no wrong one)."""
    wrong = [x for x in items if not x["right"]]
    right = [x for x in items if x["right"]]
    out: dict[str, Any] = {}
    for name, more_is_right in EVIDENCE.items():
        values = [x[name] for x in wrong]
        bar = (max(values) if more_is_right else min(values)) if values else None
        passes = [x for x in right if bar is None or (x[name] > bar if more_is_right else x[name] < bar)]
        out[name] = {"bar": bar, "more_is_right": more_is_right,
                     "gained": {row: sum(1 for x in passes if x["set"] == row) for row in ROWS}}
    return out


def evidence(tmp: Path) -> dict[str, Any]:
    """Whether evidence beside the support tells right answers from wrong ones in the band the floor refuses.

    Cooc-Map's answers and hard negatives of every development set, and frames of no place of a gardens_point
    map, verified at the lowest floor of part ``floor`` (the rest of the rule as it is); of those with support
    below the default floor: the spread of the supporting matches over the query image, the share of them one
    homography explains, and whether the frame before confirms the answer (``--confirm``'s test,
    :func:`topoloc.verification.confirmed`).
    """
    rule = VerificationSpec(min_support=FLOORS[0]).rule()
    items: list[dict[str, Any]] = []
    for row in (r for r in ROWS if r not in REPEATS):
        for r in runs_of(row, "coocmap", tmp):
            r.verifier.rule = rule
            b, h, within = judge_answers(r)
            items += _band(b, within, "answer", row) + _band(h, np.zeros(len(within), bool), "hard", row)
    gp_run = fit_run("coocmap", [GP / "day_left"], GP / "night_right", "0:8")
    gp_run.verifier.rule = rule
    for S, f in _foreign_scores(gp_run).values():
        b = gp_run.verifier.verify(S, f)
        items += _band(b, np.zeros(S.shape[1], bool), "offmap", "offmap")
    out: dict[str, Any] = {"floor": FLOORS[0], "items": items, "rules": evidence_rules(items)}
    print(f"evidence: {sum(x['right'] for x in items)} right, {sum(not x['right'] for x in items)} wrong; " +
          ", ".join(f"{k} bar {v['bar']} gains {sum(v['gained'].values())}" for k, v in out["rules"].items()),
          flush=True)
    return out


# ------------------------------------------------------------------------------------------------ confidence
BINS = (0.0, 0.5, 0.8, 0.9, 0.95, 0.99, 1.0)


def confidence(pooled: dict[str, list[dict[str, np.ndarray]]]) -> dict[str, Any]:
    """The confidence model fitted on every set's answers pooled, its reliability, and leaving each set out."""
    def stack(rows: Sequence[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        parts = [a for r in rows for a in pooled[r]]
        return (np.concatenate([p["strength"] for p in parts]), np.concatenate([p["verified"] for p in parts]),
                np.concatenate([p["right"] for p in parts]))

    rows = [r for r in pooled if r not in REPEATS]
    x, v, y = stack(rows)
    model = ConfidenceModel.fit(np.log(np.maximum(x, 1e-3)), v, y, source="development data (verification.md)")
    c = model(np.log(np.maximum(x, 1e-3)), v)
    table = []
    for lo, hi in itertools.pairwise(BINS):
        k = (c >= lo) & ((c < hi) if hi < 1 else (c <= hi))
        if k.any():
            table.append({"bin": f"{lo:.2f}-{hi:.2f}", "answers": int(k.sum()), "mean_confidence":
                          round(float(c[k].mean()), 3), "right": round(float(y[k].mean()), 3)})
    loo = {}
    for held in rows:
        xt, vt, yt = stack([r for r in rows if r != held])
        mt = ConfidenceModel.fit(np.log(np.maximum(xt, 1e-3)), vt, yt)
        xh, vh, yh = stack([held])
        ch = mt(np.log(np.maximum(xh, 1e-3)), vh)
        loo[held] = {"answers": len(yh), "mean_confidence": round(float(ch.mean()), 3),
                     "right": round(float(yh.mean()), 3),
                     "brier": round(float(np.mean((ch - yh) ** 2)), 4)}
    default = decision.DEFAULT_CONFIDENCE
    return {"fitted": {"a": round(model.a, 3), "b": round(model.b, 3), "c": round(model.c, 3), "n": model.n},
            "default": {"a": default.a, "b": default.b, "c": default.c},
            "default_matches_fit": bool(abs(default.a - model.a) < 0.05 and abs(default.b - model.b) < 0.05
                                        and abs(default.c - model.c) < 0.05),
            "reliability": table, "leave_one_set_out": loo}


# ------------------------------------------------------------------------------------------------ speed
def speed(tmp: Path) -> dict[str, Any]:
    run = fit_run("coocmap", [GP / "day_left"], GP / "day_right", "0:8")
    S, qf, v = run.S, run.features, run.verifier
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


def slam(tmp: Path) -> dict[str, Any]:
    import csv

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


def _thin_curves(part: dict[str, Any], points: int = 200) -> None:
    """PR curves kept at most ``points`` points each, enough to draw them again."""
    for cells in part.values():
        for cell in cells.values():
            for scores in cell.values():
                if isinstance(scores, dict) and "recall" in scores:
                    n = len(scores["recall"])
                    keep = np.unique(np.linspace(0, n - 1, min(n, points)).round().astype(int)) if n else []
                    for key in ("precision", "recall"):
                        scores[key] = [round(float(scores[key][i]), 4) for i in keep]


# ------------------------------------------------------------------------------------------------ page
def _cell(c: dict[str, Any] | None) -> str:
    return "-" if not c else f"{c['auc']:.3f} / {c['r100p']:.2f} / {c['r1']:.2f}"


def pr_figure(q: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in ROWS if r in q]
    fig, axes = plt.subplots(1, len(rows), figsize=(4.0 * len(rows), 4), squeeze=False)
    for ax, row in zip(axes[0], rows, strict=True):
        for k, (method, cell) in enumerate(q[row].items()):
            if "with" not in cell:
                continue
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
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _floor_row(cells: dict[str, Any], sets: Sequence[str]) -> str:
    """One row of a floor table: verified-right / wrong / hard negatives per set, then off-map frames verified."""
    return " | ".join([*(f"{cells[s]['verified_right']:.2f} / {cells[s]['wrong']} / {cells[s]['hard']}" for s in sets),
                       str(cells["offmap"])])


def render(res: dict[str, Any]) -> str:
    lines = [
        "# Verified answers: what `verified` means, measured",
        "",
        "Written by `.venv/bin/python -m benchmarks.bench_verification` (issues 40, 46); do not edit by hand.",
        f"Measured {res['date']} on {res['machine']}.",
        "",
        "An answer is *verified* when its support (fundamental-matrix inliers that are distinctive matches) "
        "reaches the floor, exceeds what look-alike places of the same map reach there (learned at build; a "
        "look-alike the query itself has clearly less support at does not count), "
        "and no route neighbour has more (`docs/protocol.md`, \"Verification\"). Every setting is a default "
        "and the features are XFeat; the data are the development split (`../shared/data`), on which every "
        f"default was chosen: the floor of {decision.MIN_SUPPORT} (part `floor`) at any feature cap (part "
        "`caps`), the distinctive-match "
        f"ratio {decision.RATIO}, {DEFAULT_CANDIDATES} candidates, the climb from half the floor (on part "
        "`quality`'s verified-right, against this page as of commit 857fafc3, which climbed from the "
        "floor), the look-alikes the query is checked against (on part `quality`'s verified-right, against "
        "this page as of commit 351f9dc0, which took the map's confusion as it was), and the confidence model "
        "(part `confidence`). *Right* means within the tolerance.",
        "",
    ]
    q = res.get("quality")
    if q:
        lines += ["## Verified answers per development set", "",
                  "| set | method | without verification | with verification | verified | verified-right | "
                  "verified precision | wrong verified | hard negatives verified | stage ms (median, p95) |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        for row, cells in q.items():
            for method, c in cells.items():
                n, v = c["queries"], c["verified"]
                prec = f"{c['verified_right'] / v:.3f}" if v else "-"
                lines.append(f"| {row} | {method} | {_cell(c.get('without'))} | {_cell(c.get('with'))} | "
                             f"{v}/{n} | {c['verified_right'] / n:.2f} | {prec} | {c['verified_wrong']} | "
                             f"{c['hard_verified']}/{n} | {c['ms_median']:.1f}, {c['ms_p95']:.1f} |")
        lines += ["", "Quality columns: AUC / R@100P / R@1 (the protocol's). Sets: "
                  + "; ".join(f"`{r}` {ROWS[r][4]}" for r in q) + ".", ""]
        if "gp_day" in q and "coocmap" in q["gp_day"] and "cli_equal" in q["gp_day"]["coocmap"]:
            lines += ["`topoloc evaluate --verify` of Cooc-Map on gp_day against this benchmark's verified S: "
                      + ("equal." if q["gp_day"]["coocmap"]["cli_equal"] else "DIFFERENT."), ""]
        lines += ["### The same pairs under GV-Bench's rule", "",
                  "Each query with the method's best place, and with its best place outside the tolerance. "
                  "Verification decides each pair as it stands (the place fixed); GV-Bench's rule ranks the pairs "
                  "by their RANSAC inliers, whose best recall at 100% precision is given.", "",
                  "| set | method | pairs (right) | verification: recall, precision | inliers: recall at 100% "
                  "precision |", "| --- | --- | --- | --- | --- |"]
        for row, cells in q.items():
            for method, c in cells.items():
                p = c["pairs"]
                prec = "-" if p["ours_precision"] is None else f"{p['ours_precision']:.3f}"
                lines.append(f"| {row} | {method} | {p['n']} ({p['positive']}) | {p['ours_recall']:.2f}, {prec} | "
                             f"{p['plain_r100p']:.2f} |")
        lines += ["", "![PR curves](verification_pr.png)", ""]
    off = res.get("offmap")
    if off:
        lines += ["## Frames of no mapped place", "",
                  "Verified answers (a frame of no place of the map verified is a wrong answer); glitches are "
                  "mapped frames with their lower half grey, noise or torn, where only a wrong place verified "
                  "counts.", "", "| map | set | frames | verified |", "| --- | --- | --- | --- |"]
        for name in ("gardens_point", "webcam"):
            for set_name, c in off.get(name, {}).items():
                extra = f" ({c['verified_wrong']} wrong)" if "verified_wrong" in c else ""
                lines.append(f"| {name} | {set_name} | {c['frames']} | {c['verified']}{extra} |")
        cal = off.get("calibrated")
        if cal:
            lines += ["", f"Calibrated: {cal['map']}: threshold {cal['calibration']['threshold']} on "
                      f"{cal['calibration']['threshold_on']}, precision {cal['calibration']['precision']}, recall "
                      f"{cal['calibration']['recall']}, sequence {cal['calibration']['sequence']}. Frames of no "
                      "mapped place then accepted by `localize` (its defaults):", "",
                      "| set | frames | accepted | verified |", "| --- | --- | --- | --- |"]
            for set_name, c in cal["sets"].items():
                lines.append(f"| {set_name} | {c['frames']} | {c['accepted']} | {c['verified']} |")
        lines.append("")
    fl = res.get("floor")
    if fl:
        sets = [k for k in next(iter(fl.values())) if k != "offmap"]
        lines += ["## The support floor (Cooc-Map)", "",
                  "Verified-right / wrong verified / hard negatives verified per set, and off-map frames verified "
                  "(against the gardens_point map), by the floor `n_min` (at 1000 features).", "",
                  "| floor | " + " | ".join(sets) + " | off-map verified |",
                  "| --- |" + " --- |" * (len(sets) + 1)]
        for value, cells in fl.items():
            lines.append(f"| {value} | {_floor_row(cells, sets)} |")
        lines.append("")
    ca = res.get("caps")
    if ca:
        sets = list(CAP_ROWS)
        lines += ["## The floor and the feature cap (Cooc-Map)", "",
                  f"The floor table at {', '.join(list(ca)[:-1])} and {list(ca)[-1]} features per image "
                  "(`--max-features`; every input follows: the features, the vocabulary trained on them, the map's "
                  "confusion): verified-right / wrong verified / hard negatives verified per set, and off-map frames "
                  "verified against the map of `crowded_alone`. *proportional*: the floor a rule in proportion to "
                  f"the cap gives ({decision.MIN_SUPPORT} x features / 1000).", "",
                  "| features | floor | " + " | ".join(sets) + " | off-map verified |",
                  "| --- | --- |" + " --- |" * (len(sets) + 1)]
        for cap, c in ca.items():
            for value, cells in c["floors"].items():
                tag = " (proportional)" if int(value) == c["proportional"] else ""
                lines.append(f"| {cap} | {value}{tag} | {_floor_row(cells, sets)} |")
        lines.append("")
    ev = res.get("evidence")
    if ev:
        items = ev["items"]
        n_right = {row: sum(1 for x in items if x["right"] and x["set"] == row) for row in ROWS}
        kinds = {k: sum(1 for x in items if not x["right"] and x["kind"] == k) for k in ("answer", "hard", "offmap")}
        sets = [row for row in ROWS if n_right.get(row)]
        labels = {"cells": f"spread: the fraction of a {GRID} x {GRID} grid over the query image holding a "
                           "supporting match (more speaks for right)",
                  "homography": "planarity: the share of the supporting matches one homography explains (less "
                                "speaks for right; COLMAP's degeneracy test)",
                  "confirmed": "the frame before confirms the answer (1) or not (0) (`--confirm`'s test)"}
        lines += ["## Evidence beside the support (part `evidence`, Cooc-Map)", "",
                  f"Answers verified at the floor {ev['floor']} but below the default {decision.MIN_SUPPORT} (the "
                  "band the floor refuses; the rest of the rule as it is): "
                  f"{sum(n_right.values())} right answers, and {kinds['answer']} wrong answers, {kinds['hard']} hard "
                  f"negatives and {kinds['offmap']} frames of no place of a gardens_point map. For each piece of "
                  "evidence: the bar every wrong one of the band stays behind, and the right answers of the band "
                  "past it, per set (of the right answers in the band), which a rule adding it at this floor would "
                  "verify with no wrong one. The bar is the development data's own extreme: these counts bound "
                  "from above what each could add on data it was not fitted to.", "",
                  "| evidence | wrong ones: min / median / max | right ones: min / median / max | bar | "
                  + " | ".join(sets) + " |",
                  "| --- | --- | --- | --- | " + " | ".join("---" for _ in sets) + " |"]

        def spread(name: str, right: bool) -> str:
            v = [x[name] for x in items if x["right"] == right]
            return " / ".join(f"{q:.2f}" for q in np.percentile(v, [0, 50, 100])) if v else "-"

        for name, rule in ev["rules"].items():
            bar = "-" if rule["bar"] is None else f"{'>' if rule['more_is_right'] else '<'} {rule['bar']:g}"
            lines.append(f"| {labels.get(name, name)} | {spread(name, False)} | {spread(name, True)} | {bar} | " +
                         " | ".join(f"{rule['gained'].get(row, 0)} of {n_right[row]}" for row in sets) + " |")
        lines.append("")
    co = res.get("confidence")
    if co:
        f = co["fitted"]
        lines += ["## Confidence", "",
                  f"`confidence = 1 / (1 + exp(-(a + b log x + c [verified])))`, fitted on {f['n']} Cooc-Map answers "
                  f"of every set pooled: a = {f['a']}, b = {f['b']}, c = {f['c']} (the defaults in "
                  f"`topoloc.verification.decision`: {'the same' if co['default_matches_fit'] else 'DIFFERENT'}).",
                  "", "| confidence | answers | mean confidence | fraction right |", "| --- | --- | --- | --- |"]
        for b in co["reliability"]:
            lines.append(f"| {b['bin']} | {b['answers']} | {b['mean_confidence']} | {b['right']} |")
        lines += ["", "Fitted leaving each set out, scored on it:", "",
                  "| set left out | answers | mean confidence | fraction right | Brier score |",
                  "| --- | --- | --- | --- | --- |"]
        for s, c in co["leave_one_set_out"].items():
            lines.append(f"| {s} | {c['answers']} | {c['mean_confidence']} | {c['right']} | {c['brier']} |")
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
    sl = res.get("slam")
    if sl:
        lines += ["## `topoloc slam` (online FAB-MAP) on rtabmap_loop", "",
                  "| verification | loop closures | on the route | rejected by verification | places |",
                  "| --- | --- | --- | --- | --- |"]
        for key, x in sl.items():
            lines.append(f"| {key.replace('_', '-')} | {x['closures']} | {x['on_route']} | {x['rejected']} | "
                         f"{x['places']} |")
        lines.append("")
    return "\n".join(lines)


PARTS = ("quality", "offmap", "floor", "caps", "evidence", "confidence", "speed", "localize", "slam")


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--parts", default=",".join(PARTS))
    ap.add_argument("--rows", default=",".join(ROWS))
    ap.add_argument("--methods", default=",".join(METHODS))
    args = ap.parse_args(argv)
    parts = args.parts.split(",")
    rows = args.rows.split(",")
    unknown = sorted(set(rows) - set(ROWS)) + sorted(set(parts) - set(PARTS))
    if unknown:
        raise SystemExit(f"unknown part or row: {', '.join(unknown)}")
    require_data()
    RESULTS.mkdir(parents=True, exist_ok=True)
    old = json.loads(OUT_JSON.read_text()) if OUT_JSON.is_file() else {}
    if not {"offmap", "floor", "pooled"} & set(old):
        old = {}  # a page of the earlier rule (issue 40, without these parts): nothing of it is kept
    res: dict[str, Any] = {**old, "date": datetime.now(UTC).isoformat(timespec="seconds"), "machine": machine_line()}
    tmp = Path(tempfile.mkdtemp(prefix="bench_verification_"))
    os.environ["TOPOLOC_FEATURES"] = FEATURES
    pooled: dict[str, list[dict[str, np.ndarray]]] = {}
    try:
        t0 = time.perf_counter()
        if "quality" in parts:
            fresh = quality(rows, args.methods.split(","), tmp, pooled)
            _thin_curves(fresh)
            res["quality"] = {r: {**old.get("quality", {}).get(r, {}), **fresh.get(r, {})}
                              for r in ROWS if r in fresh or r in old.get("quality", {})}
            pr_figure(res["quality"], OUT_PNG)
        if "offmap" in parts:
            res["offmap"] = offmap(tmp, pooled)
        if pooled:
            # The labelled answers the confidence is fitted on, kept so that ``--parts confidence`` alone refits
            # (a part run alone replaces its own sets' answers, the others' kept).
            res["pooled"] = {**old.get("pooled", {}),
                             **{k: [{f: np.asarray(a[f]).tolist() for f in ("strength", "verified", "right")}
                                    for a in v] for k, v in pooled.items()}}
        if "confidence" in parts:
            pooled = {k: [{f: np.asarray(a[f], bool if f != "strength" else float) for f in a} for a in v]
                      for k, v in res.get("pooled", {}).items()}
            res["confidence"] = confidence(pooled)
        if "floor" in parts:
            res["floor"] = floor(rows, tmp)
        if "caps" in parts:
            res["caps"] = caps(tmp)
        if "evidence" in parts:
            res["evidence"] = evidence(tmp)
        if "speed" in parts:
            res["speed"] = speed(tmp)
        if "localize" in parts:
            res["localize"] = localize(tmp)
        if "slam" in parts:
            res["slam"] = slam(tmp)
        res["seconds"] = round(time.perf_counter() - t0, 1)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    write_results(OUT_MD, OUT_JSON, res, render(res))


if __name__ == "__main__":
    main()
