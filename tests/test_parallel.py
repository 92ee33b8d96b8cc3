"""Per-query searches on one OpenMP thread: same results, other threads' settings untouched."""

from __future__ import annotations

import threading

import faiss
import numpy as np
import pytest

from topoloc._parallel import SERIAL_SEARCH_ROWS, search_threads
from topoloc.vocabulary import Vocabulary


def test_small_searches_run_on_one_thread_and_restore_the_setting() -> None:
    before = faiss.omp_get_max_threads()
    with search_threads(10):
        assert faiss.omp_get_max_threads() == 1
    assert faiss.omp_get_max_threads() == before
    with search_threads(SERIAL_SEARCH_ROWS + 1):
        assert faiss.omp_get_max_threads() == before


def _read_in_a_new_thread() -> int:
    seen: list[int] = []
    t = threading.Thread(target=lambda: seen.append(faiss.omp_get_max_threads()))
    t.start()
    t.join(10)
    return seen[0]


def test_the_setting_belongs_to_the_calling_thread() -> None:
    """OpenMP's thread count is per thread: a query's search does not serialise another thread's."""
    default = _read_in_a_new_thread()
    if default < 2:
        pytest.skip("one OpenMP thread by default here: nothing to tell apart")
    with search_threads(10):
        assert faiss.omp_get_max_threads() == 1
        assert _read_in_a_new_thread() == default


def test_quantisation_is_the_same_on_one_thread_and_on_several() -> None:
    rng = np.random.default_rng(0)
    train = rng.random((4000, 128), dtype=np.float32)
    voc = Vocabulary(n_words=200, seed=0).fit(train, descriptor_kind="sift-128-float32")
    X = rng.random((SERIAL_SEARCH_ROWS + 500, 128), dtype=np.float32)
    faiss.omp_set_num_threads(2)
    big = voc.quantize(X)  # above the limit: faiss's threads
    small = np.concatenate([voc.quantize(X[i:i + 1000]) for i in range(0, len(X), 1000)])  # one thread each
    np.testing.assert_array_equal(big, small)
