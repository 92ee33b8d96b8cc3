"""Regenerate docs/results/vocabulary.md: the measurements behind the vocabulary defaults.

    .venv/bin/python -m benchmarks.bench_vocabulary [--quick | --page-only]

On this machine, with the project's own code paths:

1. k-means (``DEFAULT_N_ITER``): the descriptor sample ``train_vocabulary`` draws
   (``sample_descriptors``, default SIFT features, default sample size and seed) from
   webcam_daynight/map -- the training set of the gardens_point results -- clustered by
   ``Vocabulary.fit`` into the default number of words for twice ``DEFAULT_N_ITER``
   iterations; the objective and time of each iteration (the k-means is deterministic
   for a seed, so the first ``DEFAULT_N_ITER`` iterations are the default run).  Then the
   same ``DEFAULT_N_ITER``-iteration training with exact assignment (``index="flat"``),
   so that the time and objective of the default approximate (HNSW) assignment have a
   yardstick: wall and CPU seconds of each, and each one's final objective.
2. efSearch (``DEFAULT_EF_SEARCH``): the default cached vocabulary of the same images
   (``cached_vocabulary``, as ``topoloc evaluate --vocab-train`` uses it) quantising a
   seeded sample of 20,000 SIFT descriptors of all gardens_point images with HNSW
   (``HNSW_M``, ``HNSW_EF_CONSTRUCTION``) at several efSearch values and with exact flat
   search: agreement with exact, ms per 1,000 descriptors (interleaved rounds, median),
   and how much farther the mis-assigned descriptors' words are.

``--quick`` (a 20,000-descriptor sample, 1,000 words, 5,000 queries) only prints its JSON:
the committed page comes from the default settings.  ``--page-only`` rewrites the page from
docs/results/vocabulary.json without measuring.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from datetime import UTC, datetime
from typing import Any

import faiss
import numpy as np

from benchmarks.common import DATA, GP, RESULTS, VOCAB_FOR_GP, require_data
from topoloc.bench.quantisation import assignment_excess, interleaved_timings, kmeans_convergence
from topoloc.datasets.traverse import find_images
from topoloc.features import FeatureConfig, FeatureExtractor
from topoloc.vocabulary import Vocabulary, cached_vocabulary
from topoloc.vocabulary.vocab import (
    DEFAULT_EF_SEARCH,
    DEFAULT_N_ITER,
    HNSW_EF_CONSTRUCTION,
    HNSW_M,
    sample_descriptors,
)

EF_SEARCHES = (8, 12, 16, 24, 32)
SEED = 0


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def kmeans_section(extractor: FeatureExtractor, *, n_words: int, max_descriptors: int) -> dict[str, Any]:
    """Train ``n_words`` words for ``2 * DEFAULT_N_ITER`` iterations on the training sample; convergence."""
    images = find_images(VOCAB_FOR_GP)
    sample, n_total = sample_descriptors(images, extractor, max_descriptors=max_descriptors, seed=SEED)
    load = _load()
    print(f"k-means: {len(sample)} of {n_total} descriptors, {n_words} words, load {load}", flush=True)
    voc = Vocabulary(n_words=n_words, n_iter=2 * DEFAULT_N_ITER, max_descriptors=max_descriptors, seed=SEED)
    cpu = time.process_time()
    voc.fit(sample, descriptor_kind=extractor.config.descriptor_kind)
    cpu = time.process_time() - cpu
    p = voc.provenance_
    conv = kmeans_convergence(p["objective_per_iteration"], p["iteration_seconds"], at=DEFAULT_N_ITER)
    print(json.dumps(conv), flush=True)
    return {"images": len(images), "folders": [str(f.relative_to(DATA)) for f in VOCAB_FOR_GP],
            "n_descriptors": n_total, "n_sample": len(sample), "max_descriptors": max_descriptors,
            "n_words": voc.n_words_, "n_iter": voc.n_iter, "default_n_iter": DEFAULT_N_ITER,
            "train_seconds": p["train_seconds"], "objective_per_iteration": p["objective_per_iteration"],
            "iteration_seconds": p["iteration_seconds"], "load_before": load, "load_after": _load(),
            "threads": faiss.omp_get_max_threads(), "cpu_seconds": round(cpu, 1),
            "exact": exact_assignment(sample, extractor, n_words=n_words, max_descriptors=max_descriptors), **conv}


def exact_assignment(sample: np.ndarray, extractor: FeatureExtractor, *, n_words: int,
                     max_descriptors: int) -> dict[str, Any]:
    """The default training with exact (flat) assignment: its seconds and objective, the yardstick of HNSW's."""
    load = _load()
    print(f"k-means with exact assignment: {n_words} words, load {load}", flush=True)
    voc = Vocabulary(n_words=n_words, n_iter=DEFAULT_N_ITER, max_descriptors=max_descriptors, seed=SEED,
                     index="flat")
    cpu = time.process_time()
    voc.fit(sample, descriptor_kind=extractor.config.descriptor_kind)
    p = voc.provenance_
    return {"train_seconds": p["train_seconds"], "cpu_seconds": round(time.process_time() - cpu, 1),
            "objective": p["objective"], "objective_per_iteration": p["objective_per_iteration"],
            "load_before": load, "load_after": _load()}


