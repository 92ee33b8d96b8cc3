"""Helpers of benchmarks/bench_vocabulary.py: k-means convergence, assignment excess, interleaved timing."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.bench.quantisation import assignment_excess, interleaved_timings, kmeans_convergence
from topoloc.vocabulary import Vocabulary


def test_kmeans_convergence_reads_the_shorter_run_off_the_longer_one() -> None:
    obj = [200.0, 120.0, 110.0, 105.0, 100.0]
    sec = [3.0, 1.0, 2.0, 1.0, 1.0]  # the first includes the initialisation
    c = kmeans_convergence(obj, sec, at=3)
    assert c["n"] == 5 and c["at"] == 3
    assert c["seconds_at"] == pytest.approx(6.0) and c["seconds_n"] == pytest.approx(8.0)
    assert c["median_seconds_per_iteration"] == pytest.approx(1.0)  # iterations 2..5 only
    assert c["objective_at"] == 110.0 and c["objective_n"] == 100.0
    assert c["gap_percent"] == pytest.approx(10.0)
    assert kmeans_convergence(obj, sec, at=5)["gap_percent"] == 0.0
    for bad in (0, 6):
        with pytest.raises(ValueError, match="at="):
            kmeans_convergence(obj, sec, at=bad)
    with pytest.raises(ValueError, match="4 times"):
        kmeans_convergence(obj, sec[:4], at=2)


def test_assignment_excess_measures_only_the_misassigned() -> None:
    words = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 20.0]])
    x = np.array([[1.0, 0.0], [2.0, 0.0], [9.0, 0.0], [0.0, 19.0]])
    exact = np.array([0, 0, 1, 2])
    approx = np.array([0, 1, 1, 0])  # row 1: 8 instead of 2 (+300%); row 3: 19 instead of 1 (+1800%)
    r = assignment_excess(x, words, approx, exact)
    assert r["agreement"] == 0.5 and r["n_misassigned"] == 2
    assert r["median_distance_excess"] == pytest.approx((3.0 + 18.0) / 2)
    same = assignment_excess(x, words, exact, exact)
    assert same == {"agreement": 1.0, "n_misassigned": 0, "median_distance_excess": None}
    with pytest.raises(ValueError, match="shapes"):
        assignment_excess(x, words, approx[:3], exact)


def test_interleaved_timings_time_every_vocabulary_every_round() -> None:
    rng = np.random.default_rng(0)
    words = rng.random((50, 128), dtype=np.float32)
    kind = "sift-128-float32"
    vocabs = {"flat": Vocabulary.from_words(words, descriptor_kind=kind, index="flat"),
              "hnsw8": Vocabulary.from_words(words, descriptor_kind=kind, index="hnsw", ef_search=8)}
    t = interleaved_timings(vocabs, rng.random((30, 128), dtype=np.float32), batch=20, repeats=4)
    assert set(t) == {"flat", "hnsw8"}
    assert all(v.shape == (4,) and (v > 0).all() for v in t.values())
    with pytest.raises(ValueError):
        interleaved_timings({}, words, repeats=1)
