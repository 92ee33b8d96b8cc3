"""Maps built from shards equal maps built in one piece: every method, 3 shards, locally and on Dask."""

from __future__ import annotations

import sys
from typing import Any

import numpy as np
import pytest

from topoloc.cluster import LocalExecutor
from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.io.scratch import file_backed, spill_to
from topoloc.methods import available_methods, get_method, shard_build
from topoloc.methods.shard_build import build_from_shards
from topoloc.methods.shards import ShardPart, shard_maps, split_places
from topoloc.resources import InMemoryResources

FAST: dict[str, dict[str, Any]] = {"fabmap": {"n_samples": 20}, "fabmap2": {"n_samples": 20, "output": "posterior"},
                                   "seqslam": {"ds": 3}, "coocmap": {"top_k": 3}}


def _res(route: dict[str, Any]) -> InMemoryResources:
    return InMemoryResources(vocabulary=route["vocabulary"], training=route["training"])


def _shuffled(t: Traverse, seed: int) -> Traverse:
    """The tour with its images in another order (places no longer increase along it)."""
    order = np.random.default_rng(seed).permutation(len(t))
    return Traverse(root=t.root, images=tuple(t.images[i] for i in order), places=t.places[order],
                    times=None if t.times is None else t.times[order], name=t.name + "_shuffled")


def assert_same_state(a: Any, b: Any) -> None:
    """Equal metadata and equal arrays, bit for bit (same dtype, same shape, same bytes)."""
    meta_a, arrays_a = a.get_state()
    meta_b, arrays_b = b.get_state()
    assert meta_a == meta_b
    assert sorted(arrays_a) == sorted(arrays_b)
    for name in arrays_a:
        x, y = np.asarray(arrays_a[name]), np.asarray(arrays_b[name])
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert x.tobytes() == y.tobytes(), name


def test_split_places_covers_every_place_once() -> None:
    ids = np.array([2, 3, 5, 8, 9, 10, 11])
    ranges = split_places(ids, 3)
    assert ranges == [(2, 5), (5, 9), (9, 12)]
    inside = [[int(p) for p in ids if lo <= p < hi] for lo, hi in ranges]
    assert [p for part in inside for p in part] == ids.tolist() and all(inside)
    assert len(split_places(ids, 50)) == len(ids)  # at most one shard per place
    with pytest.raises(TopolocError, match="at least 1"):
        split_places(ids, 0)


def test_shard_positions_index_the_concatenated_tours(tiny_route: dict[str, Any]) -> None:
    maps = [tiny_route["map"], _shuffled(tiny_route["training"], 1)]
    seen = []
    for rng in split_places(np.unique(np.concatenate([m.places for m in maps])), 3):
        subs, pos = shard_maps(maps, rng)
        places = np.concatenate([m.places for m in maps])[pos]
        np.testing.assert_array_equal(places, np.concatenate([s.places for s in subs]))
        assert np.all((places >= rng[0]) & (places < rng[1]))
        seen.append(pos)
    np.testing.assert_array_equal(np.sort(np.concatenate(seen)), np.arange(sum(len(m) for m in maps)))


@pytest.mark.parametrize(("name", "extra"), [(name, {}) for name in available_methods()]
                         + [("landmarks", {"tours": "first"})])
def test_three_shards_equal_the_one_piece_map(name: str, extra: dict[str, Any], tiny_route: dict[str, Any]) -> None:
    cls = get_method(name)
    res = _res(tiny_route)
    params = {**FAST.get(name, {}), **extra}
    # Two tours, the second visiting the places out of order: positions, not place order, rebuild the map.
    maps = [tiny_route["map"], _shuffled(tiny_route["training"], 0)]
    whole = cls(**params).fit(maps, resources=res)
    merged = build_from_shards(cls, maps, params=params, resources=res, n_shards=3,
                               executor=LocalExecutor(n_jobs=1))
    assert_same_state(merged, whole)
    np.testing.assert_array_equal(merged.place_ids_, whole.place_ids_)
    np.testing.assert_array_equal(merged.similarity(tiny_route["query"]), whole.similarity(tiny_route["query"]))


@pytest.mark.parametrize("name", available_methods())
def test_shards_moved_to_scratch_files_as_they_arrive_build_the_same_map(name: str, tiny_route: dict[str, Any],
                                                                        tmp_path: Any) -> None:
    # Within spill_to (map build, map add) each shard's arrays go to scratch files as the shard arrives,
    # so that the merging process holds one shard in memory; every method merges them the same.
    cls = get_method(name)
    if not cls.tags.builds_shards:
        pytest.skip(f"{name} is built in one piece")
    maps = [tiny_route["map"], tiny_route["training"]]
    params = FAST.get(name, {})
    want = build_from_shards(cls, maps, params=params, resources=_res(tiny_route), n_shards=3,
                             executor=LocalExecutor(n_jobs=1))
    arrived: list[ShardPart] = []
    spilled = shard_build._spilled

    def spy(part: ShardPart) -> ShardPart:
        arrived.append(spilled(part))
        return arrived[-1]

    with spill_to(tmp_path, min_bytes=1 << 30):  # "always": even arrays far below the threshold
        shard_build._spilled = spy
        try:
            got = build_from_shards(cls, maps, params=params, resources=_res(tiny_route), n_shards=3,
                                    executor=LocalExecutor(n_jobs=1))
        finally:
            shard_build._spilled = spilled
    assert len(arrived) == 3
    assert all(file_backed(a) for p in arrived for a in p.arrays.values() if a.size)
    assert list(tmp_path.iterdir()) == []
    assert_same_state(got, want)
    np.testing.assert_array_equal(got.similarity(tiny_route["query"]), want.similarity(tiny_route["query"]))


