"""``topoloc evaluate``: run one method on map and query traverses and score it.

This is the single door of ``docs/protocol.md``.  Outputs under ``out``:

``S.npy``
    float32 (n_places, n_queries), higher = more similar; with ``top_k`` instead
    ``S_topk.npz`` (``rows``, ``scores`` of shape (n_queries, K), best first, and
    ``shape``; see :mod:`topoloc.evaluation.topk`) and no dense ground truth.
``places.npy`` / ``queries.npy``
    place id of each row / true place id of each column.
``metrics.json``
    the metrics of the protocol plus a ``run`` block describing what ran.
``pr.png``, ``pr.csv``
    the precision-recall curve (``pr.csv``: columns precision,recall).
``report.md``
    the table and what was run, including the vocabulary's provenance.
"""

from __future__ import annotations

import io
import json
import logging
import os
import platform
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.cluster import Executor
from topoloc.datasets.groundtruth import (
    GroundTruth,
    ground_truth_from_file,
    ground_truth_from_places,
    ground_truth_from_xy,
    parse_tolerance,
    place_positions,
)
from topoloc.datasets.sources import load_input
from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.evaluation.metrics import Scores, compute_metrics, parse_recall_at
from topoloc.evaluation.plots import plot_pr_curves
from topoloc.evaluation.prepare import build_method, make_resources, resolve_max_side
from topoloc.evaluation.report import render_run_report, run_title
from topoloc.evaluation.timing import apply_sequence, peak_rss_mb, score_queries
from topoloc.evaluation.topk import TopK, compute_metrics_top_k, score_top_k, top_k_of
from topoloc.io.container import atomic_write_bytes
from topoloc.io.dirs import check_output_dir, staged_dir
from topoloc.methods.base import PlaceRecognizer
from topoloc.methods.resources import CachedResources
from topoloc.progress import ProgressFactory, no_progress
from topoloc.progress import stage as progress_stage

log = logging.getLogger(__name__)


@dataclass
class EvaluateOptions:
    """Everything ``topoloc evaluate`` takes (see ``docs/protocol.md``)."""

    method: str
    maps: list[Path]
    query: Path
    out: Path
    vocab: Path | None = None
    vocab_train: list[Path] = field(default_factory=list)
    vocab_words: int = 10000
    tolerance: str = "0:8"
    tolerance_m: str | None = None
    ground_truth: Path | None = None
    sequence: int = 0
    sequence_mode: str = "constant"
    params: dict[str, str] = field(default_factory=dict)
    features: str = "sift"
    max_features: int = 1000
    max_side: str = "auto"
    preprocess: str = "auto"
    cache_dir: Path | None = None
    seed: int = 0
    map_file: Path | None = None
    recall_at: str = "1,5,10"
    top_k: int = 0  # > 0: keep only the K best places per query (S_topk.npz), metrics from them
    html: Path | None = None  # also write the browsable HTML page of this run here
    topic: str | None = None  # ROS bags among maps/query: the image topic
    every_s: float | None = None  # bags and videos: one keyframe every T seconds
    every_m: float | None = None  # bags with poses: one keyframe every D metres
    pose_topic: str | None = None  # bags: the odometry, pose or GPS topic (default: the bag's first)


def _save_npy(path: Path, arr: np.ndarray) -> None:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    atomic_write_bytes(path, buf.getvalue())


def make_ground_truth(
    opts: EvaluateOptions, maps: list[Traverse], query: Traverse, place_ids: np.ndarray,
    map_xy: np.ndarray | None = None,
) -> GroundTruth:
    """Ground truth from ``--ground-truth``, ``--tolerance-m`` or ``--tolerance``.

    ``map_xy`` (shape (n_places, 2)) gives the places' positions when there are no
    map traverses (a saved map); else they are the mean over the map images.
    """
    if opts.ground_truth is not None:
        if not maps:
            raise TopolocError("--ground-truth files index the map's images: use --map tours, not --map-file")
        return ground_truth_from_file(
            opts.ground_truth, map_traverse=maps[0], place_ids=place_ids, n_queries=len(query)
        )
    if opts.tolerance_m is not None:
        hard, soft = parse_tolerance(opts.tolerance_m)
        if query.xy is None:
            raise TopolocError(f"--tolerance-m needs x,y columns in places.csv: {query.root}")
        positions = map_xy if map_xy is not None else place_positions(maps, place_ids)
        return ground_truth_from_xy(positions, query.xy, hard, soft)
    hard, soft = parse_tolerance(opts.tolerance)
    return ground_truth_from_places(place_ids, query.places, hard, soft)


