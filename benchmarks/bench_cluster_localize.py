"""Batch localisation on 1 and 2 Dask workers, against a map that ``benchmarks/bench_cluster.py`` built.

    .venv/bin/python -m benchmarks.bench_cluster_localize [--work build/cluster_route] [--places 20000]

Re-measures the localisation stage alone (the query tour of the scale route,
``topoloc localize --scheduler``'s path ``topoloc.maps.batch.localize_on``), each
worker count on a fresh ``distributed.LocalCluster`` of one-thread workers,
after a warm-up batch that opens the map and compiles the matcher on every
worker. Prints queries per second and records them in ``docs/results/cluster.json``
(key ``localisation_recheck``), from which ``bench_cluster --page-only`` rewrites the pages.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, default=ROOT / "build" / "cluster_route")
    ap.add_argument("--places", type=int, default=20_000)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--results", type=Path, default=ROOT / "docs" / "results" / "cluster.json")
    args = ap.parse_args()

    import distributed

    from topoloc.cluster import connect
    from topoloc.datasets.traverse import load_traverse
    from topoloc.maps.batch import localize_on
    from topoloc.maps.map import Map

    map_file = args.work / "route_w1.tlm"
    query = load_traverse(args.work / f"route_{args.places}" / "query")
    load = os.getloadavg()[0]
    print(f"load average before: {load:.2f}")
    rates: dict[str, float] = {}
    for w in args.workers:
        with distributed.LocalCluster(n_workers=w, threads_per_worker=1, processes=True, dashboard_address=None,
                                      host="127.0.0.1", silence_logs=40) as cluster, \
                connect(cluster.scheduler_address, timeout_s=60) as ex:
            warm = [(p.name, None, query.read(k, gray=False)) for k, p in enumerate(query.images[:64])]
            list(localize_on(ex, Map.load(map_file).localizer(top_k=1), iter(warm)))
            frames = ((p.name, None, query.read(k, gray=False)) for k, p in enumerate(query.images))
            t0 = time.perf_counter()
            n = sum(1 for _ in localize_on(ex, Map.load(map_file).localizer(top_k=1), frames))
            rates[str(w)] = n / (time.perf_counter() - t0)
            print(f"{w} worker(s): {rates[str(w)]:.1f} queries/s ({n} queries)")
    if args.results.is_file():
        data = json.loads(args.results.read_text())
        data["localisation_recheck"] = {"queries_per_s": rates, "load_before": load, "queries": len(query)}
        args.results.write_text(json.dumps(data, indent=2, default=float) + "\n")


if __name__ == "__main__":
    main()
