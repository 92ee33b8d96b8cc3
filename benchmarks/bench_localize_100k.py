"""Regenerate docs/results/localize_100k.md: ms per query at 100,000 places, maps tiled from a measured route.

    .venv/bin/python -m benchmarks.bench_localize_100k --run build/cluster_route/run_1000 [--places 100000]

Rendering 100,000 places of images takes hours on 2 cores, so the maps here are built from
word arrays: the words and keypoint positions of every image of a route that
``benchmarks.bench_cluster`` rendered and described (``--run``: its vocabulary, feature
cache and route; nothing is extracted again when the cache is there) are repeated, place
ids shifted, until the map has ``--places`` places.  The words' statistics are thus those
of real SIFT features of synthetic street images, and every inverted-file list is
``--places / route places`` times longer than on the route, as it would be on a route of
that length.  The route's query images are then scored one at a time
(``PlaceRecognizer.score`` of one encoded query, what ``localize`` does per frame after the
features), after one warm-up query.  A query's right place appears once per copy, so
"right" counts a best place in any copy of the true one.

Bag of words and FAB-MAP 2.0 are fitted with ``Traverse.from_words`` (FAB-MAP learns its
word statistics from the route's own images: timing only); Cooc-Map's location models are
fed through ``CoocModel.add_tour``, as ``fit`` feeds them.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import RESULTS

TARGET_MS = {"bow": 20.0, "fabmap2": 20.0, "coocmap": 50.0}
"""Median ms per query each method must stay under at 100,000 places (issue 30: 20 ms for the
inverted-file methods; Cooc-Map's 50 ms is the target set here: at 10 frames/s a frame has 100 ms,
of which features take about 50 on one core (the camera-rate section of performance.md))."""


def route_words(run: Path, max_features: int) -> dict[str, Any]:
    """Placed words of the map and query images of the route of a ``bench_cluster`` run folder."""
    from topoloc.datasets.traverse import load_traverse
    from topoloc.features import FeatureExtractor
    from topoloc.maps.map import Map
    from topoloc.resources import CachedResources
    from topoloc.spec.parts import FeatureSpec

    m = Map.load(run / "route.tlm")
    route = run.parent / f"route_{run.name.removeprefix('run_')}"
    config = FeatureSpec(max_features=max_features).config()
    res = CachedResources(extractor=FeatureExtractor(config, cache_dir=run / "cache"), vocabulary=m.vocabulary)
    maps, query = load_traverse(route / "map"), load_traverse(route / "query")
    return {"vocabulary": m.vocabulary, "map": res.placed_words(maps), "map_places": maps.places,
            "query": res.placed_words(query), "query_places": query.places, "route_places": len(np.unique(maps.places))}


def tile(base: dict[str, Any], places: int) -> tuple[list[Any], np.ndarray, int]:
    """The route's map images repeated until ``places`` places; place ids shifted by a stride per copy."""
    ids = np.asarray(base["map_places"], np.int64)
    stride = int(ids.max()) + 1
    copies = -(-places // base["route_places"])
    items = [x for _ in range(copies) for x in base["map"]]
    tiled = np.concatenate([ids + c * stride for c in range(copies)])
    return items, tiled, stride


def time_queries(score_one: Any, items: list[Any], truth: np.ndarray, place_ids: np.ndarray, stride: int
                 ) -> dict[str, float]:
    score_one(items[0])  # warm-up: numba compilation, lazily built indexes
    ms, cpu, right = [], [], 0
    for item, t in zip(items, truth, strict=True):
        t0, c0 = time.perf_counter(), time.process_time()
        col = score_one(item)
        ms.append(1e3 * (time.perf_counter() - t0))
        cpu.append(1e3 * (time.process_time() - c0))
        right += int(int(place_ids[int(np.argmax(col))]) % stride == int(t))
    return {"ms_median": statistics.median(ms), "ms_p95": sorted(ms)[int(0.95 * (len(ms) - 1))],
            "cpu_ms_median": statistics.median(cpu), "right": right / len(items), "queries": len(items)}


def bench_inverted(method: str, base: dict[str, Any], places: int, queries: int) -> dict[str, Any]:
    from topoloc.datasets.traverse import Traverse
    from topoloc.methods import get_method
    from topoloc.resources import InMemoryResources

    items, ids, stride = tile(base, places)
    training = Traverse.from_words([w for w, _, _ in base["map"]], name="training")
    res = InMemoryResources(vocabulary=base["vocabulary"], training=[training])
    t0 = time.perf_counter()
    rec = get_method(method)().fit([Traverse.from_words([w for w, _, _ in items], places=ids, name="map")],
                                   resources=res)
    fit_s = time.perf_counter() - t0

    def one(w: np.ndarray) -> np.ndarray:
        enc = rec.encode(Traverse.from_words([w], name="q"), resources=res)
        return np.asarray(rec.score(enc)[:, 0])

    qs = [np.asarray(w, np.int64) for w, _, _ in base["query"][:queries]]
    out = time_queries(one, qs, np.asarray(base["query_places"][:queries]), rec.place_ids_, stride)
    return {"method": method, "places": len(rec.place_ids_), "images": len(items), "fit_s": fit_s, **out}


def bench_coocmap(base: dict[str, Any], places: int, queries: int) -> dict[str, Any]:
    from topoloc.coocmap.model import CoocModel
    from topoloc.coocmap.spatial import normalise_xy
    from topoloc.methods.cooc_map import CoocMap

    rec = CoocMap()
    items, ids, stride = tile(base, places)
    k = rec.max_words_per_image or None
    place_ids = np.unique(ids)
    rows = np.searchsorted(place_ids, ids)
    t0 = time.perf_counter()
    model = CoocModel(n_locations=len(place_ids), n_words=int(base["vocabulary"].n_words_), grid_x=rec.grid_x,
                      grid_y=rec.grid_y, interpolate=rec.interpolate, position_bits=rec.position_bits)
    model.add_tour([(int(r), np.asarray(w[:k], np.int64), normalise_xy(xy[:k], shape))
                    for r, (w, xy, shape) in zip(rows, items, strict=True)], name="map", hour=12.0)
    rec.model_, rec.place_ids_, rec.tour_order_ = model, place_ids, ["map"]
    fit_s = time.perf_counter() - t0
    qs = [(np.asarray(w[:k], np.int64), normalise_xy(xy[:k], shape)) for w, xy, shape in base["query"][:queries]]
    out = time_queries(rec._scores, qs, np.asarray(base["query_places"][:queries]), place_ids, stride)
    return {"method": "coocmap", "places": len(place_ids), "images": len(items), "fit_s": fit_s, **out}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, required=True, help="a run folder of benchmarks.bench_cluster")
    ap.add_argument("--places", type=int, default=100_000)
    ap.add_argument("--queries", type=int, default=100)
    ap.add_argument("--max-features", type=int, default=300, help="as the run was built with")
    ap.add_argument("--methods", default="bow,fabmap2,coocmap")
    ap.add_argument("--out", type=Path, default=RESULTS / "localize_100k.md")
    args = ap.parse_args()
    load_before = os.getloadavg()[0]
    base = route_words(args.run, args.max_features)
    rows = []
    for method in args.methods.split(","):
        row = (bench_coocmap(base, args.places, args.queries) if method == "coocmap"
               else bench_inverted(method, base, args.places, args.queries))
        row["load"] = os.getloadavg()[0]
        rows.append(row)
        print(json.dumps(row), flush=True)
    n_feat = statistics.median(len(w) for w, _, _ in base["map"])
    text = [
        f"# Localisation at {args.places:,} places\n\n",
        f"Generated by `.venv/bin/python -m benchmarks.bench_localize_100k --run {args.run.name} --places "
        f"{args.places} --queries {args.queries}` (the run folder of `benchmarks.bench_cluster`); do not edit by "
        f"hand ({platform.machine()}, "
        f"{os.cpu_count()} cores, {datetime.now(UTC).isoformat(timespec='seconds')}; 1-minute load average "
        f"{load_before:.2f} before the run).\n\n",
        f"The map of a rendered route of {base['route_places']:,} places ({len(base['map']):,} images, median "
        f"{n_feat:.0f} SIFT features an image, {int(base['vocabulary'].n_words_):,} words) repeated until it has "
        f"{args.places:,} places; its query images scored one at a time from their words (features not "
        "counted), after a warm-up (`benchmarks/bench_localize_100k.py` says why and how).\n\n",
        "| method | places | map images | fit s | ms per query (median) | ms per query (p95) | CPU ms per query "
        "(median) | target (median) | met (wall / CPU) | best place right | load |\n"
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n",
    ]
    for r in rows:
        target = TARGET_MS[r["method"]]
        text.append(f"| {r['method']} | {r['places']:,} | {r['images']:,} | {r['fit_s']:.1f} | {r['ms_median']:.1f} | "
                    f"{r['ms_p95']:.1f} | {r['cpu_ms_median']:.1f} | "
                    f"{target:.0f} ms | {'yes' if r['ms_median'] < target else 'no'} / "
                    f"{'yes' if r['cpu_ms_median'] < target else 'no'} | "
                    f"{r['right']:.2f} | {r['load']:.2f} |\n")
    text.append(
        "\nWhat bounds each: bag of words and FAB-MAP 2.0 score through an inverted file, so a query touches only "
        "the images that share one of its words (FAB-MAP 2.0's bailout also drops the places that cannot win). "
        "Cooc-Map (Sec. II-D) takes its candidate locations from the inverted file of each query word, every "
        "location holding it, then refines only the best `top_k` by consistency graphs, the other scores being "
        "the paper's upper bounds; its time grows with the inverted-file lists, i.e. with the route. Tiling "
        "makes this pessimistic for Cooc-Map: every copy of the right place ties with it, and a tie at the top "
        "must be matched exactly, so a query matches about one location per copy where a real route has one. "
        "The CPU column is the process's CPU time per query (all its threads): on a machine shared with other "
        "work the wall clock also counts the time the query waited for a core (at a load average of 20 on 2 cores, "
        "most of it), so \"met\" is given for both. Bag of words and FAB-MAP 2.0 score on one thread, so on an "
        "idle core the two agree; Cooc-Map's matcher also runs on numba's threads, whose CPU times add up.\n")
    args.out.write_text("".join(text))
    print("".join(text))


if __name__ == "__main__":
    main()
