"""Map density versus frame rate (Johns & Yang 2011, Sec. VIII, Fig. 5-6).

For each map density (every ``stride``-th image of the map traverse is a
node) the landmark map and the image-voting map are built and every query
image is localised.  :func:`density_experiment` reports the localisation rate
(frames per second, feature extraction excluded, wall clock) and the share of
queries whose best node is within ``tolerance`` places of the truth.

:func:`frame_rate_sweep` is the paper's comparison on real data: per map
density and method configuration it measures the single-threaded CPU time of
matching one query and of extracting its features, and scores ``S`` with the
metrics of ``topoloc evaluate`` against the ground truth of the sparser map
(:func:`nearest_node_ground_truth`); :func:`densest_within_budget` then picks,
per method, the densest map that still runs at a given frame rate.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.datasets.groundtruth import GroundTruth
from topoloc.datasets.traverse import Traverse, load_traverse
from topoloc.methods.base import PlaceRecognizer
from topoloc.methods.image_voting import ImageVoting
from topoloc.methods.landmark_map import LandmarkMap
from topoloc.resources import CachedResources, Resources

log = logging.getLogger(__name__)


def _subsample(t: Traverse, stride: int) -> Traverse:
    return t.take(np.arange(0, len(t), stride))


def density_experiment(
    route_dir_or_traverses: str | Path | Sequence[str | Path],
    *,
    strides: Sequence[int] = (1, 2, 5),
    tolerance: int | None = None,
    methods: Sequence[str] = ("landmarks", "voting"),
    params: dict[str, dict[str, Any]] | None = None,
    resources: Resources | None = None,
    max_queries: int | None = None,
) -> list[dict[str, Any]]:
    """Frames per second and correct-localisation rate per map density and method.

    Parameters
    ----------
    route_dir_or_traverses : path or sequence of paths
        A route folder whose first two sub-folders (sorted) are the map and
        the query traverse, or explicit ``(map, query)`` traverse folders.
    strides : sequence of int
        Every ``stride``-th map image is a node (1: every frame).
    tolerance : int, optional
        A query is correctly localised when ``|best place - true place| <=
        tolerance``; default ``max(strides)`` // 2 + 1 place ids, so that a
        sparse map can be right at all.
    methods : sequence of {"landmarks", "voting"}
    params : dict, optional
        Constructor keywords per method name.
    resources : Resources, optional
        Shared feature cache (default: SIFT, 1000 features).
    max_queries : int, optional
        Use only the first queries (shorter runs).

    Returns
    -------
    list of dict
        ``{"method", "stride", "nodes", "nodes_per_m" (None without x,y),
        "fps", "ms_per_query", "correct_rate", "n_queries"}`` per method and stride.
    """
    if isinstance(route_dir_or_traverses, (str, Path)):
        root = Path(route_dir_or_traverses)
        dirs = sorted(p for p in root.iterdir() if p.is_dir())
        if len(dirs) < 2:
            from topoloc.errors import TopolocError

            raise TopolocError(f"density_experiment needs two traverse folders under {root}")
        map_dir, query_dir = dirs[0], dirs[1]
    else:
        map_dir, query_dir = (Path(p) for p in route_dir_or_traverses)
    full_map, query = load_traverse(map_dir), load_traverse(query_dir)
    if max_queries is not None:
        query = Traverse(root=query.root, images=query.images[:max_queries],
                         places=query.places[:max_queries], name=query.name)
    res = resources or CachedResources()
    tol = tolerance if tolerance is not None else max(strides) // 2 + 1
    classes: dict[str, type[PlaceRecognizer]] = {"landmarks": LandmarkMap, "voting": ImageVoting}
    rows: list[dict[str, Any]] = []
    for stride in strides:
        m = _subsample(full_map, stride)
        length_m = None
        route_xy = full_map.xy
        if route_xy is not None and len(route_xy) > 1:
            step = np.diff(route_xy, axis=0)
            length_m = float(np.sum(np.hypot(step[:, 0], step[:, 1])))
        for name in methods:
            method = classes[name](**(params or {}).get(name, {}))
            method.fit([m], resources=res)
            items = method.encode(query, resources=res)
            ms = np.empty(len(items))
            cols = []
            for j, item in enumerate(items):
                t0 = time.perf_counter()
                cols.append(method.score([item]))
                ms[j] = 1e3 * (time.perf_counter() - t0)
            S = np.concatenate(cols, axis=1)
            best = method.place_ids_[np.argmax(S, axis=0)]
            med = float(np.median(ms))
            rows.append({
                "method": name, "stride": int(stride), "nodes": len(m),
                "nodes_per_m": (len(m) / length_m) if length_m else None,
                "fps": 1e3 / med if med > 0 else float("inf"), "ms_per_query": med,
                "correct_rate": float(np.mean(np.abs(best - query.places) <= tol)),
                "n_queries": len(items),
            })
    return rows


# -- equal frame rate on real data (issue 12) ------------------------------------------------------

#: Method configurations of :func:`frame_rate_sweep`: ``(label, method name, constructor keywords)``.
Config = tuple[str, str, dict[str, Any]]

#: The rates a row of :func:`frame_rate_sweep` reports, by key.
RATE_KEYS = ("fps_match_cpu", "fps_total_cpu", "fps_total_cpu_2cores", "fps_match_wall", "fps_total_wall")


def nearest_node_ground_truth(gt: GroundTruth, nodes: np.ndarray) -> GroundTruth:
    """Ground truth of a sparser map whose nodes are rows ``nodes`` of the full map.

    Every full-map row is represented by its nearest node(s) along the route
    (both on a tie), so a node is right (soft) for a query when a row it
    represents is right (soft) for it.  With every map image a node this is
    ``gt`` itself; with every ``k``-th image and a place tolerance ``h:s`` a
    node is right within ``h + k // 2`` places, so that every query that has
    a correct image keeps a correct node and a sparse map can be right at all
    (the paper, Sec. VIII, reports the share of correctly identified locations
    without saying how a sparse map is judged).

    Parameters
    ----------
    gt : GroundTruth, shape (n_full, n_queries)
        Ground truth of the full map (rows in route order).
    nodes : ndarray of int, shape (n_nodes,)
        Ascending rows of the full map that are nodes.

    Returns
    -------
    GroundTruth, shape (n_nodes, n_queries)

    Raises
    ------
    ValueError
        For empty, unsorted or out-of-range ``nodes``.
    """
    nodes = np.asarray(nodes, np.int64)
    n_full = gt.shape[0]
    if nodes.ndim != 1 or len(nodes) == 0 or np.any(np.diff(nodes) <= 0) or nodes[0] < 0 or nodes[-1] >= n_full:
        raise ValueError(f"nodes must be ascending rows of the {n_full}-row map, got {nodes[:5]}...")
    d = np.abs(nodes[:, None] - np.arange(n_full)[None, :])
    cover = (d == d.min(axis=0, keepdims=True)).astype(np.int64)  # (n_nodes, n_full)
    hard = (cover @ gt.hard.astype(np.int64)) > 0
    soft = (cover @ gt.soft.astype(np.int64)) > 0
    return GroundTruth(hard, soft, f"{gt.description}, each map image represented by its nearest node")


def _per_place(gt: GroundTruth, image_places: np.ndarray, place_ids: np.ndarray) -> GroundTruth:
    """Ground truth of map images, shape (n_images, n_queries), as rows of ``S``: one per place of ``place_ids``."""
    if len(image_places) == len(place_ids) and np.array_equal(image_places, place_ids):
        return gt
    member = (np.asarray(place_ids)[:, None] == np.asarray(image_places)[None, :]).astype(np.int64)
    return GroundTruth((member @ gt.hard.astype(np.int64)) > 0, (member @ gt.soft.astype(np.int64)) > 0,
                       gt.description)


@contextlib.contextmanager
def single_threaded() -> Iterator[None]:
    """OpenCV, faiss and the BLAS/OpenMP pools on one thread, restored on exit.

    ``time.process_time()`` then measures one core's work per query, which
    other processes on the machine change far less than wall-clock time.
    """
    import cv2
    import faiss
    from threadpoolctl import threadpool_limits

    n_cv, n_faiss = cv2.getNumThreads(), faiss.omp_get_max_threads()
    cv2.setNumThreads(1)
    faiss.omp_set_num_threads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        cv2.setNumThreads(n_cv)
        faiss.omp_set_num_threads(n_faiss)


def _map_elements(method: PlaceRecognizer) -> int:
    """What one query is matched against: landmarks of a landmark map, descriptors of a voting map."""
    if isinstance(method, LandmarkMap):
        return int(method.model_.n_landmarks_)
    if isinstance(method, ImageVoting):
        return int(method.index_.ntotal)
    return 0


def _rate(ms: float) -> float:
    return 1e3 / ms if ms > 0 else float("inf")


def frame_rate_sweep(
    map_traverse: Traverse,
    query: Traverse,
    ground_truth: GroundTruth,
    *,
    resources: Resources,
    strides: Sequence[int] = (1, 2, 3, 4, 5, 10),
    configs: Sequence[Config] = (("landmarks", "landmarks", {}), ("voting", "voting", {})),
    fixed_tolerance: int | None = None,
    log_progress: bool = True,
) -> list[dict[str, Any]]:
    """Per-query time and accuracy of each method configuration at each map density.

    Every ``stride``-th image of ``map_traverse`` is a node; each configuration
    is fitted on those nodes and localises every query, one at a time, on one
    thread (:func:`single_threaded`).  The query's feature extraction is timed
    apart, once per query (it does not depend on the map), on the pixels read
    beforehand, with the settings of ``resources`` -- what a robot pays per
    camera frame before matching.  Accuracy: :func:`topoloc.evaluation.metrics.compute_metrics`
    of ``S`` against :func:`nearest_node_ground_truth` of the nodes.

    Parameters
    ----------
    map_traverse, query : Traverse
        Map tour (every image a place, in route order) and query traverse.
    ground_truth : GroundTruth, shape (len(map_traverse), len(query))
        Ground truth of every map image (rows in route order) for every query;
        with one image per place, the one ``topoloc evaluate`` builds.
    resources : Resources
        Features of map and query (their extractor settings are the ones timed).
    strides : sequence of int
        Map densities: every ``stride``-th image a node (1: every frame).
    configs : sequence of (label, method, params)
        Configurations to run; ``method`` in {"landmarks", "voting"}.
    fixed_tolerance : int, optional
        Place ids within which the best place counts as right for
        ``correct_rate``, the same at every density (default
        ``max(strides) // 2``, so that the sparsest map can be right everywhere).
    log_progress : bool
        One INFO line per fitted configuration.

    Returns
    -------
    list of dict
        One row per stride and configuration: ``label``, ``method``,
        ``params``, ``stride``, ``nodes``; ``error`` (and nothing more) when the
        configuration cannot be built on those nodes; else ``map_elements`` (landmarks or
        indexed descriptors), ``fit_s``; medians over queries of the
        milliseconds ``ms_match_cpu``, ``ms_match_wall``, ``ms_extract_cpu``,
        ``ms_extract_wall``, ``ms_total_cpu`` (extraction + matching of the
        same query), ``ms_total_wall``; the rates of :data:`RATE_KEYS`
        (``fps_total_cpu_2cores``: two frames at a time, one per core);
        ``auc``, ``recall_at_100_precision``, ``recall_at_1``, ``recall_at_5``,
        ``n_queries``, ``n_queries_with_match``; ``correct_rate``, the share of
        queries whose best place is within ``fixed_tolerance`` place ids of
        the truth (Fig. 6's "correct localisation"), and ``fixed_tolerance``.

    Raises
    ------
    TopolocError
        For a ground truth of the wrong shape, a stride < 1 or an unknown method,
        before any work.
    """
    from topoloc.errors import TopolocError
    from topoloc.evaluation.metrics import compute_metrics
    from topoloc.features import extract_features

    classes: dict[str, type[PlaceRecognizer]] = {"landmarks": LandmarkMap, "voting": ImageVoting}
    if ground_truth.shape != (len(map_traverse), len(query)):
        raise TopolocError(f"ground truth has shape {ground_truth.shape}, expected (map images, queries) = "
                           f"{(len(map_traverse), len(query))} for {map_traverse.root} and {query.root}")
    if not strides or min(strides) < 1:
        raise TopolocError(f"strides must be >= 1, got {list(strides)}")
    unknown = sorted({m for _, m, _ in configs} - set(classes))
    if unknown:
        raise TopolocError(f"frame_rate_sweep runs {', '.join(classes)}, not {', '.join(unknown)}")
    fixed = max(strides) // 2 if fixed_tolerance is None else int(fixed_tolerance)
    config = resources.extractor.config
    resources.features(query)  # extracted (or read from the cache) once, before anything is timed
    ext_cpu = np.empty(len(query))
    ext_wall = np.empty(len(query))
    with single_threaded():
        for j in range(len(query)):
            pixels = query.read(j)
            c0, w0 = time.process_time(), time.perf_counter()
            extract_features(pixels, config)
            ext_cpu[j] = 1e3 * (time.process_time() - c0)
            ext_wall[j] = 1e3 * (time.perf_counter() - w0)
    rows: list[dict[str, Any]] = []
    for stride in strides:
        nodes = np.arange(0, len(map_traverse), stride)
        m = _subsample(map_traverse, stride)
        gt = nearest_node_ground_truth(ground_truth, nodes)
        for label, name, params in configs:
            method = classes[name](**params)
            t0 = time.perf_counter()
            try:
                method.fit([m], resources=resources)
            except TopolocError as exc:
                # A sparse map can leave a configuration nothing to build (no track as long as
                # landmarks' min_track_length): a row saying so, never a silent gap.
                log.warning("%s stride %d: %s", label, stride, exc)
                rows.append({"label": label, "method": name, "params": dict(params), "stride": int(stride),
                             "nodes": len(m), "error": str(exc)})
                continue
            fit_s = time.perf_counter() - t0
            items = method.encode(query, resources=resources)
            cpu = np.empty(len(items))
            wall = np.empty(len(items))
            cols = []
            with single_threaded():
                method.score(items[:1])  # first-call set-up (index, caches) is not a per-frame cost
                for j, item in enumerate(items):
                    c0, w0 = time.process_time(), time.perf_counter()
                    cols.append(method.score([item]))
                    cpu[j] = 1e3 * (time.process_time() - c0)
                    wall[j] = 1e3 * (time.perf_counter() - w0)
            S = np.concatenate(cols, axis=1)
            gt_rows = _per_place(gt, m.places, method.place_ids_)
            sc = compute_metrics(S, gt_rows)
            ms = {"match_cpu": float(np.median(cpu)), "match_wall": float(np.median(wall)),
                  "extract_cpu": float(np.median(ext_cpu)), "extract_wall": float(np.median(ext_wall)),
                  "total_cpu": float(np.median(cpu + ext_cpu)), "total_wall": float(np.median(wall + ext_wall))}
            row: dict[str, Any] = {
                "label": label, "method": name, "params": dict(params), "stride": int(stride),
                "nodes": len(m), "map_elements": _map_elements(method), "fit_s": fit_s,
                **{f"ms_{k}": v for k, v in ms.items()},
                "fps_match_cpu": _rate(ms["match_cpu"]), "fps_total_cpu": _rate(ms["total_cpu"]),
                "fps_total_cpu_2cores": 2.0 * _rate(ms["total_cpu"]),
                "fps_match_wall": _rate(ms["match_wall"]), "fps_total_wall": _rate(ms["total_wall"]),
                "auc": sc.auc, "recall_at_100_precision": sc.recall_at_100_precision,
                "recall_at_1": sc.recall_at_1, "recall_at_5": sc.recall_at_5,
                "n_queries": len(items), "n_queries_with_match": int(gt_rows.hard.any(axis=0).sum()),
                "correct_rate": float(np.mean(np.abs(method.place_ids_[np.argmax(S, axis=0)] - query.places) <= fixed)),
                "fixed_tolerance": fixed,
            }
            rows.append(row)
            if log_progress:
                log.info("%s stride %d: %d nodes, %.1f ms/query CPU (+ %.1f ms features), AUC %.3f, R@1 %.3f",
                         label, stride, len(m), row["ms_match_cpu"], row["ms_extract_cpu"], sc.auc, sc.recall_at_1)
    return rows


def densest_within_budget(
    rows: Sequence[dict[str, Any]], *, fps: float, rate: str = "fps_total_cpu"
) -> dict[str, dict[str, Any] | None]:
    """Per method, the densest measured map that localises at ``fps`` frames/s or faster.

    Densest: most nodes, then most map elements (a landmark configuration
    that keeps more landmarks per node is the denser map), then the smaller
    stride.  This is the paper's choice at equal frame rate (Sec. VIII).

    Parameters
    ----------
    rows : sequence of dict
        Rows of :func:`frame_rate_sweep` (``method``, ``nodes``,
        ``map_elements``, ``stride`` and the ``rate`` key; rows with an
        ``error`` are never chosen).
    fps : float
        The frame-rate budget, > 0.
    rate : str
        Which measured rate must meet it (one of :data:`RATE_KEYS`).

    Returns
    -------
    dict
        Method name -> its chosen row, or None when no measured map of the
        method is fast enough; methods in order of first appearance.

    Raises
    ------
    ValueError
        For ``fps <= 0`` or a row without the ``rate`` key.
    """
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    out: dict[str, dict[str, Any] | None] = {}
    for r in rows:
        out.setdefault(r["method"], None)
        if "error" in r:
            continue
        if rate not in r:
            raise ValueError(f"row of {r.get('label', r.get('method'))} has no {rate!r}")
        name = r["method"]
        if r[rate] < fps:
            continue
        best = out[name]
        key = (r["nodes"], r["map_elements"], -r["stride"])
        if best is None or key > (best["nodes"], best["map_elements"], -best["stride"]):
            out[name] = r
    return out


def nodes_at_rate(rows: Sequence[dict[str, Any]], *, label: str, fps: float,
                  ms_key: str = "ms_total_cpu") -> float | None:
    """Map size (nodes) at which configuration ``label`` would fall to ``fps``, by a straight-line fit.

    ``ms = a + b * nodes`` is fitted by least squares to the configuration's
    rows; the answer ``(1000 / fps - a) / b`` is an extrapolation beyond the
    measured map sizes (None when the time does not grow with the nodes or
    fewer than two sizes were measured; 0 when even ``a`` misses the budget).
    """
    mine = [r for r in rows if r["label"] == label and "error" not in r]
    n = np.array([r["nodes"] for r in mine], np.float64)
    ms = np.array([r[ms_key] for r in mine], np.float64)
    if len(np.unique(n)) < 2:
        return None
    b, a = np.polyfit(n, ms, 1)
    if b <= 0:
        return None
    return max(0.0, float((1e3 / fps - a) / b))
