"""Regenerate docs/results/performance.md: speed of the foundation's building blocks.

    .venv/bin/python -m benchmarks.bench_performance

Measures, on this machine: local-feature extraction in images/s at 640x480 (gardens_point
images resized), 10,000-word vocabulary training time on SIFT descriptors of
all webcam_daynight images, quantisation time per 1,000 descriptors with the default HNSW index
and its agreement with exact nearest-word search, and every method's ms/query from the runs under
docs/results/runs/ (run the other benchmarks first).
"""

from __future__ import annotations

import json
import os
import platform
import time
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime
from typing import Any

import cv2
import numpy as np

from benchmarks.common import GP, RESULTS, WEBCAM, keep_sections, require_data
from topoloc.bench.quantisation import measure_quantisation, quantisation_agreement
from topoloc.datasets.traverse import find_images, read_image
from topoloc.evaluation.timing import peak_rss_mb
from topoloc.features import FeatureConfig, FeatureExtractor, extract_features
from topoloc.vocabulary import Vocabulary


def feature_speed(images: list[np.ndarray], method: str) -> dict[str, Any]:
    cfg = FeatureConfig(method=method, max_features=1000)
    extract_features(images[0], cfg)  # warm-up (detector creation)
    t0 = time.perf_counter()
    n_feat = [len(extract_features(im, cfg)) for im in images]
    serial = time.perf_counter() - t0
    workers = os.cpu_count() or 1
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=workers) as pool:
        list(pool.map(lambda im: extract_features(im, cfg), images))
    parallel = time.perf_counter() - t0
    return {"method": method, "images": len(images), "mean_features": float(np.mean(n_feat)),
            "images_per_s_1_thread": len(images) / serial,
            f"images_per_s_{workers}_threads": len(images) / parallel, "threads": workers}


def main() -> None:
    require_data()
    out: dict[str, Any] = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    paths = find_images([GP / "day_left"])[:60]
    images = [cv2.resize(read_image(p), (640, 480), interpolation=cv2.INTER_AREA) for p in paths]
    out["features"] = [feature_speed(images, m) for m in ("sift", "rootsift", "orb", "akaze")]
    print(json.dumps(out["features"], indent=1), flush=True)

    # Vocabulary training: SIFT descriptors of every webcam_daynight image (map and queries).
    ex = FeatureExtractor(FeatureConfig(method="sift", max_features=1000))
    train = ex.extract_paths(find_images([WEBCAM]))  # map tours and queries: ~370k descriptors
    desc = np.concatenate([f.descriptors for f in train])
    voc = Vocabulary(n_words=10000, seed=0)
    t0 = time.perf_counter()
    voc.fit(desc, descriptor_kind=ex.config.descriptor_kind)
    out["vocabulary"] = {"n_words": voc.n_words_, "n_descriptors": len(desc), "n_images": len(train),
                         "n_iter": voc.n_iter, "train_seconds": time.perf_counter() - t0}
    print(out["vocabulary"], flush=True)

    # Quantisation of descriptors the vocabulary has not seen (gardens_point).
    test = np.concatenate([f.descriptors for f in ex.extract_paths(find_images([GP / "night_right"]))])
    q = measure_quantisation(voc, test, batch=1000, repeats=100)
    q["agreement_with_exact"] = quantisation_agreement(voc, test[:20000])
    flat = Vocabulary(n_words=10000, index="flat")
    flat.words_, flat.n_words_ = voc.words_, voc.n_words_
    flat.descriptor_kind_, flat.n_features_in_, flat.provenance_ = voc.descriptor_kind_, voc.n_features_in_, {}
    q["exact_flat_median_ms_per_1000"] = measure_quantisation(flat, test, batch=1000, repeats=20)[
        "median_ms_per_1000"]
    out["quantisation"] = q
    print(q, flush=True)

    matching = []
    for mpath in sorted((RESULTS / "runs").glob("*/metrics.json")):
        m = json.loads(mpath.read_text())
        matching.append({"run": mpath.parent.name, "method": m["method"], "ms_per_query": m["ms_per_query"],
                         "ms_per_query_p95": m["run"]["ms_per_query_p95"], "n_places": m["n_places"],
                         "ms_features": m["ms_features"], "peak_rss_mb": m["peak_rss_mb"]})
    out["matching"] = matching
    # Method benchmarks at scale, written by benchmarks/bench_fabmap.py and bench_coocmap.py.
    for name in ("fabmap_speed", "coocmap_speed", "coocmap_speed_real", "seqslam_speed"):
        f = RESULTS / f"{name}.json"
        out[name] = json.loads(f.read_text()) if f.is_file() else None
    out["peak_rss_mb"] = peak_rss_mb()
    (RESULTS / "performance.json").write_text(json.dumps(out, indent=2) + "\n")
    # The sections other benchmarks write into this page (bench_load, bench_camera_rate,
    # bench_feature_scale) stay.
    (RESULTS / "performance.md").write_text(keep_sections(RESULTS / "performance.md", render(out)))
    print(f"wrote {RESULTS / 'performance.md'}")


