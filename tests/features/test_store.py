"""The feature store: blocks written atomically, bit-identical features, resumable, checked on load."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.cluster import LocalExecutor, connect
from topoloc.errors import TopolocError
from topoloc.features import FeatureConfig, FeatureExtractor
from topoloc.features import store as store_mod
from topoloc.features.store import FeatureStore, fill_block, read_block, store_usage


def _store(route: dict[str, Any], cache: Path, method: str = "sift", block_size: int = 3) -> FeatureStore:
    trav = route["map"]
    return FeatureStore(FeatureConfig(method=method), trav.images, root=trav.root, cache_dir=cache,
                        block_size=block_size)


def _expected(route: dict[str, Any], method: str = "sift") -> list[Any]:
    ex = FeatureExtractor(FeatureConfig(method=method), use_cache=False)
    return [ex.extract_path(p) for p in route["map"].images]


def _assert_same(got: list[Any], want: list[Any]) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert g.descriptors.dtype == w.descriptors.dtype
        # Bit for bit: the raw bytes, not a tolerance.
        assert g.keypoints.tobytes() == w.keypoints.tobytes()
        assert g.descriptors.tobytes() == w.descriptors.tobytes()
        assert g.image_shape == w.image_shape


class _Counter:
    """Wraps the store's per-image extraction to count calls (threads of this process)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, fail_on: str | None = None) -> None:
        self.calls: list[str] = []
        self.lock = threading.Lock()
        real = store_mod._extract_one

        def counted(path: str, config: FeatureConfig) -> Any:
            if fail_on is not None and Path(path).name == fail_on:
                raise RuntimeError("worker killed")
            with self.lock:
                self.calls.append(Path(path).name)
            return real(path, config)

        monkeypatch.setattr(store_mod, "_extract_one", counted)


@pytest.mark.parametrize("method", ["sift", "rootsift"])
def test_round_trip_is_bit_identical(method: str, tiny_route: dict[str, Any], tmp_path: Path) -> None:
    st = _store(tiny_route, tmp_path, method)
    want = _expected(tiny_route, method)
    with LocalExecutor(n_jobs=2) as ex:
        fresh = st.read(st.fill(ex, keep=True))  # as extracted, kept in memory
        again = st.read(st.fill(ex))  # read back from the block files
    _assert_same(fresh, want)
    _assert_same(again, want)
    assert st.n_blocks == 4 and all(st.block_path(b).is_file() for b in range(4))
    from topoloc.io import read_container

    _, arrays = read_container(st.block_path(0), "feature-block", 1)
    # OpenCV SIFT descriptors are integers 0..255: stored as uint8. RootSIFT is not: float32.
    assert arrays["descriptors"].dtype == (np.uint8 if method == "sift" else np.float32)
    assert (tmp_path / "features").is_dir() and not list(tmp_path.rglob("*.tmp"))


def test_compact_keeps_what_would_not_round_trip() -> None:
    ints = np.array([[0, 1, 255]], np.float32)
    assert store_mod._compact(ints).dtype == np.uint8
    for bad in ([[0.5, 1, 2]], [[-1.0, 1, 2]], [[256.0, 1, 2]], [[np.nan, 1, 2]], [[-0.0, 1, 2]]):
        arr = np.array(bad, np.float32)
        assert store_mod._compact(arr) is arr


