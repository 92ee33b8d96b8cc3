"""Regenerate docs/results/scale.md: ``evaluate --top-k`` on 100,000 places x 100,000 queries.

    .venv/bin/python -m benchmarks.bench_scale [--places 100000] [--queries 100000] [--dim 64]

Random global descriptors go through ``topoloc evaluate --method descriptors``
(NumPy ``.npy`` files, as a learned method would write them) with ``--top-k 10``
and ``--tolerance-m``: map place ``i`` is image ``i`` of the map traverse, on a
10 m grid; query ``j`` shows place ``j`` (a random permutation), its descriptor a
noisy copy of the place's (Gaussian noise of ``--noise`` times the descriptors'
spread) and its position the place's plus 1 m of Gaussian noise per axis.  The
traverses' images are symbolic links to one small JPEG (the method never reads
pixels).  The run is one ``topoloc evaluate`` process, timed from outside; its
``metrics.json`` gives the peak resident memory.  ``S_topk.npz`` is checked against
an exact top 10 computed with NumPy for 1,000 random queries.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from benchmarks.common import RESULTS, TOPOLOC


def write_traverse(folder: Path, places: np.ndarray, xy: np.ndarray, image: Path) -> None:
    folder.mkdir(parents=True)
    names = [f"{i:07d}.jpg" for i in range(len(places))]
    for name in names:
        os.symlink(image, folder / name)
    lines = ["image,place,x,y\n"] + [f"{n},{p},{x:.3f},{y:.3f}\n" for n, p, (x, y) in zip(names, places, xy,
                                                                                           strict=True)]
    (folder / "places.csv").write_text("".join(lines))


def make_data(work: Path, n_places: int, n_queries: int, dim: int, noise: float, seed: int = 0) -> dict:
    import cv2

    rng = np.random.default_rng(seed)
    image = work / "frame.jpg"
    cv2.imwrite(str(image), np.full((48, 64, 3), 128, np.uint8))
    side = int(np.ceil(np.sqrt(n_places)))
    grid = np.c_[np.arange(n_places) % side, np.arange(n_places) // side] * 10.0
    map_desc = rng.standard_normal((n_places, dim), dtype=np.float32)
    truth = rng.permutation(n_places)[:n_queries] if n_queries <= n_places else rng.integers(0, n_places, n_queries)
    query_desc = map_desc[truth] + noise * rng.standard_normal((n_queries, dim), dtype=np.float32)
    query_xy = grid[truth] + rng.normal(0, 1.0, (n_queries, 2))
    np.save(work / "map.npy", map_desc)
    np.save(work / "query.npy", query_desc)
    write_traverse(work / "map", np.arange(n_places), grid, image)
    write_traverse(work / "query", truth, query_xy, image)
    return {"map_desc": map_desc, "query_desc": query_desc, "truth": truth}


def check_exact(out: Path, data: dict, n_check: int = 1000, seed: int = 1) -> dict:
    """Compare S_topk.npz with a NumPy top 10 (cosine) for ``n_check`` random queries."""
    z = np.load(out / "S_topk.npz")
    rows, scores = z["rows"], z["scores"]
    k = rows.shape[1]
    pick = np.random.default_rng(seed).choice(len(rows), size=min(n_check, len(rows)), replace=False)
    m = data["map_desc"] / np.linalg.norm(data["map_desc"], axis=1, keepdims=True)
    q = data["query_desc"][pick] / np.linalg.norm(data["query_desc"][pick], axis=1, keepdims=True)
    S = m @ q.T
    want = np.argsort(-S, axis=0, kind="stable")[:k].T
    same_rows = float(np.mean([set(a) == set(b) for a, b in zip(rows[pick], want, strict=True)]))
    err = float(np.abs(np.sort(scores[pick], axis=1) - np.sort(np.take_along_axis(S.T, want, 1), axis=1)).max())
    return {"queries_checked": len(pick), "same_top_k_share": same_rows, "max_score_error": err}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--places", type=int, default=100_000)
    ap.add_argument("--queries", type=int, default=100_000)
    ap.add_argument("--dim", type=int, default=64)
    ap.add_argument("--noise", type=float, default=1.0)
    ap.add_argument("--top-k", type=int, default=10)
    ap.add_argument("--tolerance-m", default="5:15")
    ap.add_argument("--out", type=Path, default=RESULTS / "scale.md")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="topoloc_scale_") as tmp:
        work = Path(tmp)
        t0 = time.perf_counter()
        data = make_data(work, args.places, args.queries, args.dim, args.noise)
        gen_s = time.perf_counter() - t0
        out = work / "run"
        cmd = [str(TOPOLOC), "evaluate", "--method", "descriptors", "--map", str(work / "map"),
               "--query", str(work / "query"), "--param", f"map={work / 'map.npy'}",
               "--param", f"query={work / 'query.npy'}", "--top-k", str(args.top_k),
               "--tolerance-m", args.tolerance_m, "--recall-at", "1,5,10", "--out", str(out), "--quiet"]
        load = os.getloadavg()[0]  # the machine may be shared: say how busy it was
        t0 = time.perf_counter()
        res = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if res.returncode != 0:
            raise SystemExit(f"failed: {' '.join(cmd)}\n{res.stderr}")
        metrics = json.loads((out / "metrics.json").read_text())
        sizes = {p.name: p.stat().st_size for p in sorted(out.iterdir())}
        check = check_exact(out, data)
    shown = " ".join(c if not c.startswith(str(work)) and f"={work}" not in c else
                     c.replace(str(work), "WORK") for c in cmd[1:])
    record = {"places": args.places, "queries": args.queries, "dim": args.dim, "noise": args.noise,
              "top_k": args.top_k, "tolerance_m": args.tolerance_m, "generate_s": round(gen_s, 1),
              "evaluate_wall_s": round(wall, 1), "load_average_before": round(load, 2),
              "peak_rss_mb": round(metrics["peak_rss_mb"], 1),
              "ms_per_query": metrics["ms_per_query"], "metrics": {k: metrics[k] for k in (
                  "auc", "recall_at_100_precision", "recall_at_1", "recall_at_5", "recall_at_10")},
              "files": sizes, "check": check, "command": f"topoloc {shown}",
              "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
              "date": datetime.now(UTC).isoformat(timespec="seconds")}
    write_markdown(record, args.out)
    print(json.dumps(record, indent=2))


def write_markdown(r: dict, path: Path) -> None:
    m = r["metrics"]
    dense_gb = r["places"] * r["queries"] * 4 / 2**30
    files = ", ".join(f"`{k}` {v / 2**20:.1f} MiB" for k, v in r["files"].items() if v > 2**20)
    text = f"""# Evaluation at scale: `--top-k` and ground truth in metres