def test_parts_that_do_not_cover_the_map_are_refused(tiny_route: dict[str, Any]) -> None:
    cls = get_method("bow")
    res = _res(tiny_route)
    maps = [tiny_route["map"]]
    ranges = split_places(tiny_route["map"].place_ids, 3)
    parts = [cls().fit_shard(maps, places=r, index=k, resources=res) for k, r in enumerate(ranges)]
    with pytest.raises(TopolocError, match=r"not 0\.\.1"):
        cls.from_shards(parts[1:], maps, resources=res)
    with pytest.raises(TopolocError, match="not each of the map's"):
        cls.from_shards(parts[:2], maps, resources=res)
    overlapping = ShardPart(index=1, places=(ranges[0][0], ranges[1][1]), positions=parts[1].positions,
                            meta=parts[1].meta, arrays=parts[1].arrays)
    with pytest.raises(TopolocError, match="overlaps"):
        cls.from_shards([parts[0], overlapping, parts[2]], maps, resources=res)


@pytest.fixture(scope="module")
def _pickle_tests_by_value() -> None:
    cloudpickle = pytest.importorskip("cloudpickle")
    cloudpickle.register_pickle_by_value(sys.modules[__name__])


@pytest.mark.parametrize("name", ["coocmap", "landmarks", "bow"])
def test_shards_built_on_a_dask_cluster_equal_the_local_build(name: str, tiny_route: dict[str, Any],
                                                             dask_scheduler: str,
                                                             _pickle_tests_by_value: None) -> None:
    from topoloc.cluster import connect

    cls = get_method(name)
    res = _res(tiny_route)
    maps = [tiny_route["map"], tiny_route["training"]]
    local = build_from_shards(cls, maps, params=FAST.get(name, {}), resources=res, n_shards=3,
                              executor=LocalExecutor(n_jobs=1))
    with connect(dask_scheduler, timeout_s=20) as ex:
        remote = build_from_shards(cls, maps, params=FAST.get(name, {}), resources=_res(tiny_route), n_shards=3,
                                   executor=ex)
    assert_same_state(remote, local)
    np.testing.assert_array_equal(remote.similarity(tiny_route["query"]), local.similarity(tiny_route["query"]))


def test_a_coocmap_model_file_cannot_be_combined_with_shards(tiny_route: dict[str, Any], tmp_path: Any) -> None:
    # model_path is gone altogether (a fitted method is kept in its map file): refused before any work.
    cls = get_method("coocmap")
    with pytest.raises(TopolocError, match="no parameter 'model_path' any more"):
        build_from_shards(cls, [tiny_route["map"]], params={"model_path": str(tmp_path / "m.tlc")},
                          resources=_res(tiny_route), n_shards=2, executor=LocalExecutor(n_jobs=1))


def test_landmark_shards_built_with_other_tours_are_refused(tiny_route: dict[str, Any]) -> None:
    cls = get_method("landmarks")
    res = _res(tiny_route)
    maps = [tiny_route["map"], tiny_route["training"]]
    ranges = split_places(np.unique(np.concatenate([m.places for m in maps])), 2)
    # Shards of the paper's map match only the first tour's pairs; a map of separate tours needs all.
    parts = [cls(tours="first").fit_shard(maps, places=r, index=k, resources=res) for k, r in enumerate(ranges)]
    with pytest.raises(TopolocError, match=r"no shard matched map images \d+ and \d+"):
        cls.from_shards(parts, maps, params={"tours": "separate"}, resources=res)


def test_shard_tasks_keep_no_memo_in_the_resources_they_share(tiny_route: dict[str, Any]) -> None:
    # A Dask worker runs every shard it gets with one deserialised copy of the task's arguments:
    # what one shard memoises must go with it, or a worker's memory grows with the route.
    from topoloc.methods.shard_build import _shard_task

    res = _res(tiny_route)
    maps = [tiny_route["map"]]
    ranges = split_places(np.unique(maps[0].places), 3)
    for k in range(3):
        part = _shard_task(k, cls=get_method("coocmap"), params=FAST["coocmap"], maps=maps, resources=res,
                           ranges=ranges)
        assert part.index == k
    assert not res._memo and not res.image_ms
