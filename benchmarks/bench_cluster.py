"""Regenerate docs/results/cluster.md (+ .json): the whole pipeline on a local Dask cluster, 1 and 2 workers.

    .venv/bin/python -m benchmarks.bench_cluster [--places 20000] [--workers 1 2] [--work DIR]

A synthetic route of ``--places`` places (:mod:`topoloc.bench.cluster_scale`:
independent synthetic streets end to end, 160 x 120 images, a query tour for one
segment in 20) is rendered once on a 2-worker cluster.  Then, for each worker
count, a fresh ``distributed.LocalCluster`` (worker processes of one thread) runs
every stage of building and using a Cooc-Map map, each timed on its own, with a
fresh cache so that nothing is reused across worker counts:

1. features: SIFT of every map and query image into the chunked feature store;
2. vocabulary: the descriptor sample drawn by the workers, k-means here;
3. quantisation of the map images;
4. map building: partial models of ``4 x workers`` shards built by the workers, merged here;
5. localisation: the query frames described and scored by the workers
   (``topoloc localize --scheduler``'s path), lines in order.

Reported per stage: wall seconds, items per second, the peak resident memory
of the workers and of this process, and the bytes on disk; then
``docs/cluster_scaling.md`` extrapolates from these measured rates to a
100,000-place route on N workers.  The machine has 2 cores: with 2 workers
the client's own work (k-means, merging, writing lines) competes with them.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import RESULTS

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("features", "vocabulary", "quantisation", "map building", "localisation")


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _du(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.exists() else 0


def run_pipeline(route: Any, workers: int, work: Path, *, n_words: int, max_features: int) -> dict[str, Any]:
    """Every stage on a fresh local cluster of ``workers`` processes; timings, memory and disk per stage."""
    import distributed

    from topoloc.cluster import DaskExecutor, connect
    from topoloc.datasets.traverse import load_traverse
    from topoloc.features import FeatureConfig, FeatureExtractor
    from topoloc.maps.batch import localize_on
    from topoloc.maps.map import Map
    from topoloc.methods.cooc_map import CoocMap
    from topoloc.methods.shards import build_from_shards
    from topoloc.resources import CachedResources
    from topoloc.vocabulary.vocab import cached_vocabulary

    cache = work / f"cache_w{workers}"
    shutil.rmtree(cache, ignore_errors=True)
    cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                       dashboard_address=None, host="127.0.0.1", silence_logs=40)
    rows: list[dict[str, Any]] = []
    try:
        ex = connect(cluster.scheduler_address, timeout_s=60)
        assert isinstance(ex, DaskExecutor)  # an address always gives the Dask executor
        client = ex.client

        def worker_peak_mb() -> float:
            peaks = client.run(lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
            return float(max(peaks.values()))

        def stage(name: str, items: int, fn: Any) -> Any:
            t0 = time.perf_counter()
            out = fn()
            wall = time.perf_counter() - t0
            rows.append({"stage": name, "workers": workers, "items": items, "seconds": wall,
                         "items_per_s": items / wall if wall > 0 else float("inf"),
                         "worker_peak_mb": worker_peak_mb(), "client_peak_mb": _rss_mb(),
                         "disk_bytes": _du(cache)})
            return out

        config = FeatureConfig(max_features=max_features)
        extractor = FeatureExtractor(config, cache_dir=cache)
        map_t = load_traverse(route.map_dir)
        query_t = load_traverse(route.query_dir)
        res0 = CachedResources(extractor=extractor, executor=ex)
        feats = stage("features", len(map_t) + len(query_t),
                      lambda: (res0.features(map_t), res0.features(query_t)))
        n_feat = float(np.median([len(f) for f in feats[0]]))
        voc, _ = stage("vocabulary", len(map_t), lambda: cached_vocabulary(
            [route.map_dir], extractor=extractor, n_words=n_words, cache_dir=cache, executor=ex))
        res = CachedResources(extractor=extractor, vocabulary=voc, executor=ex)
        stage("quantisation", len(map_t), lambda: res.words(map_t))
        rec = stage("map building", len(map_t), lambda: build_from_shards(
            CoocMap, [map_t], resources=res, n_shards=4 * workers, executor=ex))
        m = Map.from_fitted(rec, [map_t], features=config, vocabulary=voc)
        map_file = work / f"route_w{workers}.tlm"
        m.save(map_file)
        loc = Map.load(map_file).localizer(top_k=1)
        frames = ((p.name, None, query_t.read(k, gray=False)) for k, p in enumerate(query_t.images))
        lines = stage("localisation", len(query_t), lambda: [line for line, _ in localize_on(ex, loc, frames)])
        right = float(np.mean([abs(int(line["place"]) - int(p)) <= 1
                               for line, p in zip(lines, query_t.places, strict=True)]))
        ex.close()
    finally:
        cluster.close()
    return {"workers": workers, "stages": rows, "map_bytes": map_file.stat().st_size,
            "store_bytes": _du(cache / "features"), "n_features_median": n_feat,
            "query_right_within_1": right, "n_places": route.n_places}


def extrapolate(measured: list[dict[str, Any]], *, places: int = 100_000, workers: tuple[int, ...] = (1, 8, 32, 128)
                ) -> list[dict[str, Any]]:
    """Hours per stage for ``places`` map images on N workers, from the 1-worker rates of ``measured``.

    Worker-side work scales as N at the 1-worker rate times the stage's
    measured 2-worker efficiency (speed-up from 1 to 2 workers, divided by 2,
    at most 1), applied once for every N >= 2: a linear model, pessimistic
    where the 2-worker run shared the 2 cores with the client.
    """
    one = {r["stage"]: r for r in next(m for m in measured if m["workers"] == 1)["stages"]}
    two_m = next((m for m in measured if m["workers"] == 2), None)
    two = {r["stage"]: r for r in two_m["stages"]} if two_m else {}
    n_meas = next(m for m in measured if m["workers"] == 1)["n_places"]
    out = []
    for stage, r in one.items():
        eff = min(1.0, (two[stage]["items_per_s"] / (2 * r["items_per_s"]))) if stage in two else 1.0
        items = r["items"] * places / n_meas
        for n in workers:
            speed = r["items_per_s"] * n * (eff if n > 1 else 1.0)
            out.append({"stage": stage, "workers": n, "hours": items / speed / 3600.0, "efficiency_at_2": eff})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--places", type=int, default=20_000)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--work", type=Path, default=ROOT / "build" / "cluster_route")
    ap.add_argument("--words", type=int, default=2000)
    ap.add_argument("--max-features", type=int, default=300)
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--generate-only", action="store_true", help="render the route and stop")
    ap.add_argument("--page-only", action="store_true", help="rewrite the pages from cluster.json, measure nothing")
    args = ap.parse_args()
    if args.page_only:
        data = json.loads((args.out / "cluster.json").read_text())
        ext = extrapolate(data["measured"])
        data["extrapolated"] = ext
        (args.out / "cluster.json").write_text(json.dumps(data, indent=2, default=float) + "\n")
        write_pages(data["meta"], data["measured"], ext, args.out, recheck=data.get("localisation_recheck"))
        return

    import distributed

    from topoloc.bench.cluster_scale import generate_scale_route
    from topoloc.cluster import connect

    args.work.mkdir(parents=True, exist_ok=True)
    # The route is rendered once per size and kept (segments resume); its rendering time is recorded with it.
    route_dir = args.work / f"route_{args.places}"
    gen_file = route_dir / "generation.json"
    t0 = time.perf_counter()
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  host="127.0.0.1", silence_logs=40) as cluster, \
            connect(cluster.scheduler_address, timeout_s=60) as ex:
        route = generate_scale_route(route_dir, n_places=args.places, executor=ex)
    if not gen_file.is_file():
        gen_file.write_text(json.dumps({"seconds": time.perf_counter() - t0, "load": os.getloadavg()[0]}))
    gen_s = float(json.loads(gen_file.read_text())["seconds"])
    if args.generate_only:
        print(f"route of {args.places} places in {route_dir} ({gen_s:.0f} s to render)")
        return
    load_before = os.getloadavg()[0]
    measured = [run_pipeline(route, w, args.work, n_words=args.words, max_features=args.max_features)
                for w in args.workers]
    ext = extrapolate(measured)
    meta = {"date": datetime.now(UTC).isoformat(timespec="seconds"), "machine": platform.machine(),
            "cores": os.cpu_count(), "python": platform.python_version(), "load_before": load_before,
            "generation_s": gen_s, "places": args.places, "map_images": route.n_map_images,
            "query_images": route.n_query_images, "image_size": [route.width, route.height],
            "words": args.words, "max_features": args.max_features}
    (args.out / "cluster.json").write_text(json.dumps({"meta": meta, "measured": measured, "extrapolated": ext},
                                                      indent=2, default=float) + "\n")
    write_pages(meta, measured, ext, args.out)
    print((args.out / "cluster.md").read_text())


def write_pages(meta: dict[str, Any], measured: list[dict[str, Any]], ext: list[dict[str, Any]], out: Path, *,
                recheck: dict[str, Any] | None = None) -> None:
    """docs/results/cluster.md (measured) and docs/cluster_scaling.md (the extrapolation)."""
    cmd = f".venv/bin/python -m benchmarks.bench_cluster --places {meta['places']}"
    lines = [
        "# The pipeline on a Dask cluster: measured stage rates\n\n",
        f"Generated by `{cmd}`; do not edit by hand ({meta['machine']}, {meta['cores']} cores, "
        f"Python {meta['python']}, {meta['date']}; 1-minute load average before the run "
        f"{meta['load_before']:.2f}).\n\n",
        f"Route: {meta['places']:,} places, {meta['map_images']:,} map images and {meta['query_images']:,} query "
        f"images of {meta['image_size'][0]} x {meta['image_size'][1]} pixels (synthetic streets end to end, "
        f"`topoloc.bench.cluster_scale`; rendered in {meta['generation_s']:.0f} s on 2 workers, not counted). "
        f"Cooc-Map, SIFT at most {meta['max_features']} per image, {meta['words']:,} words. Each worker count "
        "starts a fresh `distributed.LocalCluster` (worker processes of one thread) and a fresh cache.\n\n",
        "| workers | stage | items | seconds | items/s | worker peak MiB | client peak MiB | cache on disk MiB |\n",
        "| --- | --- | --- | --- | --- | --- | --- | --- |\n",
    ]
    for i, m in enumerate(measured):
        for r in m["stages"]:
            # Linux keeps a process's peak RSS across fork and exec: workers started after this
            # process had grown report its peak, not their own, so only the first cluster's count.
            wpeak = f"{r['worker_peak_mb']:.0f}" if i == 0 else "n/a"
            lines.append(f"| {r['workers']} | {r['stage']} | {r['items']:,} | {r['seconds']:.1f} | "
                         f"{r['items_per_s']:.1f} | {wpeak} | {r['client_peak_mb']:.0f} | "
                         f"{r['disk_bytes'] / 2**20:.1f} |\n")
    lines.append("\n| workers | map file MiB | feature store MiB | median features per image | "
                 "queries localised within 1 place |\n| --- | --- | --- | --- | --- |\n")
    for m in measured:
        lines.append(f"| {m['workers']} | {m['map_bytes'] / 2**20:.1f} | {m['store_bytes'] / 2**20:.1f} | "
                     f"{m['n_features_median']:.0f} | {m['query_right_within_1']:.3f} |\n")
    lines.append("\nThe machine has 2 cores, so the 2-worker rows share them with the client (k-means, "
                 "merging the shards, writing result lines); the speed-up from 1 to 2 workers per stage is the "
                 "efficiency used in [the extrapolation](../cluster_scaling.md). Worker peak memory is shown "
                 "for the first cluster only: the others were started after this process had grown, and Linux "
                 "reports a parent's peak to the processes it starts. The client's peak is this whole process "
                 "(it holds every image's features of the route after the features stage).\n")
    if recheck:
        q = recheck["queries_per_s"]
        lines.append("\nLocalisation re-measured after this run with `.venv/bin/python -m benchmarks."
                     f"bench_cluster_localize` (same map and {recheck['queries']:,} queries, load average "
                     f"{recheck['load_before']:.2f}): " + ", ".join(f"{rate:.1f} queries/s on {w} worker(s)"
                                                                   for w, rate in q.items()) + ".\n")
    if meta.get("notes"):
        lines.append("\n" + meta["notes"] + "\n")
    (out / "cluster.md").write_text("".join(lines))

    one = {r["stage"]: r for r in measured[0]["stages"]}
    per_place_map = measured[0]["map_bytes"] / meta["places"]
    per_image_store = measured[0]["store_bytes"] / max(1, meta["map_images"] + meta["query_images"])
    doc = [
        "# From a laptop to a cluster: what a 1,000 km route costs\n\n",
        f"Generated by `{cmd}` from the rates measured in [results/cluster.md](results/cluster.md); "
        "do not edit by hand.\n\n",
        "FAB-MAP 2.0's 1,000 km route has about 100,000 places. The table scales each stage's measured "
        "1-worker rate to 100,000 map images on N workers, times the stage's measured 2-worker efficiency "
        "(pessimistic: on a real cluster workers do not share cores with the client). Image size matters: "
        "the benchmark's images are "
        f"{meta['image_size'][0]} x {meta['image_size'][1]}; SIFT on 640 x 480 frames is about 15 images/s "
        "per core (docs/results/performance.md), so multiply the features row by the ratio of the two rates "
        "for camera-size images.\n\n",
        "| stage | " + " | ".join(f"{n} workers (h)" for n in sorted({e['workers'] for e in ext})) +
        " | 2-worker efficiency |\n",
        "| --- |" + " --- |" * (len({e['workers'] for e in ext}) + 1) + "\n",
    ]
    for stage in one:
        es = [e for e in ext if e["stage"] == stage]
        doc.append(f"| {stage} | " + " | ".join(f"{e['hours']:.2f}" for e in es) +
                   f" | {es[0]['efficiency_at_2']:.2f} |\n")
    worst = max(one, key=lambda s: one[s]["seconds"])
    doc += [
        "\n**Disk**: the feature store takes "
        f"{per_image_store / 1024:.1f} KiB per image here ({100_000 * per_image_store / 2**30:.1f} GiB for "
        "100,000 images); the Cooc-Map map file "
        f"{per_place_map / 1024:.1f} KiB per place ({100_000 * per_place_map / 2**30:.2f} GiB). "
        f"**Memory**: a worker peaked at {max(r['worker_peak_mb'] for r in measured[0]['stages']):.0f} MiB "
        "(it holds one block of images or one shard, not the route). The client peaked at "
        f"{max(r['client_peak_mb'] for m in measured for r in m['stages']):.0f} MiB at {meta['places']:,} places: "
        "the benchmark asks it for every image's features of the route at once (`Resources.features`), which "
        "grows with the route and would not fit at 100,000 places; the workers' own stages (quantisation, "
        "shards, localisation) read their blocks from the store and do not need that.\n\n",
        f"**Which stage limits it**: on one worker the slowest stage is {worst}. Stages run by workers scale "
        "with N; what runs on the client does not (k-means of the vocabulary sample, merging shard models, "
        "the sequence search and writing lines), so at large N the client-side part of the vocabulary and map "
        "building stages is the floor; before that, the client's memory, if it gathers the whole route's "
        "features.\n",
    ]
    if meta.get("notes"):
        doc.append("\n" + meta["notes"] + "\n")
    (out.parent / "cluster_scaling.md").write_text("".join(doc))


if __name__ == "__main__":
    main()
