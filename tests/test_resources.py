"""Resources' bookkeeping stays small on long routes (topoloc.resources)."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np

from topoloc.datasets.traverse import Traverse
from topoloc.resources import InMemoryResources, traverse_key


def _tour(root: Path, n: int, prefix: str = "frame") -> Traverse:
    return Traverse(root=root, images=tuple(root / f"{prefix}_{k:06d}.png" for k in range(n)),
                    places=np.arange(n, dtype=np.int64), name=root.name)


def test_traverse_key_has_a_fixed_size_and_tells_tours_apart(tmp_path: Path) -> None:
    long, short = _tour(tmp_path, 100_000), _tour(tmp_path, 10)
    assert max(len(traverse_key(long)), len(traverse_key(short))) < len(str(tmp_path.resolve())) + 60
    assert traverse_key(long) == traverse_key(_tour(tmp_path, 100_000))
    assert traverse_key(short) != traverse_key(_tour(tmp_path, 10, prefix="other"))


def test_per_image_times_cost_bytes_not_a_key_per_image(tmp_path: Path) -> None:
    # The key used to name every image of the tour for each image: quadratic in the tour's length
    # (12 GB for the tour `map add` adds to a 100,000-place route, benchmarks/bench_cluster.py).
    res = InMemoryResources()
    tour = _tour(tmp_path, 3_000)
    tracemalloc.start()
    try:
        res._map(tour, "test", lambda k: k, "test", True)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20 * 2**20  # the thread pool's futures; the old keys took 100 MB here
    assert [len(ms) for ms in res.image_ms.values()] == [3_000]
    assert res.ms_features_median() >= 0.0