def render(o: dict[str, Any]) -> str:
    thr = o["features"][0]["threads"]
    lines = [
        "# Performance of the foundation\n\n",
        "Generated by `.venv/bin/python -m benchmarks.bench_performance` (raw numbers in `performance.json`); ",
        f"do not edit by hand. Machine: {o['machine']}; {o['date']}.\n\n",
        "## Local features at 640x480 (60 gardens_point images resized, at most 1000 per image)\n\n",
        f"| features | mean features/image | images/s, 1 thread | images/s, {thr} threads |\n",
        "| --- | --- | --- | --- |\n",
    ]
    for f in o["features"]:
        lines.append(f"| {f['method']} | {f['mean_features']:.0f} | {f['images_per_s_1_thread']:.1f} | "
                     f"{f[f'images_per_s_{thr}_threads']:.1f} |\n")
    v = o["vocabulary"]
    lines += [
        "\n## Vocabulary training (faiss k-means)\n\n",
        f"{v['n_words']} words on {v['n_descriptors']} SIFT descriptors ({v['n_images']} webcam_daynight images), "
        f"{v['n_iter']} iterations: **{v['train_seconds']:.1f} s** (feature extraction excluded).\n\n",
    ]
    q = o["quantisation"]
    lines += [
        "## Quantisation (1,000 SIFT descriptors of gardens_point night_right, 10,000 words)\n\n",
        "| index | median ms per 1,000 | p95 ms per 1,000 | agreement with exact nearest word |\n",
        "| --- | --- | --- | --- |\n",
        f"| {q['index']} (efSearch {q['ef_search']}) | **{q['median_ms_per_1000']:.2f}** | "
        f"{q['p95_ms_per_1000']:.2f} | {q['agreement_with_exact']:.3f} |\n",
        f"| flat (exact) | {q['exact_flat_median_ms_per_1000']:.2f} | | 1.000 |\n",
    ]
    at_scale = []
    f2, cm, sq = o.get("fabmap_speed"), o.get("coocmap_speed"), o.get("seqslam_speed")
    if f2:
        b = f2["fabmap2_100000"]
        at_scale.append("| FAB-MAP 2.0, 100,000 places (`topoloc bench fabmap2`) | "
                        f"median {b['ms_per_query_median']:.2f}, p95 {b['ms_per_query_p95']:.2f} ms per query | "
                        "paper: 14 ms mean |\n")
    cr = o.get("coocmap_speed_real")
    if cr:  # written by benchmarks/bench_coocmap_speed.py
        at_scale.append(f"| Cooc-Map, real features: {cr['locations']} locations x {cr['tours']} tours, median "
                        f"{cr['n_features_median']:.0f} SIFT features per image ([coocmap_speed.md](coocmap_speed.md), "
                        f"`topoloc bench coocmap --real`) | median {cr['ms_per_query_median']:.1f}, p95 "
                        f"{cr['ms_per_query_p95']:.1f} ms per localisation; map {cr['map_bytes'] / 1e6:.1f} MB | "
                        "paper: 82 ms |\n")
    if cm:
        at_scale.append(f"| Cooc-Map, synthetic: {cm['locations']} locations x {cm['tours']} tours, "
                        f"{cm['features']} features "
                        f"(`topoloc bench coocmap`) | median {cm['ms_per_query_median']:.1f}, p95 "
                        f"{cm['ms_per_query_p95']:.1f} ms per localisation; map {cm['map_bytes'] / 1e6:.1f} MB | "
                        "paper: 82 ms |\n")
    if sq:
        n = sq["nordland"]["runs"][0]
        at_scale.append(f"| SeqSLAM, nordland 1,788 x 1,788 (difference matrix + search) | {n['ms_per_query']:.2f} ms "
                        "per query | OpenSeqSLAM ~50 ms |\n")
    if at_scale:
        lines += ["\n## Methods at scale (from the method benchmarks' JSON files)\n\n",
                  "| benchmark | measured | reference |\n| --- | --- | --- |\n", *at_scale]
    lines += [
        "\n## Matching time per query, every method (from the runs under `docs/results/runs/`)\n\n",
        "Feature extraction excluded; frames/s = 1000 / ms per query. Each run is its own process.\n\n",
        "| run | method | places | ms/query median | p95 | frames/s | ms features/image | peak MiB |\n",
        "| --- | --- | --- | --- | --- | --- | --- | --- |\n",
    ]
    for b in o["matching"]:
        lines.append(f"| {b['run']} | {b['method']} | {b['n_places']} | {b['ms_per_query']:.2f} | "
                     f"{b['ms_per_query_p95']:.2f} | {1000 / max(b['ms_per_query'], 1e-9):.1f} | "
                     f"{b['ms_features']:.1f} | {b['peak_rss_mb']:.0f} |\n")
    return "".join(lines)


if __name__ == "__main__":
    main()