def evaluate(
    opts: EvaluateOptions | None = None, *, progress: ProgressFactory | None = None,
    executor: Executor | None = None, **options: Any
) -> dict[str, Any]:
    """Run ``opts.method`` and write every output file of ``docs/protocol.md`` under ``opts.out``.

    Parameters
    ----------
    opts : EvaluateOptions, optional
        What to run; or give its fields as keyword arguments, e.g.
        ``evaluate(method="bow", maps=[...], query=..., out=..., vocab_train=[...])``.
    progress : ProgressFactory, optional
        Progress bars (the CLI passes rich's).
    executor : Executor, optional
        Where feature extraction and quantisation of image files run
        (:func:`topoloc.cluster.connect`: a Dask cluster, or by default this
        process's threads); the caller closes it.  S is the same either way.

    Returns
    -------
    dict
        The content of ``metrics.json``.
    """
    if opts is None:
        try:
            opts = EvaluateOptions(**options)
        except TypeError as exc:
            raise TopolocError(f"evaluate: {exc}") from None
    elif options:
        raise TopolocError("evaluate: pass either EvaluateOptions or keyword options, not both")
    opts.maps = [Path(m) for m in opts.maps]
    opts.query, opts.out = Path(opts.query), Path(opts.out)
    prog: ProgressFactory = progress or no_progress
    if opts.map_file is not None and opts.maps:
        raise TopolocError("pass either --map tours or --map-file, not both")
    if not opts.maps and opts.map_file is None:
        raise TopolocError("evaluate needs at least one --map traverse (or --map-file)")
    if not opts.method and opts.map_file is None:
        raise TopolocError("evaluate needs --method NAME (see `topoloc methods`), or --map-file")
    # Validate every cheap option before any expensive work starts.
    check_output_dir(opts.out)
    if opts.sequence < 0:
        raise TopolocError(f"--sequence must be >= 0 (0 = off), got {opts.sequence}")
    if opts.sequence_mode not in ("constant", "acceleration"):
        raise TopolocError(f"--sequence-mode must be constant or acceleration, got {opts.sequence_mode!r}")
    parse_tolerance(opts.tolerance)
    recall_at = parse_recall_at(opts.recall_at)
    if opts.top_k < 0:
        raise TopolocError(f"--top-k must be >= 0 (0 = keep the whole S), got {opts.top_k}")
    if opts.top_k and opts.html is not None:
        raise TopolocError("--html draws the whole S: leave out --top-k, or --html")
    if opts.tolerance_m is not None:
        parse_tolerance(opts.tolerance_m)
    if opts.ground_truth is not None and not Path(opts.ground_truth).is_file():
        raise TopolocError(f"ground-truth file not found: {opts.ground_truth}")
    # Folders, or bags and videos (their keyframes in memory: topoloc.datasets.sources).
    loaded = [load_input(p, topic=opts.topic, every_s=opts.every_s, every_m=opts.every_m,
                         pose_topic=opts.pose_topic) for p in [*opts.maps, opts.query]]
    maps, query = loaded[:-1], loaded[-1]
    if opts.sequence >= len(query):
        raise TopolocError(f"--sequence {opts.sequence} needs more than {opts.sequence} queries; "
                           f"{opts.query} has {len(query)}")
    map_xy = None
    if opts.map_file is not None:
        method, resources, vocab_info, map_xy = _saved_map(opts, progress, executor)
        max_side, fit_s = resources.extractor.config.max_side, 0.0
        map_labels = [str(opts.map_file)]
    else:
        method = build_method(opts.method, opts.params)
        if not method.uses_vocabulary and (opts.vocab is not None or opts.vocab_train):
            log.warning("method %s uses no visual vocabulary: --vocab/--vocab-train are ignored", method.name)
        max_side = resolve_max_side(opts.max_side, [*maps, query])
        resources, vocab_info = make_resources(
            vocab=opts.vocab, vocab_train=opts.vocab_train, vocab_words=opts.vocab_words, features=opts.features,
            max_features=opts.max_features, max_side=max_side, preprocess=opts.preprocess,
            cache_dir=opts.cache_dir, seed=opts.seed,
            needs_vocabulary=f"method {method.name!r}" if method.uses_vocabulary else "", progress=progress,
            executor=executor,
        )
        t0 = time.perf_counter()
        with progress_stage(prog, f"fit {method.name} on {sum(len(m) for m in maps)} map images"):
            method.fit(maps, resources=resources)
        # The vocabulary is loaded or trained lazily inside fit: its time is reported apart.
        fit_s = time.perf_counter() - t0 - float(vocab_info.get("seconds_this_run", 0.0))
        map_labels = [str(m) for m in opts.maps]
    place_ids = method.place_ids_
    gt = make_ground_truth(opts, maps, query, place_ids, map_xy)
    check_overlap(gt, query, place_ids)
    items = method.encode(query, resources=resources)
    top: TopK | None = None
    S: np.ndarray | None = None
    if opts.top_k and not opts.sequence:
        top, ms_each = score_top_k(method, items, opts.top_k, prog)
        del items
    else:
        S, ms_each = score_queries(method, items, prog)
        if opts.sequence:
            S, seq_ms = apply_sequence(S, opts.sequence, opts.sequence_mode)
            ms_each = ms_each + seq_ms
        S = np.asarray(S, dtype=np.float32)
        if opts.top_k:  # sequence matching needs neighbouring columns: the dense S is formed first
            top = TopK(*top_k_of(S, opts.top_k), n_places=S.shape[0])
            S = None
    if top is not None:
        scores = compute_metrics_top_k(top, gt, recall_at)
        shape = (top.n_places, top.n_queries)
    else:
        assert S is not None
        scores = compute_metrics(S, gt, recall_at)
        shape = S.shape

    metrics: dict[str, Any] = {
        "method": method.name,
        **scores.as_dict(),
        "ms_per_query": float(np.median(ms_each)) if len(ms_each) else 0.0,
        "ms_features": resources.ms_features_median(),
        "peak_rss_mb": peak_rss_mb(),
        "n_places": int(shape[0]),
        "n_queries": int(shape[1]),
        **({"top_k": top.k} if top is not None else {}),
        "params": {**method.get_params(), "sequence": opts.sequence,
                   **({"sequence_mode": opts.sequence_mode} if opts.sequence else {})},
        "run": {
            "map": map_labels,
            "query": str(opts.query),
            "ground_truth": gt.description,
            "features": {
                "method": resources.extractor.config.method, "max_features": resources.extractor.config.max_features,
                "max_side": max_side, "max_side_option": "map file" if opts.map_file else str(opts.max_side),
                "preprocess": resources.extractor.config.preprocess,
            },
            "vocabulary": vocab_info,
            # "local", or the Dask scheduler the features were extracted and quantised on.
            "executor": resources.executor.name if isinstance(resources, CachedResources) else "local",
            "fit_seconds": fit_s,
            "vocabulary_seconds": float(vocab_info.get("seconds_this_run", 0.0)),
            "ms_per_query_p95": float(np.percentile(ms_each, 95)) if len(ms_each) else 0.0,
            "date": datetime.now(UTC).isoformat(timespec="seconds"),
            "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
        },
    }
    # All files of the run appear together, replacing an earlier run's whole (never a mixture).
    with staged_dir(opts.out) as stage:
        write_outputs(stage, S, place_ids, query.places, metrics, scores, None if top is not None else gt, top=top)
    if opts.html is not None:
        from topoloc.evaluation.html import build_html_report

        build_html_report([opts.out], Path(opts.html), progress=prog)
    return metrics