def query_descriptors(extractor: FeatureExtractor, n: int) -> tuple[np.ndarray, int, int]:
    """Seeded uniform sample of ``n`` descriptors of all gardens_point images; (sample, of how many, images)."""
    images = find_images([GP])
    desc = np.concatenate([f.descriptors for f in extractor.extract_paths(images) if len(f)])
    rng = np.random.default_rng(SEED)
    pick = np.sort(rng.choice(len(desc), size=min(n, len(desc)), replace=False))
    return np.ascontiguousarray(desc[pick]), len(desc), len(images)


def ef_search_section(voc: Vocabulary, queries: np.ndarray, *, repeats: int) -> dict[str, Any]:
    """Agreement with exact search, ms per 1,000 and distance excess for each efSearch, plus flat."""
    kind = voc.descriptor_kind_
    vocabs = {"flat": Vocabulary.from_words(voc.words_, descriptor_kind=kind, index="flat")}
    for ef in EF_SEARCHES:  # one vocabulary (and HNSW index) each, built by the project's code
        vocabs[f"hnsw{ef}"] = Vocabulary.from_words(voc.words_, descriptor_kind=kind, index="hnsw", ef_search=ef)
    exact = vocabs["flat"].quantize(queries)
    load = _load()
    print(f"efSearch sweep: {len(queries)} queries, {voc.n_words_} words, load {load}", flush=True)
    times = interleaved_timings(vocabs, queries, batch=1000, repeats=repeats)
    rows = []
    for name, v in vocabs.items():
        stats = assignment_excess(queries, voc.words_, v.quantize(queries), exact)
        t = times[name]
        rows.append({"index": v.index, "ef_search": v.ef_search if v.index == "hnsw" else None, **stats,
                     "median_ms_per_1000": float(np.median(t)), "p95_ms_per_1000": float(np.percentile(t, 95))})
        print(json.dumps(rows[-1]), flush=True)
    return {"rows": rows, "repeats": repeats, "batch": 1000, "hnsw_m": HNSW_M,
            "hnsw_ef_construction": HNSW_EF_CONSTRUCTION, "default_ef_search": DEFAULT_EF_SEARCH,
            "threads": faiss.omp_get_max_threads(), "load_before": load, "load_after": _load()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="small sample and vocabulary; print the JSON, write no page")
    parser.add_argument("--repeats", type=int, default=100, help="timed rounds of the efSearch sweep")
    parser.add_argument("--page-only", action="store_true", help="rewrite vocabulary.md from vocabulary.json")
    args = parser.parse_args()
    if args.page_only:
        (RESULTS / "vocabulary.md").write_text(render(json.loads((RESULTS / "vocabulary.json").read_text())))
        return
    require_data()
    t_start = time.perf_counter()
    defaults = Vocabulary()
    n_words, max_descriptors = (1000, 20_000) if args.quick else (defaults.n_words, defaults.max_descriptors)
    extractor = FeatureExtractor(FeatureConfig())
    out: dict[str, Any] = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
                   f"faiss {faiss.__version__}",
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "load_at_start": _load(),
        "quick": args.quick,
        "features": extractor.config.key(),
    }
    out["kmeans"] = kmeans_section(extractor, n_words=n_words, max_descriptors=max_descriptors)

    if args.quick:
        sample, _ = sample_descriptors(find_images(VOCAB_FOR_GP), extractor, max_descriptors=max_descriptors,
                                       seed=SEED)
        voc = Vocabulary(n_words=n_words, max_descriptors=max_descriptors, seed=SEED).fit(
            sample, descriptor_kind=extractor.config.descriptor_kind)
        vocab_file = None
    else:  # the vocabulary the gardens_point runs use (trained once, then from the cache)
        voc, path = cached_vocabulary(VOCAB_FOR_GP, extractor=extractor, n_words=n_words, seed=SEED)
        vocab_file = path.name
    queries, n_query_total, n_query_images = query_descriptors(extractor, 5_000 if args.quick else 20_000)
    sweep = ef_search_section(voc, queries, repeats=args.repeats)
    out["ef_search"] = {**sweep, "vocabulary_file": vocab_file, "vocabulary_n_iter": voc.n_iter,
                        "vocabulary_n_words": voc.n_words_,
                        "vocabulary_n_descriptors_used": voc.provenance_.get("n_descriptors_used"),
                        "vocabulary_objective": voc.provenance_.get("objective"),
                        "query_folder": str(GP.relative_to(DATA)), "query_images": n_query_images,
                        "query_descriptors": len(queries), "query_descriptors_total": n_query_total}
    out["load_at_end"] = _load()
    out["wall_seconds"] = round(time.perf_counter() - t_start, 1)
    if args.quick:
        print(json.dumps(out, indent=1))
        return
    (RESULTS / "vocabulary.json").write_text(json.dumps(out, indent=2) + "\n")
    (RESULTS / "vocabulary.md").write_text(render(out))
    print(f"wrote {RESULTS / 'vocabulary.md'} in {out['wall_seconds']:.0f} s")


