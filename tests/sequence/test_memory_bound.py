"""The sequence search's memory is bounded before it is allocated (SEQUENCE_MEMORY_BUDGET)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from topoloc.errors import ParameterError
from topoloc.sequence import SEQUENCE_MEMORY_BUDGET, search_memory_bytes, sequence_similarity
from topoloc.sequence.search import acceleration_search, constant_velocity_search
from topoloc.spec import SequenceSpec


@pytest.mark.parametrize("mode", ["constant", "acceleration"])
def test_a_million_frames_is_refused_before_allocation(mode: str) -> None:
    # localize --sequence 1000000 used to try to allocate 4.37 TiB.
    S = np.random.default_rng(0).random((20, 5)).astype(np.float32)
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match="SEQUENCE_MEMORY_BUDGET"):
        sequence_similarity(S, ds=1_000_000, mode=mode)  # type: ignore[arg-type]
    with pytest.raises(ParameterError, match=r"^sequence\.length 1000000 is too long"):
        SequenceSpec(length=1_000_000, mode=mode)
    assert time.perf_counter() - t0 < 1.0


def test_estimate_bounds_what_the_search_allocates() -> None:
    # The estimate is an upper bound of the tile (checked on small cases against tracemalloc).
    import tracemalloc

    D = np.random.default_rng(1).random((300, 200)).astype(np.float32)
    for ds, mode, search in ((7, "constant", constant_velocity_search), (7, "acceleration", acceleration_search)):
        tracemalloc.start()
        search(D, ds=ds, n_jobs=1)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert peak <= search_memory_bytes(ds, mode=mode, n_db=300, n_q=200) + 2 * D.nbytes, (mode, peak)  # type: ignore[arg-type]


def test_lengths_in_use_are_far_under_the_budget() -> None:
    for mode in ("constant", "acceleration"):
        assert search_memory_bytes(100, mode=mode) < SEQUENCE_MEMORY_BUDGET / 10  # type: ignore[arg-type]
        SequenceSpec(length=100, mode=mode)


def test_online_window_counts_the_places() -> None:
    spec = SequenceSpec(length=1000)
    spec.check_memory(100)
    with pytest.raises(ParameterError, match="over 1000000 places"):
        spec.check_memory(1_000_000, online=True)  # 1001 columns of a million places, kept and stacked