Generated by `.venv/bin/python -m benchmarks.bench_scale`; do not edit by hand ({r['machine']}, {r['date']}).

{r['places']:,} map places x {r['queries']:,} queries, random {r['dim']}-D float32 global descriptors
(queries: noisy copies of their place's descriptor, noise {r['noise']:g} x the descriptors' spread; places on a
10 m grid, queries 1 m (standard deviation per axis) from their place) through one process:

```
{r['command']}
```

| evaluate wall time | peak memory (peak_rss_mb) | ms per query | AUC | R@100P | R@1 | R@5 | R@10 |
| --- | --- | --- | --- | --- | --- | --- | --- |
| {r['evaluate_wall_s']:.1f} s | {r['peak_rss_mb']:.0f} MiB | {r['ms_per_query']:.3f} | {m['auc']:.4f} | \
{m['recall_at_100_precision']:.4f} | {m['recall_at_1']:.4f} | {m['recall_at_5']:.4f} | {m['recall_at_10']:.4f} |

The wall time covers the whole command: reading the two traverses' `places.csv`, the descriptor files,
the KD-tree ground truth (`--tolerance-m {r['tolerance_m']}`, kept sparse), the exact faiss search of the
{r['top_k']} best places of every query (flat inner-product index on L2-normalised rows: cosine), the metrics
from the kept places and writing the run folder ({files}).
The dense `S` would take {dense_gb:.0f} GiB in float32; it is never formed. Generating the data took
{r['generate_s']:.0f} s more (not counted). The 1-minute load average just before the run was
{r['load_average_before']:.2f} (other jobs share the machine's cores).

Check: for {r['check']['queries_checked']:,} random queries the top {r['top_k']} of `S_topk.npz` equals an
exact NumPy top {r['top_k']} in {100 * r['check']['same_top_k_share']:.1f}% of the queries (largest score
difference {r['check']['max_score_error']:.1e}).

A correct place outside a query's {r['top_k']} kept places counts as not found (`docs/protocol.md`), so
R@N for N > K would equal R@K; here every metric uses N <= K.
"""
    path.write_text(text)
    path.with_suffix(".json").write_text(json.dumps(r, indent=2) + "\n")


if __name__ == "__main__":
    main()