def check_overlap(gt: GroundTruth, query: Traverse, place_ids: np.ndarray) -> None:
    """Refuse ground truth that gives no query a correct map place; warn (one line) when some have none.

    Such queries count in no recall (they have nothing to find), so a run
    where most queries show places the map lacks would report recall over a
    handful of queries without a word.
    """
    has = np.diff(gt.hard_sparse.indptr) > 0 if gt.is_sparse else np.asarray(gt.hard.any(axis=0))
    if not has.any():
        raise TopolocError(
            f"no query of {query.root} has a correct place in the map (query places "
            f"{int(query.places.min())}..{int(query.places.max())}, map places {int(place_ids.min())}.."
            f"{int(place_ids.max())}): check places.csv and the tolerance")
    if not has.all():
        log.warning("%d of %d queries have no correct place in the map; recall is computed over the other %d",
                    int((~has).sum()), int(has.size), int(has.sum()))


def _saved_map(
    opts: EvaluateOptions, progress: ProgressFactory | None, executor: Executor | None = None
) -> tuple[PlaceRecognizer, CachedResources, dict[str, Any], np.ndarray]:
    """The recogniser, resources, vocabulary record and place positions of ``opts.map_file``.

    A saved map fixes the method, its parameters, the features and the
    vocabulary: options that would change them are refused, not ignored.
    """
    from topoloc.maps import Map

    saved = Map.load(opts.map_file)  # type: ignore[arg-type]
    rec = saved.recognizer
    if opts.method and opts.method != rec.name:
        raise TopolocError(f"--method {opts.method} but the map file holds a {rec.name} map: {opts.map_file}")
    if opts.params or opts.vocab is not None or opts.vocab_train:
        raise TopolocError("a saved map fixes its parameters and vocabulary: --param, --vocab and --vocab-train "
                           f"cannot be used with --map-file {opts.map_file}")
    res = saved._resources(cache_dir=opts.cache_dir, progress=progress, executor=executor)
    voc: dict[str, Any] = {"used": saved.vocabulary is not None}
    if saved.vocabulary is not None:
        voc.update({"file": f"embedded in {opts.map_file}", **saved.vocabulary.provenance_})
    return rec, res, voc, saved.place_xy


