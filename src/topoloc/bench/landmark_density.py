"""Map density versus frame rate (Johns & Yang 2011, Sec. VIII, Fig. 5-6).

For each map density (every ``stride``-th image of the map traverse is a
node) the landmark map and the image-voting map are built and every query
image is localised; reported are the localisation rate (frames per second,
feature extraction excluded) and the share of queries whose best node is
within ``tolerance`` places of the truth.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.datasets.traverse import Traverse, load_traverse
from topoloc.methods.base import PlaceRecognizer
from topoloc.methods.image_voting import ImageVoting
from topoloc.methods.landmark_map import LandmarkMap
from topoloc.methods.resources import CachedResources, Resources


def _subsample(t: Traverse, stride: int) -> Traverse:
    idx = np.arange(0, len(t), stride)
    return Traverse(root=t.root, images=tuple(t.images[i] for i in idx), places=t.places[idx],
                    times=None if t.times is None else t.times[idx],
                    xy=None if t.xy is None else t.xy[idx], name=t.name)


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
