"""Regenerate docs/results/cluster.md (+ .json) and docs/cluster_scaling.md: the CLI on a local Dask cluster.

    .venv/bin/python -m benchmarks.bench_cluster --places 2000 8000 [--work DIR] [--words 2000] [--max-features 300]
    .venv/bin/python -m benchmarks.bench_cluster --places 100000     # the 1,000 km run (hours on 2 cores)

For each route length of ``--places`` a synthetic route (:mod:`topoloc.bench.cluster_scale`:
independent synthetic streets end to end, 160 x 120 images; a map tour over every place, a
tour to add over one segment in ``--add-every``, a query tour over one segment in 20) is
rendered once and kept.  Then a fresh ``distributed.LocalCluster`` of 2 worker processes
(one thread each) and a fresh cache run the command line itself, each command a process
of its own started through :mod:`benchmarks.peak_run` (which records its peak memory):

1. ``topoloc vocab train MAP`` (features of every map image into the feature store, the
   sample drawn by the workers, k-means on the client);
2. ``topoloc map build --method coocmap --map MAP --shards S`` (the workers read the store,
   quantise and build one partial model per shard; the client merges them);
3. ``topoloc map add`` of the added tour;
4. ``topoloc localize`` of the query tour (frames described and scored by the workers).

Reported per command: wall seconds, images per second, the client's peak resident memory
(the command's own VmHWM) and the workers' (VmHWM, reset through ``/proc/self/clear_refs``
before each command), and the cache on disk; then the map file's size, the time to open it
in a fresh process, and ms per query localised on one thread of this machine from that
file.  The client's peak at each route length is compared: it must not grow with the route.
``docs/cluster_scaling.md`` extrapolates the measured rates of the longest route to 100,000
places on N machines.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from benchmarks.common import RESULTS, output_folder
from benchmarks.peak_run import reset_vm_hwm, vm_hwm_mib

ROOT = Path(__file__).resolve().parents[1]
WORKERS = 2
TARGET_PLACES = 100_000  # FAB-MAP 2.0's 1,000 km route


def _du(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.exists() else 0


def _peak() -> float:
    return vm_hwm_mib() or float("nan")


def _render(places: int, work: Path, add_every: int) -> Any:
    import distributed

    from topoloc.bench.cluster_scale import generate_scale_route
    from topoloc.cluster import connect

    route_dir = work / f"route_{places}"
    gen_file = route_dir / "generation.json"
    t0 = time.perf_counter()
    with distributed.LocalCluster(n_workers=WORKERS, threads_per_worker=1, processes=True, dashboard_address=None,
                                  host="127.0.0.1", silence_logs=40) as cluster, \
            connect(cluster.scheduler_address, timeout_s=60) as ex:
        route = generate_scale_route(route_dir, n_places=places, executor=ex, add_every=add_every)
    if not gen_file.is_file():
        gen_file.write_text(json.dumps({"seconds": time.perf_counter() - t0, "load": os.getloadavg()[0]}))
    return route, float(json.loads(gen_file.read_text())["seconds"])


OPEN_AND_QUERY = """
import json, statistics, sys, time
import numpy as np
from topoloc.datasets.traverse import load_traverse
t0 = time.perf_counter()
from topoloc.maps.map import Map
m = Map.load(sys.argv[1])
open_s = time.perf_counter() - t0
q = load_traverse(sys.argv[2])
n = min(int(sys.argv[3]), len(q))
loc = m.localizer(top_k=1)
frames = [q.read(k, gray=False) for k in range(n)]
loc.step(frames[0])  # warm-up: compiles the matcher, builds the indexes
feats, match = [], []  # the localiser keeps running sums of its stages: per frame, their increments
for f in frames:
    before = (loc.ms_decode + loc.ms_features + loc.ms_quantise, loc.ms_matching)
    loc.step(f)
    feats.append(loc.ms_decode + loc.ms_features + loc.ms_quantise - before[0])
    match.append(loc.ms_matching - before[1])
out = {"open_s": open_s, "queries": n, "ms_features_median": statistics.median(feats),
       "ms_matching_median": statistics.median(match), "ms_matching_p95": sorted(match)[int(0.95 * (n - 1))]}
