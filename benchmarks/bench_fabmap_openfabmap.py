"""Regenerate docs/results/fabmap_openfabmap.md (+ .json): FAB-MAP 2.0 beside openFABMAP 2.0 per query.

    .venv/bin/python -m benchmarks.bench_fabmap_openfabmap --openfabmap-src OPENFABMAP_CLONE

The openFABMAP sources are a clone of its public repository (``benchmarks/openfabmap.py`` names the
repository and the commit measured), given by ``--openfabmap-src`` or ``$OPENFABMAP_SRC``.

Both implementations score the same words in one run: openFABMAP 2.0 (``of2::FabMap2``,
sampled new-place term, Chow-Liu; built from its public repository by
``benchmarks/openfabmap.py``) and topoloc's ``fabmap2`` with ``output=posterior`` (the
posterior of Eq. 3 with the sampled new place; openFABMAP's ``localize`` without a motion model
normalises the same likelihoods without a location prior and smooths them by 0.99) and with the
default ``output=loglik``.  They share the Chow-Liu tree and detector model (topoloc's,
exported to openFABMAP's layout), the training images of the new-place term, the map images
(each its own location) and the queries:

* ``webcam``: webcam_daynight, all 12 map tours (576 images), its 976 queries, the 10,000-word
  vocabulary and model trained on gardens_point (as in fabmap.md; features from the cache);
* ``synthetic``: Zipf bag-of-words (:mod:`topoloc.synth.words`), 10,000 words, ~300 words per
  image, 1,000 map places, 1,000 training images, 300 revisit queries.

Per query the time is the fastest of ``ROUNDS`` calls, the rounds alternating between the two
implementations so that a change of machine load hits both; openFABMAP's time is its
``FabMap2::localize`` call, topoloc's the method's ``_score`` of one query (word states
included).  The load average is recorded beside the numbers.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from benchmarks.common import RESULTS, VOCAB_FOR_WEBCAM, WEBCAM, WEBCAM_TOURS, require_data
from benchmarks.openfabmap import SRC_ENV, OpenFabMapUnavailable, build_openfabmap, run_openfabmap
from topoloc.datasets import load_traverse
from topoloc.datasets.groundtruth import ground_truth_from_places
from topoloc.evaluation.metrics import recall_at_k
from topoloc.fabmap.model import FabMapModel
from topoloc.maps import Map
from topoloc.methods.fab_map import FabMap2
from topoloc.synth.words import revisit_queries, zipf_occurrence

ROUNDS = 3


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def _method(model: FabMapModel, words: Sequence[np.ndarray], places: np.ndarray, output: str) -> FabMap2:
    """A fitted ``fabmap2`` on these words (what ``fit`` builds from a traverse's words)."""
    m = FabMap2(output=output)
    m.model_ = model
    m.obs_ptr_ = np.r_[0, np.cumsum([len(w) for w in words])].astype(np.int64)
    m.obs_words_ = np.concatenate(words).astype(np.int64)
    m.obs_places_ = np.asarray(places, dtype=np.int64)
    m._build_places()
    return m


def _time_ours(m: FabMap2, items: Sequence[np.ndarray]) -> np.ndarray:
    m._score(items[:1])  # warm-up outside the timings, as the driver does
    ms = np.empty(len(items))
    for j, it in enumerate(items):
        t = time.perf_counter()
        m._score([it])
        ms[j] = 1e3 * (time.perf_counter() - t)
    return ms


def side_by_side(name: str, model: FabMapModel, training: Sequence[np.ndarray], words: Sequence[np.ndarray],
                 places: np.ndarray, queries: Sequence[np.ndarray], truth: np.ndarray) -> dict[str, Any]:
    """Per-query milliseconds of openFABMAP 2.0 and of ``fabmap2`` (posterior, loglik) on the same words.

    ``truth``: each query's place; R@1 counts the queries whose best map image is of that place.
    """
    items = [np.unique(np.asarray(q, np.int64)).astype(np.int32) for q in queries]
    ours = {out: _method(model, words, places, out) for out in ("posterior", "loglik")}
    times: dict[str, list[np.ndarray]] = {"openfabmap": [], "posterior": [], "loglik": []}
    load_before = _load()
    of: dict[str, np.ndarray] = {}
    of_lik = np.zeros(0)
    for r in range(ROUNDS):
        of = run_openfabmap(model, training, words, items, reps=1, likelihoods=r == 0)
        of_lik = of["log_lik"] if r == 0 else of_lik
        times["openfabmap"].append(of["ms"])
        for output, m in ours.items():
            times[output].append(_time_ours(m, items))
    load_after = _load()
    best = {k: np.min(np.stack(v), axis=0) for k, v in times.items()}
    # which map image each side ranks first (ours per image: the method's models are grouped by place)
    m = ours["loglik"]
    rows = np.searchsorted(m.place_ids_, m.obs_places_)
    image_of_model = np.argsort(rows, kind="stable")
    our_best = np.array([image_of_model[int(np.argmax(m.map_.log_likelihood(m.obs_model_.observe(it))))]
                         for it in items])
    # R@1 as `evaluate` counts it (ties as chance): a place scores its best image on both sides
    place_ids = np.unique(places)
    of_S = np.full((place_ids.size, len(items)), -np.inf)
    np.maximum.at(of_S, np.searchsorted(place_ids, places), of_lik)
    gt = ground_truth_from_places(place_ids, np.asarray(truth), hard=0, soft=0)
    out: dict[str, Any] = {
        "workload": name, "n_map_images": len(words), "n_places": int(np.unique(places).size),
        "n_training": len(training), "n_queries": len(items), "n_words": model.n_words,
        "words_per_query": float(np.mean([it.size for it in items])),
        "load_average_before": load_before, "load_average_after": load_after, "rounds": ROUNDS,
        "same_best_image": float(np.mean(our_best == of["best"])),
        "recall_at_1_openfabmap": float(np.mean(np.asarray(places)[of["best"]] == truth)),
        "recall_at_1_fabmap2": float(np.mean(np.asarray(places)[our_best] == truth)),
        "recall_at_1_ties_as_chance_openfabmap": recall_at_k(of_S, gt, (1,))[1],
        "recall_at_1_ties_as_chance_fabmap2": recall_at_k(m._score(items), gt, (1,))[1],
    }
    for k, v in best.items():
        out[k] = {"ms_median": float(np.median(v)), "ms_p95": float(np.percentile(v, 95)),
                  "ms_mean": float(v.mean())}
    for k in ("posterior", "loglik"):
        out[f"ratio_{k}"] = out[k]["ms_median"] / out["openfabmap"]["ms_median"]
    print(json.dumps(out), flush=True)
    return out


def webcam() -> dict[str, Any]:
    m = Map.build(method="fabmap2", tours=WEBCAM_TOURS, vocab_train=VOCAB_FOR_WEBCAM)
    rec = m.recognizer
    assert isinstance(rec, FabMap2)
    words = np.split(rec.obs_words_, rec.obs_ptr_[1:-1])
    q = load_traverse(WEBCAM / "queries")
    queries = rec._encode(q, m.resources())
    training = rec.model_.training_words()  # all of them: n_samples (1000) exceeds the 300 images
    return side_by_side("webcam", rec.model_, training, words, rec.obs_places_, queries, q.places)


def synthetic() -> dict[str, Any]:
    v, wpi = 10_000, 300
    train = zipf_occurrence(1000, n_words=v, words_per_image=wpi, seed=101, permutation_seed=0)
    model = FabMapModel.train(train, n_words=v)
    x = zipf_occurrence(1000, n_words=v, words_per_image=wpi, seed=202, permutation_seed=0)
    queries, truth = revisit_queries(x, 300, words_per_image=wpi, permutation_seed=0, seed=303)
    words = [x.indices[x.indptr[i]:x.indptr[i + 1]].astype(np.int64) for i in range(x.shape[0])]
    return side_by_side("synthetic", model, model.training_words(), words, np.arange(len(words)), queries,
                        np.asarray(truth))


def _row(r: dict[str, Any], label: str) -> str:
    o, p, ll = r["openfabmap"], r["posterior"], r["loglik"]
    return (f"| {label} | {o['ms_median']:.3f} / {o['ms_p95']:.3f} | {p['ms_median']:.3f} / {p['ms_p95']:.3f} | "
            f"**{r['ratio_posterior']:.2f}x** | {ll['ms_median']:.3f} / {ll['ms_p95']:.3f} | "
            f"{r['ratio_loglik']:.2f}x | {100 * r['same_best_image']:.1f}% | {r['recall_at_1_openfabmap']:.3f} / "
            f"{r['recall_at_1_fabmap2']:.3f} | {r['recall_at_1_ties_as_chance_openfabmap']:.3f} / "
            f"{r['recall_at_1_ties_as_chance_fabmap2']:.3f} | {r['load_average_before']} -> "
            f"{r['load_average_after']} |\n")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--openfabmap-src", help=f"openFABMAP sources (a clone of its repository; default ${SRC_ENV})")
    args = ap.parse_args(argv)
    if args.openfabmap_src:
        os.environ[SRC_ENV] = args.openfabmap_src  # read by run_openfabmap's build
    require_data()
    try:
        build_openfabmap()  # before any work: sources missing or not compiling stop the benchmark here
        results = [webcam(), synthetic()]
    except OpenFabMapUnavailable as e:
        raise SystemExit(f"bench_fabmap_openfabmap: {e}") from e
    (RESULTS / "fabmap_openfabmap.json").write_text(json.dumps(
        {"machine": f"{platform.machine()}, {os.cpu_count()} cores", "results": results}, indent=2) + "\n")
    wc, syn = results
    text = [
        "# FAB-MAP 2.0 beside openFABMAP 2.0, per query\n\n",
        "Generated by `.venv/bin/python -m benchmarks.bench_fabmap_openfabmap`; do not edit by hand. Both score ",
        "the same words in one run: openFABMAP 2.0 (`of2::FabMap2::localize`, sampled new-place term, Chow-Liu, ",
        "compiled with `g++ -O3` from its public repository by `benchmarks/openfabmap.py`; only the driver ",
        "`benchmarks/openfabmap_driver.cpp` is kept here) and topoloc's `fabmap2` with `output=posterior` (the ",
        "posterior of Eq. 3 with the sampled new place; openFABMAP's `localize` without a motion model normalises ",
        "the same likelihoods without a location prior and smooths them by 0.99) and with the default ",
        "`output=loglik`. Same Chow-Liu tree and detector model, same training images for the ",
        "new-place term, each map image its own location. Times are milliseconds per query, median / p95, each ",
        f"query's fastest of {ROUNDS} rounds that alternate between the two; ratio = topoloc / openFABMAP ",
        "(below 1: topoloc faster). `same best image`: queries on which both rank the same map image first; R@1: ",
        "queries whose best map image is of their own place (each image its own location, a place scored by its ",
        "best image; a tie goes to the first image), for both on these words; `ties as chance` counts R@1 as ",
        "`topoloc evaluate` does (a tie between places scores the chance of drawing the right one: queries without ",
        "features, and images with the same few words, tie). ",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores; its load average (1, 5, 15 min) before and ",
        "after each workload is in the last column: a loaded machine slows both sides.\n\n",
        "| words | openFABMAP 2.0 ms | fabmap2 posterior ms | ratio | fabmap2 loglik ms | ratio | same best image "
        "| R@1 openFABMAP / fabmap2 | same, ties as chance | load average |\n",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n",
        _row(wc, f"webcam_daynight: {wc['n_map_images']} map images (12 tours), {wc['n_queries']} queries "
                 f"(~{wc['words_per_query']:.0f} words), {wc['n_training']} training images, "
                 f"{wc['n_words']:,}-word vocabulary from gardens_point"),
        _row(syn, f"synthetic Zipf: {syn['n_map_images']:,} places, {syn['n_queries']} queries "
                  f"(~{syn['words_per_query']:.0f} words), {syn['n_training']:,} training images, "
                  f"{syn['n_words']:,} words"),
        "\nRaw numbers: `fabmap_openfabmap.json`.\n",
    ]
    (RESULTS / "fabmap_openfabmap.md").write_text("".join(text))
    print(f"wrote {RESULTS / 'fabmap_openfabmap.md'}")


if __name__ == "__main__":
    main()