def write_outputs(
    out: Path, S: np.ndarray | None, place_ids: np.ndarray, query_places: np.ndarray,
    metrics: dict[str, Any], scores: Scores, gt: GroundTruth | None = None, *, top: TopK | None = None,
) -> None:
    """Write S, ids, metrics, PR curve and report under ``out`` (each file atomically).

    With ``gt``, also ``gt_hard.npy`` / ``gt_soft.npy`` (boolean, the shape of S) for the HTML page.
    With ``top``, ``S_topk.npz`` is written instead of ``S.npy``.
    """
    out.mkdir(parents=True, exist_ok=True)
    if gt is not None:
        _save_npy(out / "gt_hard.npy", np.asarray(gt.hard, dtype=bool))
        _save_npy(out / "gt_soft.npy", np.asarray(gt.soft, dtype=bool))
    if top is not None:
        top.save(out / "S_topk.npz")
    if S is not None:
        _save_npy(out / "S.npy", S.astype(np.float32))
    _save_npy(out / "places.npy", np.asarray(place_ids, dtype=np.int64))
    _save_npy(out / "queries.npy", np.asarray(query_places, dtype=np.int64))
    atomic_write_bytes(out / "metrics.json", (json.dumps(metrics, indent=2, default=str) + "\n").encode())
    pr = "precision,recall\n" + "".join(
        f"{p:.6f},{r:.6f}\n" for p, r in zip(scores.precision, scores.recall, strict=True)
    )
    atomic_write_bytes(out / "pr.csv", pr.encode())
    label = f"{metrics['method']} (AUC {metrics['auc']:.2f})"
    plot_pr_curves([(label, scores.precision, scores.recall)], out / "pr.png",
                   title=run_title(metrics))
    atomic_write_bytes(out / "report.md", render_run_report(metrics).encode())