rec = m.recognizer
if hasattr(rec, "model_") and getattr(rec, "schedule", "") == "compiled":
    # What bounds a Cooc-Map query (topoloc.coocmap.compiled): locations whose candidate count reaches the
    # top_k-th best score (visited), dropped by the translation bounds, J built; and one thread's time.
    from topoloc.coocmap.compiled import match_compiled
    counts, one = [], []
    for f in frames[:50]:
        (w, xy, *_), = loc.describe(f)[0]
        kw = dict(top_k=rec.top_k, interpolate=rec.interpolate, seed=rec.seed,
                  spatial_tolerance=rec.spatial_tolerance)
        res, _ = match_compiled(rec.model_, w, xy, **kw)
        counts.append((res.locations_visited, res.translation_pruned, res.locations_built))
        t1 = time.perf_counter()
        match_compiled(rec.model_, w, xy, threads=1, **kw)
        one.append(1e3 * (time.perf_counter() - t1))
    c = np.median(np.asarray(counts, float), axis=0)
    out.update(locations=rec.model_.n_locations, visited_median=c[0], translation_pruned_median=c[1],
               built_median=c[2], ms_one_thread_median=statistics.median(one[1:]), top_k=rec.top_k)
print(json.dumps(out))
"""


def run_route(route: Any, work: Path, *, words: int, max_features: int, shards: int, queries: int
              ) -> dict[str, Any]:
    """The four commands on a fresh 2-worker cluster and cache; timings, peaks and sizes."""
    import distributed

    out = work / f"run_{route.n_places}"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    cache = out / "cache"
    tlm, voc = out / "route.tlm", out / "vocab.tlv"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "src"),
                                                          os.environ.get("PYTHONPATH", "")])}
    rows: list[dict[str, Any]] = []
    with distributed.LocalCluster(n_workers=WORKERS, threads_per_worker=1, processes=True, dashboard_address=None,
                                  host="127.0.0.1", silence_logs=40) as cluster, \
            distributed.Client(cluster.scheduler_address, set_as_default=False) as client:
        sched = ["--scheduler", cluster.scheduler_address, "--scheduler-timeout", "120", "-q"]
        cached = [*sched, "--cache-dir", str(cache)]
        feats = ["--max-features", str(max_features)]
        commands = [
            ("vocab train", route.n_map_images,
             ["vocab", "train", str(route.map_dir), "--words", str(words), *feats, "--max-side", "640",
              "--out", str(voc), *cached]),
            ("map build", route.n_map_images,
             ["map", "build", "--method", "coocmap", "--map", str(route.map_dir), "--vocab", str(voc), *feats,
              "--shards", str(shards), "--out", str(tlm), *cached]),
            ("map add", route.n_add_images, ["map", "add", str(tlm), str(route.add_dir), *cached]),
            ("localize", route.n_query_images,
             ["localize", str(tlm), str(route.query_dir), "--top-k", "1", "--out", str(out / "lines.jsonl"), *sched]),
        ]
        for name, items, args in commands:
            client.run(reset_vm_hwm)
            peak_file = out / f"peak_{name.replace(' ', '_')}.json"
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "benchmarks.peak_run", str(peak_file), "--", *args],
                           check=True, env=env, cwd=ROOT)
            wall = time.perf_counter() - t0
            rows.append({"stage": name, "items": items, "seconds": wall, "items_per_s": items / wall,
                         "client_peak_mib": json.loads(peak_file.read_text())["peak_mib"],
                         "worker_peak_mib": max(client.run(_peak).values()), "disk_bytes": _du(cache),
                         "load": os.getloadavg()[0]})
            print(json.dumps(rows[-1]), flush=True)
    local = probe(tlm, route.query_dir, queries)
    truth = _places(route.query_dir)
    lines = [json.loads(x) for x in (out / "lines.jsonl").read_text().splitlines() if x.strip()]
    right = statistics.mean(abs(int(x["place"]) - truth[x["image"]]) <= 1 for x in lines)
    store = cache / "features"
    n_images = route.n_map_images + route.n_add_images + route.n_query_images
    return {"places": route.n_places, "map_images": route.n_map_images, "add_images": route.n_add_images,
            "query_images": route.n_query_images, "shards": shards, "stages": rows,
            "map_bytes": tlm.stat().st_size, "store_bytes": _du(store), "cache_bytes": _du(cache),
            "per_image_cache_files": sum(1 for _ in store.rglob("*.tlf")),
            "store_bytes_per_image": _du(store) / max(1, route.n_map_images + route.n_add_images),
            "images_described": n_images, "local": local, "query_right_within_1": right}


def probe(tlm: Path, query_dir: Path, queries: int) -> dict[str, Any]:
    """Open the map in a fresh process and time ``queries`` localisations from it (:data:`OPEN_AND_QUERY`)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "src"),
                                                          os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-c", OPEN_AND_QUERY, str(tlm), str(query_dir), str(queries)],
                         check=True, env=env, cwd=ROOT, capture_output=True, text=True)
    return {**json.loads(out.stdout.strip().splitlines()[-1]), "load": os.getloadavg()[0],
            "date": datetime.now(UTC).isoformat(timespec="seconds")}