def _exact_lines(k: dict[str, Any], at: int) -> list[str]:
    """The comparison with exact assignment (absent from pages of the earlier faiss k-means)."""
    x = k.get("exact")
    if not x:
        return []
    hnsw_obj = k["objective_per_iteration"][at - 1]
    hnsw_cpu = k.get("cpu_seconds")
    cpu = "" if hnsw_cpu is None else (f"; CPU {hnsw_cpu * k['seconds_at'] / k['seconds_n']:.0f} s "
                                       f"(pro rata of the {k['n']}-iteration run) against {x['cpu_seconds']:.0f} s")
    return [f"* the same {at} iterations with exact assignment (`index=\"flat\"`, load average {x['load_before']} "
            f"before, {x['load_after']} after): **{x['train_seconds']:.0f} s**, objective {x['objective']:.6g}; the "
            f"default HNSW assignment takes {k['seconds_at'] / x['train_seconds']:.2f}x its wall time{cpu}, and its "
            f"objective after {at} iterations is {100 * (hnsw_obj - x['objective']) / x['objective']:+.2f}% from "
            "exact k-means'\n"]


def render(o: dict[str, Any]) -> str:
    k, e = o["kmeans"], o["ef_search"]
    n, at = k["n"], k["at"]
    obj = o["ef_search"].get("vocabulary_objective")
    check = ("" if obj is None or o["ef_search"]["vocabulary_n_iter"] != at else
             f" (the cached {at}-iteration vocabulary of the efSearch section ends at objective {obj:.6g}; "
             f"iteration {at} here: {k['objective_at']:.6g})")
    sample = (f"all {k['n_sample']:,}" if k["n_sample"] == k["n_descriptors"]
              else f"{k['n_sample']:,} of the {k['n_descriptors']:,}")
    lines = [
        "# Vocabulary defaults: k-means iterations and HNSW efSearch\n\n",
        "What the default vocabulary of a run without `--vocab`/`--vocab-train` costs per method: "
        "[default_vocabulary.md](default_vocabulary.md) (`benchmarks.bench_default_vocab`).\n\n",
        "Generated by `.venv/bin/python -m benchmarks.bench_vocabulary` (raw numbers in `vocabulary.json`); ",
        f"do not edit by hand. Machine: {o['machine']}; {o['date']}; {o['wall_seconds']:.0f} s in all. ",
        f"1-minute load average: {o['load_at_start']} at the start, {o['load_at_end']} at the end (the machine ",
        "may be shared: timings are noisy, compare rows of one table).\n\n",
        f"Features: default SIFT (`{o['features']}`, at most 1,000 per image). These numbers justify ",
        "`DEFAULT_N_ITER` and `DEFAULT_EF_SEARCH` in `src/topoloc/vocabulary/vocab.py`.\n\n",
        "## k-means iterations (`DEFAULT_N_ITER`)\n\n",
        f"Training sample: {sample} SIFT descriptors of the "
        f"{k['images']} images of `{', '.join(k['folders'])}` (the vocabulary training set of the gardens_point "
        f"results), drawn by `sample_descriptors` with the default cap of {k['max_descriptors']:,} and seed 0; "
        f"`Vocabulary.fit` with {k['n_words']:,} words and n_iter = {n}, {k['threads']} faiss threads "
        f"(load average {k['load_before']} before, {k['load_after']} after). The k-means is deterministic "
        f"for a seed, so iterations 1-{at} are the default {at}-iteration run{check}.\n\n",
        f"* seconds per iteration (median of iterations 2-{n}): **{k['median_seconds_per_iteration']:.1f} s**\n",
        f"* {at} iterations: **{k['seconds_at']:.0f} s**; {n} iterations: **{k['seconds_n']:.0f} s** "
        f"(whole `fit`: {k['train_seconds']:.0f} s)\n",
        f"* objective after {at} iterations is **{k['gap_percent']:.2f}%** above its value after {n}\n",
        *_exact_lines(k, at),
        "\n",
        f"| iteration | seconds | cumulative s | objective (sum of squared distances) | above iteration {n} |\n",
        "| --- | --- | --- | --- | --- |\n",
    ]
    cum = np.cumsum(k["iteration_seconds"])
    last = k["objective_per_iteration"][-1]
    for i, (s, c, obj) in enumerate(zip(k["iteration_seconds"], cum, k["objective_per_iteration"], strict=True)):
        lines.append(f"| {i + 1} | {s:.2f} | {c:.1f} | {obj:.4g} | {100 * (obj - last) / last:.2f}% |\n")
    lines += [
        "\n## HNSW efSearch (`DEFAULT_EF_SEARCH`)\n\n",
        f"Vocabulary: the default cached one of the same training set (`{e['vocabulary_file']}`: "
        f"{e['vocabulary_n_words']:,} words, n_iter {e['vocabulary_n_iter']}, "
        f"{e['vocabulary_n_descriptors_used']:,} descriptors), as `topoloc evaluate --vocab-train` loads it. "
        f"Queries: {e['query_descriptors']:,} SIFT descriptors drawn (seed 0) from the "
        f"{e['query_descriptors_total']:,} of all {e['query_images']} images of `{e['query_folder']}`. "
        f"HNSW with M = {e['hnsw_m']}, efConstruction = {e['hnsw_ef_construction']}, built by `Vocabulary`. "
        f"Time: `Vocabulary.quantize` on 1,000 descriptors, {e['repeats']} rounds that time every index in turn "
        f"(order rotated each round), {e['threads']} faiss threads (load average {e['load_before']} before, "
        f"{e['load_after']} after). Distance excess: over the descriptors assigned to another word than exact "
        "search's, the median of (distance to that word / distance to the nearest word - 1).\n\n",
        "| index | agreement with exact | mis-assigned | median distance excess of mis-assigned "
        "| median ms per 1,000 | p95 ms per 1,000 | time / flat |\n",
        "| --- | --- | --- | --- | --- | --- | --- |\n",
    ]
    flat_ms = next(r["median_ms_per_1000"] for r in e["rows"] if r["index"] == "flat")
    for r in e["rows"]:
        name = "flat (exact)" if r["index"] == "flat" else f"hnsw efSearch {r['ef_search']}"
        if r["ef_search"] == e["default_ef_search"]:
            name = f"**{name} (default)**"
        excess = "" if r["median_distance_excess"] is None else f"{100 * r['median_distance_excess']:.1f}%"
        lines.append(f"| {name} | {100 * r['agreement']:.2f}% | {r['n_misassigned']:,} | {excess} | "
                     f"{r['median_ms_per_1000']:.2f} | {r['p95_ms_per_1000']:.2f} | "
                     f"{r['median_ms_per_1000'] / flat_ms:.2f} |\n")
    return "".join(lines)


if __name__ == "__main__":
    main()
