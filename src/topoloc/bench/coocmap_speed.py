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
from topoloc.errors import TopolocError

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

    Headline (every query): :func:`~topoloc.coocmap.compiled.match_compiled`,
    the method's default, from the query's words and positions to the scores
    of all locations (candidate look-up, ``J_i`` of the locations that can
    still win, elimination); :func:`match_lazy` (the previous default, same
    result) is timed on every query too (``ms_lazy_median``, ``ms_lazy_p95``).
    On the first ``compare`` queries the ``J_i`` of *all* locations are also
    built (:func:`consistency_graphs`) and matched (a) to completion
    (``prune=False``), (b) with the paper's simultaneous rounds and bounds
    (Sec. II-D), (c) best-first, and (d) with the plain per-location
    reference (:func:`match_sequential`), to measure the speed-up of II-D
    and check that all agree on the best location.

    Returns
    -------
    dict
        ``ms_per_query_median``, ``ms_per_query_p95`` (headline),
        ``ms_lazy_median``, ``ms_lazy_p95``,
        ``ms_graphs_all_median`` (building every ``J_i``),
        ``ms_match_complete_median``, ``ms_match_rounds_median``,
        ``ms_match_best_first_median`` (elimination only),
        ``ms_per_query_rounds_median`` (all ``J_i`` + the paper's rounds),
        ``ms_per_query_best_first_median`` (all ``J_i`` + best-first),
        ``speedup_vs_sequential`` (complete / rounds, elimination time),
        ``speedup_steps`` (complete / rounds, elimination steps),
        ``speedup_best_first``, ``speedup_steps_best_first``,
        ``speedup_lazy`` (all ``J_i`` + complete matching, over the headline),
        ``best_matches_agree`` (compiled == lazy == rounds == best-first == complete ==
        reference), ``recall_at_1``, ``map_bytes``, ``bytes_per_location``,
        ``explicit_keys_bytes_per_location`` (``M_i`` as int64 keys,
        estimated on 3 locations), ``build_s`` and the settings.
    """
    t0 = time.perf_counter()
    model, queries = synthetic_map(locations=locations, tours=tours, features=features,
                                   n_words=n_words, n_queries=n_queries, zipf=zipf,
                                   position_bits=position_bits, seed=seed)
    build_s = time.perf_counter() - t0
    from topoloc.coocmap.compiled import match_compiled

    if queries:
        match_compiled(model, queries[0][1], queries[0][2], top_k=top_k, seed=seed)  # compile / load the kernel
    comp_ms: list[float] = []
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
        comp, _ = match_compiled(model, w, xy, top_k=top_k, seed=seed)
        comp_ms.append(1e3 * (time.perf_counter() - t))
        t = time.perf_counter()
        lazy = match_lazy(model, w, xy, top_k=top_k, seed=seed)
        lazy_ms.append(1e3 * (time.perf_counter() - t))
        hits += comp.best == loc
        agree &= comp.best == lazy.best
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
        "benchmark": "synthetic",
        "ms_per_query_median": med(comp_ms),
        "ms_per_query_p95": float(np.percentile(comp_ms, 95)) if comp_ms else float("nan"),
        "ms_lazy_median": med(lazy_ms),
        "ms_lazy_p95": float(np.percentile(lazy_ms, 95)) if lazy_ms else float("nan"),
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


# -- real images --------------------------------------------------------------------------------
#: Version of the image variants below; part of the feature cache key.
_VARIANT_VERSION = 2
#: Longer side of every variant (a crop is resampled to it): gardens_point's common scale.
VARIANT_SIDE = 640


Box = tuple[int, int, int, int]


def real_locations(images: list[Any], shapes: list[tuple[int, int]], n_locations: int) -> list[tuple[int, Box]]:
    """One ``(image index, crop box x, y, w, h)`` per location.

    With at least as many images as locations, one whole image per location
    (evenly spread over the images).  Otherwise every image gives ``c =
    ceil(locations / images)`` distinct crops of half its width and height on
    a regular grid (2 rows when ``c > 2``, columns evenly spaced; neighbouring
    crops of one image overlap by at most half a crop), and the first
    ``locations`` crops in image order are used.
    """
    n = len(images)
    if n == 0 or n_locations <= 0:
        return []
    if n >= n_locations:
        pick = np.linspace(0, n - 1, n_locations).round().astype(int)
        return [(int(i), (0, 0, shapes[i][1], shapes[i][0])) for i in pick]
    c = -(-n_locations // n)
    rows = 1 if c <= 2 else 2
    cols = -(-c // rows)
    out: list[tuple[int, Box]] = []
    for i in range(n):
        h, w = shapes[i]
        cw, ch = w // 2, h // 2 if rows == 2 else h
        xs = np.linspace(0, w - cw, cols).round().astype(int) if cols > 1 else np.array([(w - cw) // 2])
        ys = np.linspace(0, h - ch, rows).round().astype(int) if rows > 1 else np.array([(h - ch) // 2])
        boxes = [(int(x), int(y), cw, ch) for y in ys for x in xs][:c]
        out.extend((i, b) for b in boxes)
    return out[:n_locations]


def image_variant(image: np.ndarray, box: Box, rng: np.random.Generator, side: int = 0) -> np.ndarray:
    """A seeded re-observation of the crop ``box`` of ``image`` (grey uint8).

    Viewpoint: scale 0.9-1.1, rotation +-3 deg and a shift of +-5 % of the
    crop about its centre (taken from the whole image, reflected at its
    borders); appearance: brightness x0.7-1.3, gamma 0.7-1.4, Gaussian blur
    sigma 0-1.5 px, Gaussian noise sigma 0-6 grey levels.  The result has
    the crop's size, or its aspect with longer side ``side`` when given.
    """
    import cv2

    x, y, w, h = box
    zoom = side / max(w, h) if side else 1.0
    ow, oh = max(round(w * zoom), 1), max(round(h * zoom), 1)
    s = rng.uniform(0.9, 1.1) * zoom
    th = np.deg2rad(rng.uniform(-3, 3))
    shift = rng.uniform(-0.05, 0.05, 2) * (w, h)
    c, si = np.cos(th) / s, np.sin(th) / s
    cx, cy = x + w / 2 + shift[0], y + h / 2 + shift[1]
    # Output pixel (u, v) samples the source at centre + R (u - ow/2, v - oh/2) / s.
    M = np.array([[c, -si, cx - c * ow / 2 + si * oh / 2], [si, c, cy - si * ow / 2 - c * oh / 2]])
    out = cv2.warpAffine(image, M, (ow, oh), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_REFLECT).astype(np.float32)
    out = 255.0 * np.clip(out * rng.uniform(0.7, 1.3) / 255.0, 0, 1) ** rng.uniform(0.7, 1.4)
    sigma = rng.uniform(0, 1.5)
    if sigma > 0.3:
        out = cv2.GaussianBlur(out, (0, 0), sigma)
    out = out + rng.normal(0, rng.uniform(0, 6), out.shape)
    return np.clip(out, 0, 255).round().astype(np.uint8)


def real_features(dirs: list[Any], *, locations: int, tours: int, n_queries: int, vocab_train: list[Any],
                  n_words: int = 10000, seed: int = 0, cache_dir: Any = None,
                  progress: Any = None) -> dict[str, Any]:
    """Words and positions of every tour image and query of the real-image benchmark.

    Images are found recursively under ``dirs``; locations come from
    :func:`real_locations`, tour ``t`` of location ``l`` is
    :func:`image_variant` seeded with ``(seed, l, t)`` and resampled to a
    longer side of :data:`VARIANT_SIDE` pixels, and a query is the
    variant ``t = tours`` of a location (``n_queries`` locations drawn
    without replacement).  Features are `topoloc evaluate`'s defaults (SIFT,
    at most 1,000 per image, no resizing, no preprocessing), quantised with
    a vocabulary of ``n_words`` trained on ``vocab_train``
    (:func:`~topoloc.vocabulary.cached_vocabulary`).  The result is cached
    under ``<cache>/bench/`` (extraction takes minutes).

    Returns
    -------
    dict
        ``tour_words``/``tour_xy``: lists (tours) of lists (locations) of
        arrays; ``query_loc`` (Q,), ``query_words``, ``query_xy``;
        ``n_images``, ``vocabulary`` (fingerprint), ``vocab_file``.
    """
    import functools
    import hashlib
    import json
    from concurrent.futures import ThreadPoolExecutor
    from pathlib import Path

    from topoloc._parallel import n_workers
    from topoloc.datasets.traverse import find_images, read_image
    from topoloc.features import FeatureConfig, FeatureExtractor
    from topoloc.features.cache import cache_root
    from topoloc.io.container import read_container, write_container
    from topoloc.vocabulary import cached_vocabulary
    from topoloc.vocabulary.vocab import vocabulary_fingerprint

    extractor = FeatureExtractor(FeatureConfig(), cache_dir=cache_dir)
    vocab, vocab_file = cached_vocabulary([Path(d) for d in vocab_train], extractor=extractor, n_words=n_words,
                                          seed=0, cache_dir=cache_dir, progress=progress)
    fp = vocabulary_fingerprint(vocab)
    paths = find_images([Path(d) for d in dirs])
    ident = [[str(p.resolve()), p.stat().st_size, p.stat().st_mtime_ns] for p in paths]
    key = hashlib.sha1(json.dumps([ident, locations, tours, n_queries, seed, extractor.config.key(),
                                   fp.get("sha1"), _VARIANT_VERSION]).encode()).hexdigest()[:20]
    root = cache_root(cache_dir)
    file = root / "bench" / f"coocmap_real_{key}.tlc"
    rng = np.random.default_rng(seed)
    query_loc = np.sort(rng.choice(locations, size=min(n_queries, locations), replace=False))
    if file.is_file():
        _, arrays = read_container(file, "coocmap_bench", 1)
        words, xy, ptr = arrays["words"], arrays["xy"], arrays["ptr"]
    else:
        shapes = [read_image(p).shape[:2] for p in paths]
        locs = real_locations(paths, shapes, locations)
        if len(locs) < locations:
            raise TopolocError(f"found {len(paths)} images under the --real folders: too few for {locations} locations")
        jobs = [(lo, t) for t in range(tours) for lo in range(locations)] + [(int(q), tours) for q in query_loc]
        read = functools.lru_cache(maxsize=16)(read_image)

        def one(job: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
            lo, t = job
            i, box = locs[lo]
            var = image_variant(read(paths[i]), box, np.random.default_rng([seed, lo, t]), VARIANT_SIDE)
            fs = extractor.extract_image(var)
            return vocab.quantize(fs.descriptors).astype(np.int32), normalise_xy(fs.xy, fs.image_shape)

        tick = progress("coocmap bench: features of the variants", len(jobs)) if progress else None
        results: list[tuple[np.ndarray, np.ndarray]] = []
        with ThreadPoolExecutor(max_workers=n_workers()) as pool:
            for r in pool.map(one, jobs):
                results.append(r)
                if tick is not None:
                    tick(1)
        ptr = np.r_[0, np.cumsum([len(w) for w, _ in results])].astype(np.int64)
        words = np.concatenate([w for w, _ in results]) if results else np.zeros(0, np.int32)
        xy = np.concatenate([x for _, x in results]) if results else np.zeros((0, 2), np.uint16)
        file.parent.mkdir(parents=True, exist_ok=True)
        write_container(file, "coocmap_bench", 1, {"words": words, "xy": xy, "ptr": ptr},
                        meta={"dirs": [str(d) for d in dirs], "locations": locations, "tours": tours})
    seg = [(words[ptr[k]:ptr[k + 1]].astype(np.int64), xy[ptr[k]:ptr[k + 1]]) for k in range(len(ptr) - 1)]
    tw = [[seg[t * locations + lo][0] for lo in range(locations)] for t in range(tours)]
    txy = [[seg[t * locations + lo][1] for lo in range(locations)] for t in range(tours)]
    qs = seg[tours * locations:]
    return {"tour_words": tw, "tour_xy": txy, "query_loc": query_loc,
            "query_words": [q[0] for q in qs], "query_xy": [q[1] for q in qs],
            "n_images": len(paths), "vocabulary": fp, "vocab_file": str(vocab_file)}


def real_map(dirs: list[Any], *, locations: int = 2200, tours: int = 5, n_queries: int = 500,
             vocab_train: list[Any], n_words: int = 10000, position_bits: int = 6, seed: int = 0,
             cache_dir: Any = None, progress: Any = None) -> tuple[CoocModel, dict[str, Any], float]:
    """The real-image benchmark's map and queries (:func:`real_features`): ``(model, data, build seconds)``.

    The map uses the ``coocmap`` method's defaults (12 x 8 grid, interpolation, ``position_bits`` 6).
    """
    data = real_features(dirs, locations=locations, tours=tours, n_queries=n_queries, vocab_train=vocab_train,
                         n_words=n_words, seed=seed, cache_dir=cache_dir, progress=progress)
    t0 = time.perf_counter()
    obs = [[(lo, data["tour_words"][t][lo], data["tour_xy"][t][lo]) for lo in range(locations)]
           for t in range(tours)]
    hours = np.linspace(8, 22, tours) if tours > 1 else np.array([14.0])
    model = CoocModel.build(obs, n_locations=locations, n_words=n_words, position_bits=position_bits,
                            tour_names=[f"t{t}" for t in range(tours)], tour_hours=list(map(float, hours)))
    return model, data, time.perf_counter() - t0


def query_profile(model: CoocModel, words: np.ndarray, res: Any) -> dict[str, float]:
    """What one query's matching did (the counters of :func:`~topoloc.coocmap.compiled.match_compiled`),
    and what its words are like: the share of its features whose word recurs in it, and the triples
    (query feature, stored feature of the same word) per candidate of its best location."""
    w = np.asarray(words, np.int64).ravel()
    w = w[(w >= 0) & (w < model.n_words)]
    _, inv, cnt = np.unique(w, return_inverse=True, return_counts=True)
    best = int(res.best)
    stored = np.bincount(np.asarray(model.word[model.loc_ptr[best]:model.loc_ptr[best + 1]], np.int64),
                         minlength=model.n_words) if best >= 0 else np.zeros(model.n_words, np.int64)
    per_f = stored[w]
    n_cand = int(np.count_nonzero(per_f))
    return {
        "features": float(len(words)), "repeated_word_share": float(np.mean(cnt[inv] > 1)) if len(w) else 0.0,
        "best_score": float(res.scores[best]) if best >= 0 else 0.0,
        "best_triples_per_candidate": float(per_f.sum() / n_cand) if n_cand else 0.0,
        "best_candidates": float(n_cand),
        "visited": float(res.locations_visited), "pruned_before_J": float(res.translation_pruned),
        "J_built": float(res.locations_built), "pair_tests": float(res.pair_tests), "steps": float(res.steps),
    }


def bench_coocmap_real(dirs: list[Any], *, locations: int = 2200, tours: int = 5, n_queries: int = 500,
                       vocab_train: list[Any], n_words: int = 10000, top_k: int = 1, compare: int = 20,
                       spatial_tolerance: int = 1, position_bits: int = 6, seed: int = 0,
                       cache_dir: Any = None, progress: Any = None, per_query: bool = False) -> dict[str, Any]:
    """Time localisation against a map of real images at the paper's size.

    Locations, tours and queries are described in :func:`real_features`.  The
    map and the matcher use the ``coocmap`` method's defaults (12 x 8 grid,
    interpolation, ``spatial_tolerance`` 1, ``position_bits`` 6) with
    ``top_k = 1`` (pure localisation, the paper's bound).  Headline (every
    query): :func:`~topoloc.coocmap.compiled.match_compiled`, the method's
    default matcher, from the query's words and positions to the scores of
    all locations (feature extraction excluded, as in the paper).  On the
    first ``compare`` queries the previous default,
    :func:`~topoloc.coocmap.matching.match_lazy`, is timed too, and its best
    location compared.

    Returns
    -------
    dict
        ``ms_per_query_median``, ``ms_per_query_p95``, ``ms_per_query_p99``,
        ``ms_per_query_max``, ``recall_at_1`` (best
        location == the query's), ``map_bytes``, ``bytes_per_location``,
        ``n_features_median`` (per image, tours and queries),
        ``ms_lazy_median``/``ms_lazy_p95``/``recall_at_1_lazy`` and
        ``lazy_agree`` (same best location) on the ``compare`` queries,
        ``locations_built_median``/``_p95`` (locations whose ``J`` was built),
        ``translation_pruned_median`` (dropped by the bounds before any
        ``J``), ``pair_tests_median``, ``slowest_5pct`` and ``rest`` (medians
        of :func:`query_profile` over the slowest 5 % of the queries and over
        the others), ``peak_rss_mb``, ``build_s`` and the settings; with
        ``per_query``, ``per_query`` (ms and :func:`query_profile` of every
        query, lists).
    """
    import resource

    from topoloc.coocmap.compiled import match_compiled

    model, data, build_s = real_map(dirs, locations=locations, tours=tours, n_queries=n_queries,
                                    vocab_train=vocab_train, n_words=n_words, position_bits=position_bits,
                                    seed=seed, cache_dir=cache_dir, progress=progress)
    kw: dict[str, Any] = {"top_k": top_k, "seed": seed, "spatial_tolerance": spatial_tolerance}
    q_loc = data["query_loc"]
    match_compiled(model, data["query_words"][0], data["query_xy"][0], **kw)  # compile / load the kernel
    ms, best, prof = [], [], []
    for w, xy in zip(data["query_words"], data["query_xy"], strict=True):
        t = time.perf_counter()
        res, _ = match_compiled(model, w, xy, **kw)
        ms.append(1e3 * (time.perf_counter() - t))
        best.append(res.best)
        prof.append(query_profile(model, w, res))
    lazy_ms, lazy_best = [], []
    for w, xy in list(zip(data["query_words"], data["query_xy"], strict=True))[:compare]:
        t = time.perf_counter()
        lazy = match_lazy(model, w, xy, **kw)
        lazy_ms.append(1e3 * (time.perf_counter() - t))
        lazy_best.append(lazy.best)
    n_feat = [len(w) for tw in data["tour_words"] for w in tw] + [len(w) for w in data["query_words"]]
    nc = len(lazy_best)
    col = {k: np.array([p[k] for p in prof]) for k in prof[0]} if prof else {}
    slow = np.asarray(ms) >= np.percentile(ms, 95)
    out = {
        "benchmark": "real", "dirs": [str(d) for d in dirs], "n_images": data["n_images"],
        "locations": locations, "tours": tours, "n_queries": len(q_loc), "n_words": n_words,
        "vocab_train": [str(d) for d in vocab_train], "features": "sift, <= 1000 per image (evaluate defaults)",
        "top_k": top_k, "spatial_tolerance": spatial_tolerance, "position_bits": position_bits,
        "ms_per_query_median": float(np.median(ms)), "ms_per_query_p95": float(np.percentile(ms, 95)),
        "ms_per_query_p99": float(np.percentile(ms, 99)), "ms_per_query_max": float(np.max(ms)),
        "recall_at_1": float(np.mean(np.asarray(best) == q_loc)),
        "map_bytes": model.nbytes, "bytes_per_location": model.bytes_per_location,
        "features_stored": model.n_features, "n_features_median": float(np.median(n_feat)),
        "locations_built_median": float(np.median(col["J_built"])),
        "locations_built_p95": float(np.percentile(col["J_built"], 95)),
        "translation_pruned_median": float(np.median(col["pruned_before_J"])),
        "pair_tests_median": float(np.median(col["pair_tests"])),
        "slowest_5pct": {k: float(np.median(v[slow])) for k, v in col.items()},
        "rest": {k: float(np.median(v[~slow])) for k, v in col.items()},
        "compare": nc,
        "ms_lazy_median": float(np.median(lazy_ms)) if nc else float("nan"),
        "ms_lazy_p95": float(np.percentile(lazy_ms, 95)) if nc else float("nan"),
        "recall_at_1_lazy": float(np.mean(np.asarray(lazy_best) == q_loc[:nc])) if nc else float("nan"),
        "recall_at_1_compiled_same_queries": (float(np.mean(np.asarray(best[:nc]) == q_loc[:nc])) if nc
                                              else float("nan")),
        "lazy_agree": float(np.mean(np.asarray(lazy_best) == np.asarray(best[:nc]))) if nc else float("nan"),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "build_s": build_s,
    }
    if per_query:
        out["per_query"] = {"ms": [float(x) for x in ms], **{k: v.tolist() for k, v in col.items()}}
    return out