def _places(folder: Path) -> dict[str, int]:
    import csv

    with (folder / "places.csv").open(encoding="utf-8") as fh:
        return {row["image"]: int(row["place"]) for row in csv.DictReader(fh)}


def extrapolate(run: dict[str, Any], *, places: int = TARGET_PLACES, machines: tuple[int, ...] = (1, 4, 16, 64)
                ) -> list[dict[str, Any]]:
    """Hours per command for a route of ``places`` on N machines like the measured one (2 workers each).

    Items scale with the route (the map and added images with its places; the queries are
    per query, so their rate is kept).  A command's measured rate on one machine is
    multiplied by N: linear, and optimistic for the client-side part (k-means, merging the
    shards, writing lines), which does not scale with N; the measured client seconds bound
    it from above.
    """
    out = []
    factor = places / run["places"]
    for r in run["stages"]:
        items = r["items"] * (1 if r["stage"] == "localize" else factor)
        for n in machines:
            out.append({"stage": r["stage"], "machines": n, "items": items,
                        "hours": items / (r["items_per_s"] * n) / 3600.0})
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--places", type=int, nargs="+", default=[2_000, 8_000])
    ap.add_argument("--work", type=Path, default=ROOT / "build" / "cluster_route")
    ap.add_argument("--words", type=int, default=2000)
    ap.add_argument("--max-features", type=int, default=300)
    ap.add_argument("--add-every", type=int, default=4, help="one segment in N has a tour to add")
    ap.add_argument("--queries", type=int, default=200, help="queries timed one frame at a time from the map file")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--page-only", action="store_true", help="rewrite the pages from cluster.json, measure nothing")
    ap.add_argument("--probe-only", action="store_true",
                    help="time the localisation again from the maps a previous run left in --work, and rewrite "
                         "the pages (the commands' rows are kept)")
    ap.add_argument("--keep", action="store_true",
                    help="keep the runs of other route lengths already in cluster.json (each keeps its own date)")
    args = ap.parse_args(argv)
    output_folder(args.out)  # before the minutes of work, not after them
    if args.page_only:
        data = json.loads((args.out / "cluster.json").read_text())
        write_pages(data, args.out)
        return
    if args.probe_only:
        data = json.loads((args.out / "cluster.json").read_text())
        for run in data["runs"]:
            tlm = args.work / f"run_{run['places']}" / "route.tlm"
            query = args.work / f"route_{run['places']}" / "query"
            if not (tlm.is_file() and query.is_dir()):
                raise SystemExit(f"--probe-only: no map {tlm} or queries {query} of the {run['places']:,}-place run")
            run["local"] = probe(tlm, query, args.queries)
            print(json.dumps(run["local"]), flush=True)
        (args.out / "cluster.json").write_text(json.dumps(data, indent=2, default=float) + "\n")
        write_pages(data, args.out)
        return
    args.work.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()[0]
    runs = []
    for places in sorted(args.places):
        route, gen_s = _render(places, args.work, args.add_every)
        # About 2,500 map images a shard: a worker holds one shard's features (a few hundred MB at most).
        shards = max(2 * WORKERS, -(-route.n_map_images // 2_500))
        run = run_route(route, args.work, words=args.words, max_features=args.max_features, shards=shards,
                        queries=args.queries)
        run["generation_s"] = gen_s
        runs.append(run)
    for run in runs:
        run["date"] = datetime.now(UTC).isoformat(timespec="seconds")
    if args.keep and (args.out / "cluster.json").is_file():
        old = json.loads((args.out / "cluster.json").read_text())
        measured = {r["places"] for r in runs}
        kept = [{"date": old["meta"]["date"], **r} for r in old["runs"] if r["places"] not in measured]
        runs = sorted(runs + kept, key=lambda r: r["places"])
        args.places = [r["places"] for r in runs]
    meta = {"date": datetime.now(UTC).isoformat(timespec="seconds"), "machine": platform.machine(),
            "cores": os.cpu_count(), "python": platform.python_version(), "load_before": load_before,
            "load_after": os.getloadavg()[0], "places": sorted(args.places), "words": args.words,
            "max_features": args.max_features, "workers": WORKERS, "image_size": [route.width, route.height]}
    data = {"meta": meta, "runs": runs, "extrapolated": extrapolate(runs[-1])}
    (args.out / "cluster.json").write_text(json.dumps(data, indent=2, default=float) + "\n")
    write_pages(data, args.out)
    print((args.out / "cluster.md").read_text())


#: Issue #30's bounds on peak memory, whatever the route's length (MiB).
CLIENT_BOUND_MIB = 2048
WORKER_BOUND_MIB = 4096


def _run_dates(runs: list[dict[str, Any]]) -> str:
    """When the routes were measured apart (``--keep``): each one's date."""
    dates = {r.get("date") for r in runs}
    if len(dates) <= 1:
        return ""
    return " Routes measured apart: " + ", ".join(f"{r['places']:,} places on {r.get('date', 'an earlier run')}"
                                                  for r in runs) + "."


def _growth_sentence(runs: list[dict[str, Any]], peaks: list[tuple[int, float, float]]) -> str:
    """The shortest route against the longest: how the peaks grew beside the route and the map file.

    Each command's growth is also given per 100,000 places (a straight line through the shortest and the
    longest route), and where that line would take its peak past the client's bound.
    """
    (p0, c0, w0), (p1, c1, w1) = peaks[0], peaks[-1]
    m0, m1 = runs[0]["map_bytes"] / 2**20, runs[-1]["map_bytes"] / 2**20
    slopes = []
    for r0, r1 in zip(runs[0]["stages"], runs[-1]["stages"], strict=True):
        per = (r1["client_peak_mib"] - r0["client_peak_mib"]) / (p1 - p0) * 100_000
        reach = (f", {p1 + (CLIENT_BOUND_MIB - r1['client_peak_mib']) / per * 100_000:,.0f} places to "
                 f"{CLIENT_BOUND_MIB:,} MiB" if per > 0 else "")
        slopes.append(f"`{r1['stage']}` {r0['client_peak_mib']:.0f} → {r1['client_peak_mib']:.0f} "
                      f"({per:+.0f} per 100,000 places{reach})")
    within = c1 <= CLIENT_BOUND_MIB and w1 <= WORKER_BOUND_MIB and all(
        c <= CLIENT_BOUND_MIB and w <= WORKER_BOUND_MIB for _, c, w in peaks)
    return (f"\n**Growth.** From {p0:,} to {p1:,} places ({p1 / p0:.0f}x the route) the client's highest peak went "
            f"from {c0:.0f} to {c1:.0f} MiB ({c1 / c0:.2f}x), the workers' from {w0:.0f} to {w1:.0f} MiB "
            f"({w1 / w0:.2f}x), and the map file from {m0:.1f} to {m1:.1f} MiB ({m1 / m0:.1f}x). Per command, "
            f"client MiB: {'; '.join(slopes)}. Every peak is {'within' if within else '**not** within'} "
            f"{CLIENT_BOUND_MIB:,} MiB for the client and {WORKER_BOUND_MIB:,} MiB for a worker.\n")


def _query_sentence(runs: list[dict[str, Any]]) -> str:
    """What bounds a Cooc-Map query on each route: the probe's counters (medians over its first 50 queries)."""
    rows = [(r["places"], r["local"]) for r in runs if "visited_median" in r["local"]]
    if not rows:
        return ""
    parts = "; ".join(
        f"{p:,} places: {lo['visited_median']:,.0f} of {lo['locations']:,} locations visited, "
        f"{lo['translation_pruned_median']:,.0f} of them dropped by the bounds before J, J built for "
        f"{lo['built_median']:,.0f}, {lo['ms_one_thread_median']:.1f} ms on one thread "
        f"(probe {lo.get('date', '?')}, load {lo.get('load', float('nan')):.2f})" for p, lo in rows)
    return ("\n**What a Cooc-Map query costs** (`topoloc.coocmap.compiled`; medians over the first 50 queries): "
            f"a location is visited when its candidate count reaches the top_k-th best exact score (top_k = "
            f"{rows[-1][1]['top_k']}, the default), and the bounds before J then drop most of them. {parts}. "
            "The time grows with the locations visited, and those with the route: with 2,000 words a word's "
            "inverted list holds several per cent of the route's locations. The ms per query in the table are "
            "the localiser's, with the matcher's default threads (one per core).\n")


def write_pages(data: dict[str, Any], out: Path) -> None:
    """docs/results/cluster.md (measured) and docs/cluster_scaling.md (the extrapolation)."""
    meta, runs = data["meta"], data["runs"]
    ext = extrapolate(runs[-1])
    cmd = ".venv/bin/python -m benchmarks.bench_cluster --places " + " ".join(str(p) for p in meta["places"])
    lines = [
        "# The command line on a Dask cluster: measured rates and memory\n\n",
        f"Generated by `{cmd}`; do not edit by hand ({meta['machine']}, {meta['cores']} cores, "
        f"Python {meta['python']}, {meta['date']}; 1-minute load average {meta['load_before']:.2f} before "
        f"the run, {meta['load_after']:.2f} after).{_run_dates(runs)}\n\n",
        f"Synthetic routes of {', '.join(f'{p:,}' for p in meta['places'])} places "
        f"({meta['image_size'][0]} x {meta['image_size'][1]} images, `topoloc.bench.cluster_scale`): a map tour "
        "over every place, a tour added with `map add` over one segment of 100 places in four, a query tour "
        f"over one in twenty. Cooc-Map, SIFT at most {meta['max_features']} per image, {meta['words']:,} words. "
        f"Each route gets a fresh `distributed.LocalCluster` of {meta['workers']} worker processes (one thread "
        "each) and a fresh cache, and each command runs as a process of its own with `--scheduler` "
        "(`benchmarks.peak_run` records its peak memory, VmHWM). Worker peaks are VmHWM after a reset before "
        "each command.\n\n",
        "| places | command | images | seconds | images/s | client peak MiB | worker peak MiB | cache on disk MiB "
        "| load |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n",
    ]
    for run in runs:
        for r in run["stages"]:
            lines.append(f"| {run['places']:,} | `{r['stage']}` | {r['items']:,} | {r['seconds']:.1f} | "
                         f"{r['items_per_s']:.1f} | {r['client_peak_mib']:.0f} | {r['worker_peak_mib']:.0f} | "
                         f"{r['disk_bytes'] / 2**20:.1f} | {r['load']:.2f} |\n")
    lines.append("\n| places | shards | map file MiB | map file KiB per place | open s (fresh process) | "
                 "ms per query, matching (median / p95) | ms per query, features | feature store KiB per "
                 "image | per-image cache files | queries within 1 place |\n"
                 "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n")
    for run in runs:
        lo = run["local"]
        lines.append(f"| {run['places']:,} | {run['shards']} | {run['map_bytes'] / 2**20:.1f} | "
                     f"{run['map_bytes'] / run['places'] / 1024:.2f} | {lo['open_s']:.2f} | "
                     f"{lo['ms_matching_median']:.1f} / {lo['ms_matching_p95']:.1f} | "
                     f"{lo['ms_features_median']:.1f} | {run['store_bytes_per_image'] / 1024:.1f} | "
                     f"{run['per_image_cache_files']} | {run['query_right_within_1']:.3f} |\n")
    peaks = [(run["places"], max(r["client_peak_mib"] for r in run["stages"]),
              max(r["worker_peak_mib"] for r in run["stages"])) for run in runs]
    growth = ", ".join(f"{p:,} places: client {c:.0f} MiB, workers {w:.0f} MiB" for p, c, w in peaks)
    lines.append(f"\n**Memory against route length** (highest peak of any command): {growth}. "
                 "The client holds the vocabulary's bounded sample, one wave of block results (word ids and "
                 "keypoint positions, never descriptors: `tests/maps/test_cluster_client_memory.py`), the "
                 "tours' image lists (names, places, times) and, for `map add`, the added tour's word ids and "
                 "positions. The map itself never is in its memory whole: shard models go to scratch files "
                 "beside the map as they arrive, and merging them, adding a tour (a block of locations at a "
                 "time), building the inverted files and writing and checking the file all run a chunk at a "
                 "time, the pages of each chunk let go of when it is done (`topoloc.io.scratch`). A worker holds "
                 "one block of images or one shard. `vocab train`'s client peak grows with the route until its "
                 "descriptor "
                 "sample reaches the cap (`Vocabulary.max_descriptors`, 500,000 by default: 244 MiB of float32 "
                 "SIFT descriptors, k-means working on that), then stays. ms per query are measured in one "
                 "process, one frame at a time, from the map "
                 "file (after one warm-up query), matching excluding feature extraction.\n")
    if len({r["places"] for r in runs}) > 1:  # growth needs two route lengths (one `--places` has one)
        lines.append(_growth_sentence(runs, peaks))
    lines.append(_query_sentence(runs))
    gen = runs[-1]["generation_s"] * TARGET_PLACES / runs[-1]["places"]
    one = sum(e["hours"] for e in ext if e["machines"] == 1)
    lines.append(f"\n**The {TARGET_PLACES:,}-place run on this machine**, estimated from the rates of the "
                 f"{runs[-1]['places']:,}-place route: {gen / 3600:.1f} h to render the route, then {one:.1f} h "
                 "for the four commands ([extrapolation](../cluster_scaling.md)); `--places 100000` runs it.\n")
    (out / "cluster.md").write_text("".join(lines))

    last = runs[-1]
    machines = sorted({e["machines"] for e in ext})
    doc = [
        "# From a laptop to a cluster: what a 1,000 km route costs\n\n",
        f"Generated by `{cmd}` from the rates measured in [results/cluster.md](results/cluster.md) on its "
        f"longest route ({last['places']:,} places); do not edit by hand.\n\n",
        f"FAB-MAP 2.0's 1,000 km route has about {TARGET_PLACES:,} places. Each command's measured rate on this "
        f"machine ({meta['workers']} workers on {meta['cores']} cores, shared with the client) is scaled to "
        f"{TARGET_PLACES:,} places (map and added images in proportion; the queries as measured) on N such "
        "machines. Linear in N, so optimistic for the client's own part (k-means on the bounded sample, merging "
        "shards, writing lines), which does not shrink with N. Image size matters: these images are "
        f"{meta['image_size'][0]} x {meta['image_size'][1]}; SIFT on 640 x 480 frames is about 15 images/s per "
        "core (docs/results/performance.md), so the feature-bound commands (`vocab train` extracts the map's "
        "features) scale by the ratio of the two rates for camera-size images.\n\n",
        "| command | images at 100,000 places | " + " | ".join(f"{n} machine(s) (h)" for n in machines) + " |\n",
        "| --- | --- |" + " --- |" * len(machines) + "\n",
    ]
    for stage in [r["stage"] for r in last["stages"]]:
        es = [e for e in ext if e["stage"] == stage]
        doc.append(f"| `{stage}` | {es[0]['items']:,.0f} | " + " | ".join(f"{e['hours']:.2f}" for e in es) + " |\n")
    per_place = last["map_bytes"] / last["places"]
    doc.append(
        f"\n**Disk**: the feature store takes {last['store_bytes_per_image'] / 1024:.1f} KiB per image "
        f"({TARGET_PLACES * last['store_bytes_per_image'] / 2**30:.2f} GiB for {TARGET_PLACES:,} images; the "
        "vocabulary's sample is drawn from the same store, so no image is stored twice: "
        f"{last['per_image_cache_files']} per-image cache files); the Cooc-Map map file "
        f"{per_place / 1024:.2f} KiB per place ({TARGET_PLACES * per_place / 2**30:.2f} GiB). "
        f"**Memory**: the client peaked at {max(c for _, c, _ in peaks):.0f} MiB and a worker at "
        f"{max(w for _, _, w in peaks):.0f} MiB over routes of {', '.join(f'{p:,}' for p, _, _ in peaks)} places "
        "(see the results page for each).\n")
    (out.parent / "cluster_scaling.md").write_text("".join(doc))


if __name__ == "__main__":
    main()