def test_a_killed_block_is_recomputed_and_only_it(tiny_route: dict[str, Any], tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    st = _store(tiny_route, tmp_path)
    victim = st.images[4].name  # in block 1
    with monkeypatch.context() as m:
        _Counter(m, fail_on=victim)
        with pytest.raises(RuntimeError, match="worker killed"), LocalExecutor(n_jobs=2) as ex:
            st.fill(ex)
    assert [st.block_path(b).is_file() for b in range(4)] == [True, False, True, True]
    assert not list(st.path.rglob("*.tmp"))
    counter = _Counter(monkeypatch)
    with LocalExecutor(n_jobs=2) as ex:
        got = st.read(st.fill(ex))
    assert sorted(counter.calls) == sorted(st.images[k].name for k in st.block_range(1))
    _assert_same(got, _expected(tiny_route))


@pytest.mark.parametrize("damage", ["flip", "truncate", "other-settings"])
def test_a_corrupt_block_is_detected_and_recomputed(damage: str, tiny_route: dict[str, Any], tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    st = _store(tiny_route, tmp_path)
    with LocalExecutor(n_jobs=2) as ex:
        st.fill(ex)
    path = st.block_path(2)
    data = bytearray(path.read_bytes())
    if damage == "flip":
        data[-100] ^= 0xFF
        path.write_bytes(bytes(data))
    elif damage == "truncate":
        path.write_bytes(bytes(data[: len(data) // 2]))
    else:
        other = _store(tiny_route, tmp_path / "other", "rootsift")
        with LocalExecutor(n_jobs=1) as ex:
            other.fill(ex)
        path.write_bytes(other.block_path(2).read_bytes())
    with pytest.raises(TopolocError, match=r"feature.block.*000002\.tlb") as err:
        read_block(path, st.config)
    assert "\n" not in str(err.value)
    counter = _Counter(monkeypatch)
    with LocalExecutor(n_jobs=2) as ex:
        got = st.read(st.fill(ex))
    assert sorted(counter.calls) == sorted(st.images[k].name for k in st.block_range(2))
    _assert_same(got, _expected(tiny_route))


def test_an_edited_image_invalidates_its_block(tiny_route: dict[str, Any], tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    import shutil

    src = tiny_route["map"]
    folder = tmp_path / "tour"
    shutil.copytree(src.root, folder)
    images = [folder / p.name for p in src.images]
    st = FeatureStore(FeatureConfig(), images, root=folder, cache_dir=tmp_path / "cache", block_size=4)
    with LocalExecutor(n_jobs=2) as ex:
        st.fill(ex)
    shutil.copyfile(src.images[0], images[5])  # image 5 (block 1) now shows another place
    counter = _Counter(monkeypatch)
    with LocalExecutor(n_jobs=2) as ex:
        got = st.read(st.fill(ex))
    assert sorted(counter.calls) == sorted(images[k].name for k in st.block_range(1))
    ex1 = FeatureExtractor(use_cache=False)
    _assert_same(got, [ex1.extract_path(p) for p in images])


def test_read_checks_the_images_sha1(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    st = _store(tiny_route, tmp_path)
    res = fill_block(st.task(0))
    assert len(read_block(st.block_path(0), st.config, res.sha1)) == 3
    with pytest.raises(TopolocError, match="does not describe the current images"):
        read_block(st.block_path(0), st.config, list(reversed(res.sha1)))


def test_an_interrupt_leaves_the_store_consistent(tiny_route: dict[str, Any], tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    st = _store(tiny_route, tmp_path, block_size=2)  # 6 blocks
    seen: list[int] = []

    def advance(n: int) -> None:
        seen.append(n)
        if len(seen) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt), LocalExecutor(n_jobs=1) as ex:
        st.fill(ex, advance=advance)
    complete = [b for b in range(st.n_blocks) if st.block_path(b).is_file()]
    assert 2 <= len(complete) < st.n_blocks
    assert not list(st.path.rglob("*.tmp"))
    for b in complete:  # every block present is whole
        assert len(read_block(st.block_path(b), st.config)) == len(st.block_range(b))
    counter = _Counter(monkeypatch)
    with LocalExecutor(n_jobs=2) as ex:
        got = st.read(st.fill(ex))
    missing = [b for b in range(st.n_blocks) if b not in complete]
    assert sorted(counter.calls) == sorted(st.images[k].name for b in missing for k in st.block_range(b))
    _assert_same(got, _expected(tiny_route))


def test_concurrent_writers_do_not_corrupt_the_store(tiny_route: dict[str, Any], tmp_path: Path,
                                                     dask_scheduler: str) -> None:
    st = _store(tiny_route, tmp_path, block_size=1)  # 12 blocks over 2 worker processes
    want = _expected(tiny_route)
    with connect(dask_scheduler, timeout_s=20) as ex:
        results = st.fill(ex)
    assert all(r.features is None and r.extracted == 1 for r in results)  # on the cluster, written not shipped
    _assert_same(st.read(results), want)
    # Two runs filling the same store at once (same blocks) from two threads: last rename wins, both whole.
    for b in range(st.n_blocks):
        st.block_path(b).unlink()
    out: list[Any] = [None, None]

    def run(i: int) -> None:
        with LocalExecutor(n_jobs=2) as local:
            out[i] = st.read(st.fill(local))

    threads = [threading.Thread(target=run, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    _assert_same(out[0], want)
    _assert_same(out[1], want)
    _assert_same(st.read(st.fill(LocalExecutor(n_jobs=1))), want)


def test_xfeat_features_extracted_on_dask_workers_equal_local_ones(xfeat_route: dict[str, Any], tmp_path: Path,
                                                                   dask_scheduler: str) -> None:
    # (xfeat_route skips without the 'learned' extra.)  One thread per image: the workers' bytes are this process's.
    from topoloc.resources import CachedResources

    st = _store(xfeat_route, tmp_path, "xfeat")
    want = _expected(xfeat_route, "xfeat")
    voc = xfeat_route["vocabulary"]
    with connect(dask_scheduler, timeout_s=20) as ex:
        results = st.fill(ex)
        # Quantised on the workers too (they load the XFeat vocabulary from the cache folder).
        res = CachedResources(extractor=FeatureExtractor(st.config, cache_dir=tmp_path), vocabulary=voc, executor=ex)
        words = res.words(xfeat_route["map"])
    assert all(r.features is None and r.extracted == len(st.block_range(r.block)) for r in results)
    got = st.read(results)
    _assert_same(got, want)
    assert got[0].descriptors.dtype == np.float32 and got[0].descriptors.shape[1] == 64  # not compacted to uint8
    for w, fs in zip(words, want, strict=True):
        np.testing.assert_array_equal(w, voc.quantize(fs.descriptors))


def test_store_usage_lists_each_store(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    st = _store(tiny_route, tmp_path)
    with LocalExecutor(n_jobs=2) as ex:
        st.fill(ex)
    (usage,) = store_usage(tmp_path)
    assert usage["images"] == len(st.images) == 12 and usage["blocks"] == 4 and usage["complete_blocks"] == 4
    assert usage["settings"] == st.config.key() and usage["bytes"] > 0 and Path(usage["path"]) == st.path


def test_cleaning_removes_whole_stores_least_recently_used(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    import os

    from topoloc.features.cache import cache_usage, clean_cache

    old, new = _store(tiny_route, tmp_path, "sift"), _store(tiny_route, tmp_path, "rootsift")
    with LocalExecutor(n_jobs=2) as ex:
        old.fill(ex)
        new.fill(ex)
    for f in old.path.rglob("*"):
        os.utime(f, (1_000_000, 1_000_000))  # used long ago
    sizes = {u["settings"]: u["bytes"] for u in store_usage(tmp_path)}
    assert cache_usage(tmp_path)["total"]["bytes"] == sum(sizes.values())
    res = clean_cache(tmp_path, max_bytes=sizes[new.config.key()] + 10)
    assert res["removed_stores"] == 1 and res["removed_bytes"] == sizes[old.config.key()]
    assert not old.path.exists() and not list(old.path.parent.iterdir())  # gone whole, nothing left beside it
    assert [u["settings"] for u in store_usage(tmp_path)] == [new.config.key()]
    with LocalExecutor(n_jobs=2) as ex:  # the kept store is whole: nothing to extract
        assert all(r.extracted == 0 for r in new.fill(ex))
    assert clean_cache(tmp_path)["kept_bytes"] == 0 and store_usage(tmp_path) == []


def test_workers_that_do_not_see_the_cache_folder_are_one_line(tmp_path: Path) -> None:
    from topoloc.features.store import check_shared_cache

    class ElsewhereExecutor(LocalExecutor):
        """Workers on another machine: the token file this process wrote is not there for them."""

        def map(self, fn: Any, items: Any, *, advance: Any = None) -> list[Any]:
            return [fn(str(Path(item).with_name("elsewhere"))) for item in items]

    check_shared_cache(LocalExecutor(n_jobs=2), tmp_path)  # same machine: seen
    with pytest.raises(TopolocError, match=r"do not see the cache folder.*TOPOLOC_CACHE_DIR\): .*") as err:
        check_shared_cache(ElsewhereExecutor(n_jobs=2), tmp_path)
    assert str(tmp_path.resolve()) in str(err.value) and "\n" not in str(err.value)
    assert not list(tmp_path.glob(".shared-check-*"))  # the token is removed either way


def _die_once_mid_write(task: Any) -> Any:
    """Block 1's first attempt leaves half a temporary block file and kills its worker process."""
    import os

    from topoloc.features.store import fill_block

    marker = Path(task.path).parent.parent / "died"
    if task.block == 1 and not marker.exists():
        # The store's folder may not exist yet when block 1 runs first (no block written): without it
        # the marker could not be written, the task failed and was retried, and the run could outlast
        # the test's timeout.
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.write_text("died")
        Path(task.path).parent.mkdir(parents=True, exist_ok=True)
        Path(task.path).with_name(f".{Path(task.path).name}.killed.tmp").write_bytes(b"TOPOLOC\x00half")
        os._exit(1)
    return fill_block(task)


def test_a_worker_killed_mid_block_is_rescheduled_and_the_store_is_whole(
        tiny_route: dict[str, Any], tmp_path: Path, dask_scheduler: str) -> None:
    import sys

    cloudpickle = pytest.importorskip("cloudpickle")
    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # workers cannot import this test module
    st = _store(tiny_route, tmp_path, block_size=3)
    with connect(dask_scheduler, timeout_s=20) as ex:
        results = ex.map(_die_once_mid_write, [st.task(b) for b in range(st.n_blocks)])
        assert (st.path / "died").exists()  # a worker process really died
        ex.client.wait_for_workers(2, timeout=60)  # the nanny restarts it; later tests see 2 workers
    _assert_same(st.read(results), _expected(tiny_route))
    assert all(st.block_path(b).is_file() for b in range(st.n_blocks))


def test_an_interrupted_run_of_the_resources_resumes(tiny_route: dict[str, Any], tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    from topoloc.resources import CachedResources

    trav = tiny_route["map"]
    calls: list[int] = []

    def progress(description: str, total: int) -> Any:
        def advance(n: int) -> None:
            calls.append(n)
            if len(calls) == 2:
                raise KeyboardInterrupt  # the user presses Ctrl-C after the second block

        return advance

    res = CachedResources(extractor=FeatureExtractor(cache_dir=tmp_path), progress=progress, block_size=3)
    with pytest.raises(KeyboardInterrupt):
        res.features(trav)
    st = FeatureStore(FeatureConfig(), trav.images, root=trav.root, cache_dir=tmp_path, block_size=3)
    assert [st.block_path(b).is_file() for b in range(st.n_blocks)] == [True, True, False, False]
    assert not list(st.path.rglob("*.tmp"))
    counter = _Counter(monkeypatch)
    again = CachedResources(extractor=FeatureExtractor(cache_dir=tmp_path), block_size=3).features(trav)
    assert sorted(counter.calls) == sorted(p.name for p in trav.images[6:])
    _assert_same(again, _expected(tiny_route))


def test_images_in_the_per_image_cache_are_not_extracted_again(tiny_route: dict[str, Any], tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    single = FeatureExtractor(cache_dir=tmp_path)
    for p in tiny_route["map"].images[:4]:  # described alone earlier (vocabulary training, an older topoloc)
        single.extract_path(p)
    st = _store(tiny_route, tmp_path)
    counter = _Counter(monkeypatch)
    with LocalExecutor(n_jobs=2) as ex:
        results = st.fill(ex)
    assert sorted(counter.calls) == sorted(p.name for p in st.images[4:])
    assert [r.extracted for r in results] == [0, 2, 3, 3]
    _assert_same(st.read(results), _expected(tiny_route))
