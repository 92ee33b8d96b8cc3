"""Synthetic Cooc-Map of the paper's size and localisation timings (``topoloc bench coocmap``).

Synthetic data
--------------
Each location is a scene of ``2 * features`` physical points, each with a
visual word and a position on a 640 x 480 image.  Words follow a Zipf law of
exponent ``zipf`` over a seeded permutation of the vocabulary; the default
0.5 matches the word statistics we measured on Gardens Point (SIFT, 10,000
words trained on webcam_daynight): sum of squared word probabilities 2.7e-4
(Zipf 0.5: 2.5e-4), most frequent word 0.29 % of features (0.50 %).
Positions are clustered like real keypoints: 70 % around 8 blob centres
(Gaussian, sigma 40 px), 30 % uniform.  A tour (time of day) observes
``features`` of the points, drawn with weights that drift smoothly with the
time of day (points seen by day fade at night), with 2 px position jitter and
15 % of the words re-quantised at random (the noise of quantisation).  A query
is a further observation of a random location at a random time between
tours.  The map keeps positions on a 64 x 64 lattice (``position_bits=6``,
the method's default).  Timings exclude feature extraction, as in the paper (Sec. IV, 82 ms
per localisation for 2,200 locations, with sequence matching).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from topoloc.coocmap.matching import (
    consistency_graphs,
    match_best_first,
    match_lazy,
    match_sequential,
    match_simultaneous,
)
from topoloc.coocmap.model import CoocModel
from topoloc.coocmap.spatial import normalise_xy

_SHAPE = (480, 640)


def _scene(rng: np.random.Generator, n_points: int, word_p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    words = rng.choice(len(word_p), size=n_points, p=word_p)
    n_blob = int(0.7 * n_points)
    centres = rng.uniform([40, 40], [600, 440], (8, 2))
    blob = centres[rng.integers(0, 8, n_blob)] + rng.normal(0, 40, (n_blob, 2))
    uni = rng.uniform([0, 0], [640, 480], (n_points - n_blob, 2))
    xy = np.clip(np.r_[blob, uni], [0, 0], [639, 479])
    return words, xy


def _observe(rng: np.random.Generator, scene: tuple[np.ndarray, np.ndarray], phase: np.ndarray,
             hour: float, n: int, word_p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    words, xy = scene
    # Visibility drifts smoothly with the time of day: each point has a preferred hour.
    d = np.minimum(np.abs(phase - hour), 24 - np.abs(phase - hour))
    w = np.exp(-0.5 * (d / 4.0) ** 2) + 1e-3
    idx = rng.choice(len(words), size=min(n, len(words)), replace=False, p=w / w.sum())
    ow = words[idx].copy()
    noisy = rng.random(len(idx)) < 0.15
    ow[noisy] = rng.choice(len(word_p), size=int(noisy.sum()), p=word_p)
    oxy = xy[idx] + rng.normal(0, 2.0, (len(idx), 2))
    return ow.astype(np.int64), normalise_xy(oxy, _SHAPE)


def synthetic_map(*, locations: int = 2200, tours: int = 5, features: int = 500,
                  n_words: int = 10000, n_queries: int = 20, zipf: float = 0.5,
                  grid_x: int = 12, grid_y: int = 8, interpolate: bool = True,
                  position_bits: int = 6, seed: int = 0) -> tuple[CoocModel, list[tuple[int, np.ndarray, np.ndarray]]]:
    """Build a synthetic map and queries (see the module docstring).

    Returns
    -------
    model : CoocModel
    queries : list of (true location, words (n,), normalised xy (n, 2))
    """
    rng = np.random.default_rng(seed)
    ranks = np.arange(1, n_words + 1, dtype=np.float64) ** -zipf
    word_p = np.empty(n_words)
    word_p[rng.permutation(n_words)] = ranks / ranks.sum()
    scenes = [_scene(rng, 2 * features, word_p) for _ in range(locations)]
    phases = [rng.uniform(0, 24, 2 * features) for _ in range(locations)]
    hours = np.linspace(8, 22, tours) if tours > 1 else np.array([14.0])
    obs = [[(loc, *_observe(rng, scenes[loc], phases[loc], float(h), features, word_p))
            for loc in range(locations)] for h in hours]
    model = CoocModel.build(obs, n_locations=locations, n_words=n_words, grid_x=grid_x,
                            grid_y=grid_y, interpolate=interpolate, position_bits=position_bits,
                            tour_names=[f"h{h:.0f}" for h in hours], tour_hours=list(map(float, hours)))
    queries = []
    for _ in range(n_queries):
        loc = int(rng.integers(0, locations))
        h = float(rng.uniform(hours[0], hours[-1]))
        queries.append((loc, *_observe(rng, scenes[loc], phases[loc], h, features, word_p)))
    return model, queries


def bench_coocmap(*, locations: int = 2200, tours: int = 5, features: int = 500,
                  n_words: int = 10000, n_queries: int = 20, zipf: float = 0.5,
                  top_k: int = 1, compare: int = 3, position_bits: int = 6,
                  seed: int = 0) -> dict[str, Any]:
    """Time localisation against a synthetic map of the paper's size.

    Headline (every query): :func:`match_lazy`, the method's default, from
    the query's words and positions to the scores of all locations
    (candidate look-up, ``J_i`` of the locations that can still win,
    elimination).  On the first ``compare`` queries the ``J_i`` of *all*
    locations are also built (:func:`consistency_graphs`) and matched
    (a) to completion (``prune=False``), (b) with the paper's simultaneous
    rounds and bounds (Sec. II-D), (c) best-first, and (d) with the plain
    per-location reference (:func:`match_sequential`), to measure the
    speed-up of II-D and check that all agree on the best location.

    Returns
    -------
    dict
        ``ms_per_query_median``, ``ms_per_query_p95`` (headline),
        ``ms_graphs_all_median`` (building every ``J_i``),
        ``ms_match_complete_median``, ``ms_match_rounds_median``,
        ``ms_match_best_first_median`` (elimination only),
        ``ms_per_query_rounds_median`` (all ``J_i`` + the paper's rounds),
        ``ms_per_query_best_first_median`` (all ``J_i`` + best-first),
        ``speedup_vs_sequential`` (complete / rounds, elimination time),
        ``speedup_steps`` (complete / rounds, elimination steps),
        ``speedup_best_first``, ``speedup_steps_best_first``,
        ``speedup_lazy`` (all ``J_i`` + complete matching, over the headline),
        ``best_matches_agree`` (lazy == rounds == best-first == complete ==
        reference), ``recall_at_1``, ``map_bytes``, ``bytes_per_location``,
        ``explicit_keys_bytes_per_location`` (``M_i`` as int64 keys,
        estimated on 3 locations), ``build_s`` and the settings.
    """
    t0 = time.perf_counter()
    model, queries = synthetic_map(locations=locations, tours=tours, features=features,
                                   n_words=n_words, n_queries=n_queries, zipf=zipf,
                                   position_bits=position_bits, seed=seed)
    build_s = time.perf_counter() - t0
    lazy_ms: list[float] = []
    graphs_ms: list[float] = []
    full_ms: list[float] = []
    rounds_ms: list[float] = []
    bf_ms: list[float] = []
    full_steps: list[float] = []
    rounds_steps: list[float] = []
    bf_steps: list[float] = []
    agree = True
    hits = 0
    for qi, (loc, w, xy) in enumerate(queries):
        t = time.perf_counter()
        lazy = match_lazy(model, w, xy, top_k=top_k, seed=seed)
        lazy_ms.append(1e3 * (time.perf_counter() - t))
        hits += lazy.best == loc
        if qi >= compare:
            continue
        t = time.perf_counter()
        g = consistency_graphs(model, w, xy, seed=seed)
        graphs_ms.append(1e3 * (time.perf_counter() - t))
        full = match_simultaneous(g, prune=False)
        rounds = match_simultaneous(g, top_k=top_k)
        bf = match_best_first(g, top_k=top_k)
        ref = match_sequential(g)
        for r, ms, st in [(full, full_ms, full_steps), (rounds, rounds_ms, rounds_steps),
                          (bf, bf_ms, bf_steps)]:
            ms.append(1e3 * r.seconds)
            st.append(r.steps)
        agree &= lazy.best == rounds.best == bf.best == full.best == ref.best
    sample = np.linspace(0, locations - 1, min(3, locations)).astype(int)
    explicit = float(np.mean([8 * len(model.pair_keys(int(i))) for i in sample])) if locations else 0.0

    def med(x: list[float]) -> float:
        return float(np.median(x)) if x else float("nan")

    def ratio(a: list[float], b: list[float]) -> float:
        return float(np.sum(a) / max(np.sum(b), 1e-9)) if a else float("nan")

    return {
        "locations": locations, "tours": tours, "features": features, "n_words": n_words,
        "spatial_words": model.n_spatial, "n_queries": n_queries, "zipf": zipf, "top_k": top_k,
        "position_bits": position_bits, "compare": min(compare, n_queries),
        "ms_per_query_median": med(lazy_ms),
        "ms_per_query_p95": float(np.percentile(lazy_ms, 95)) if lazy_ms else float("nan"),
        "ms_graphs_all_median": med(graphs_ms),
        "ms_match_complete_median": med(full_ms),
        "ms_match_rounds_median": med(rounds_ms),
        "ms_match_best_first_median": med(bf_ms),
        "ms_per_query_rounds_median": med([a + b for a, b in zip(graphs_ms, rounds_ms, strict=True)]),
        "ms_per_query_best_first_median": med([a + b for a, b in zip(graphs_ms, bf_ms, strict=True)]),
        "speedup_vs_sequential": ratio(full_ms, rounds_ms),
        "speedup_steps": ratio(full_steps, rounds_steps),
        "speedup_best_first": ratio(full_ms, bf_ms),
        "speedup_steps_best_first": ratio(full_steps, bf_steps),
        "speedup_lazy": ratio([a + b for a, b in zip(graphs_ms, full_ms, strict=True)],
                              lazy_ms[:len(graphs_ms)]),
        "best_matches_agree": bool(agree),
        "recall_at_1": hits / max(n_queries, 1),
        "map_bytes": model.nbytes,
        "bytes_per_location": model.bytes_per_location,
        "explicit_keys_bytes_per_location": explicit,
        "features_stored": model.n_features,
        "build_s": build_s,
    }
