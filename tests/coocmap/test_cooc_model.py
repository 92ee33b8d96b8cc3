"""Location models M_i, tours, interpolation and their state (Cooc-Map Sec. II-B, II-E)."""

from __future__ import annotations

import copy
import json
import tracemalloc
from typing import Any

import numpy as np
import pytest

from topoloc.coocmap.inverted import inverted_files
from topoloc.coocmap.model import (
    INDEX_ARRAYS,
    CoocModel,
    Observation,
    _mask_dtype,
    merge_models,
    merge_sorted_features,
    sort_unique_features,
)
from topoloc.coocmap.spatial import spatial_words
from topoloc.errors import TopolocError
from topoloc.io.scratch import file_backed, spill_to
from topoloc.io.state import new_object, object_state, restore_state

G: dict[str, Any] = {"grid_x": 3, "grid_y": 2}  # 24 spatial words keep hand examples small


def _pairs(words: np.ndarray, xy: np.ndarray, n_words: int, n_spatial: int) -> set[int]:
    """Brute-force pairs(G) of the module docstring, as packed keys."""
    out = set()
    for i in range(len(words)):
        for j in range(len(words)):
            if i != j:
                s = int(spatial_words(xy[i], xy[j], **G))
                out.add((int(words[i]) * n_words + int(words[j])) * n_spatial + s)
    return out


def _union(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    w = np.r_[a[0], b[0]]
    xy = np.r_[a[1], b[1]]
    _, idx = np.unique(np.c_[w, xy], axis=0, return_index=True)  # a shared feature is one feature
    return w[idx], xy[idx]


def test_fig4_hand_example() -> None:
    # Fig. 4: words A..D (0..3); A appears left of B and also bottom-right of B.
    q = 65536 // 6
    A1, A2, B, C = (q, 3 * q), (5 * q, 5 * q), (3 * q, 3 * q), (3 * q, q)
    words = np.array([0, 0, 1, 2])
    xy = np.array([A1, A2, B, C], np.uint16)
    m = CoocModel.build([[(0, words, xy)]], n_locations=1, n_words=4, **G)
    assert m.location_words(0).tolist() == [0, 1, 2]  # D is not seen: no row for it
    keys = set(m.pair_keys(0).tolist())
    assert keys == _pairs(words, xy, 4, m.n_spatial)
    # Element (B, A) holds two spatial words: A to the left, and A to the bottom-right.
    ba = sorted(k % m.n_spatial for k in keys if k // m.n_spatial == 1 * 4 + 0)
    left = int(spatial_words(np.array(B, np.uint16), np.array(A1, np.uint16), **G))
    below_right = int(spatial_words(np.array(B, np.uint16), np.array(A2, np.uint16), **G))
    assert ba == sorted({left, below_right}) and left != below_right
    assert left // 6 in (0, 2) and below_right // 6 == 3  # quadrant: left; right-below


def _random_tours(rng: np.random.Generator, n_tours: int, n_loc: int, n_words: int, n: int) -> list:
    tours = []
    shared = [(rng.integers(0, n_words, 4), rng.integers(0, 65536, (4, 2)).astype(np.uint16))
              for _ in range(n_loc)]
    for _ in range(n_tours):
        obs = []
        for loc in range(n_loc):
            w = np.r_[shared[loc][0], rng.integers(0, n_words, n)]
            xy = np.r_[shared[loc][1], rng.integers(0, 65536, (n, 2)).astype(np.uint16)]
            obs.append((loc, w, xy))
        tours.append(obs)
    return tours


def test_tours_and_interpolation_change_m_exactly() -> None:
    rng = np.random.default_rng(3)
    nw = 6
    tours = _random_tours(rng, 3, 2, nw, 5)
    plain = CoocModel.build(tours, n_locations=2, n_words=nw, interpolate=False, **G)
    interp = CoocModel.build(tours, n_locations=2, n_words=nw, interpolate=True, **G)
    ns = plain.n_spatial
    for loc in range(2):
        img = [(t[loc][1], t[loc][2]) for t in tours]
        single = set().union(*(_pairs(w, xy, nw, ns) for w, xy in img))
        assert set(plain.pair_keys(loc).tolist()) == single
        virtual = set().union(*(_pairs(*_union(img[k], img[k + 1]), nw, ns) for k in range(2)))
        assert set(interp.pair_keys(loc).tolist()) == virtual
        assert single < virtual  # adds the cross-tour pairs of adjacent tours...
        far = _pairs(*_union(img[0], img[2]), nw, ns) - virtual
        assert far  # ...but not those of tours 0 and 2, which are not adjacent
        # The flag can also be chosen at match time from the same stored model.
        assert set(plain.pair_keys(loc, interpolate=True).tolist()) == virtual
    # Shared features are stored once, with both tours in their mask.
    assert plain.n_features < sum(len(o[1]) for t in tours for o in t)
    assert plain.tours.dtype == np.uint8 and plain.tours.max() == 0b111


def test_add_tour_in_time_order_equals_build() -> None:
    rng = np.random.default_rng(4)
    tours = _random_tours(rng, 3, 3, 8, 6)
    ref = CoocModel.build(tours, n_locations=3, n_words=8, **G)
    m = CoocModel.build([tours[0], tours[2]], n_locations=3, n_words=8, tour_names=["a", "c"], **G)
    m.add_tour(tours[1], name="b", position=1)  # a later survey of the middle time of day
    assert m.tour_names == ["a", "b", "c"]
    for loc in range(3):
        np.testing.assert_array_equal(m.pair_keys(loc), ref.pair_keys(loc))
    np.testing.assert_array_equal(m.tours, ref.tours)
    # Inverted file word -> locations.
    for w in range(8):
        locs = m.wloc[m.wloc_ptr[w]:m.wloc_ptr[w + 1]].tolist()
        assert locs == [loc for loc in range(3) if w in m.location_words(loc)]
    assert m.nbytes > 0 and m.bytes_per_location == m.nbytes / 3


def test_bad_input() -> None:
    with pytest.raises(TopolocError, match="word ids"):
        CoocModel.build([[(0, np.array([9]), np.zeros((1, 2), np.uint16))]], n_locations=1, n_words=4)
    with pytest.raises(TopolocError, match="location"):
        CoocModel.build([[(2, np.array([1]), np.zeros((1, 2), np.uint16))]], n_locations=1, n_words=4)


def test_state_round_trip() -> None:
    # The model has no file of its own: map files keep it as JSON + arrays (topoloc.io.state),
    # the way CoocMap's state does; vocabulary and damage checks are the map file's (tests/maps).
    rng = np.random.default_rng(5)
    m = CoocModel.build(_random_tours(rng, 2, 3, 8, 6), n_locations=3, n_words=8,
                        tour_names=["t1", "t2"], tour_hours=[8.0, 20.0], **G)
    voc = {"n_words": 8, "descriptor_kind": "sift-128-float32", "sha1": "abc"}
    m.vocabulary = voc
    meta, arrays = object_state(m, prefix="model/", skip=[k for k in vars(m) if k.startswith("_")])
    meta = json.loads(json.dumps(meta))
    back = restore_state(new_object(CoocModel), meta, arrays, prefix="model/")
    back._groups = {}
    assert back.tour_names == ["t1", "t2"] and back.tour_hours == [8.0, 20.0] and back.vocabulary == voc
    for loc in range(3):
        np.testing.assert_array_equal(back.pair_keys(loc), m.pair_keys(loc))
    np.testing.assert_array_equal(back.wloc, m.wloc)
    # The inverted files are read from the file, not rebuilt: those of a file written before the
    # counting sort (argsort and bincount) are the ones it builds.
    _assert_index_is_the_reference(back)
    assert not hasattr(CoocModel, "save") and not hasattr(CoocModel, "load")


def test_position_lattice_merges_reobserved_features() -> None:
    # The same word seen 300 normalised units (~3 px at 640 px) apart by two tours.
    base = np.array([[10340, 20580], [40060, 29800]], np.uint16)
    t1 = [(0, np.array([1, 2]), base)]
    t2 = [(0, np.array([1, 2]), base + np.uint16(300))]
    exact = CoocModel.build([t1, t2], n_locations=1, n_words=4, **G)
    coarse = CoocModel.build([t1, t2], n_locations=1, n_words=4, position_bits=6, **G)
    assert exact.n_features == 4 and coarse.n_features == 2
    assert coarse.tours.tolist() == [0b11, 0b11]
    # Lattice of 1024 units, positions at bin centres; queries are quantised alike.
    assert coarse.xy.tolist() == [[10240 + 512, 20480 + 512], [39936 + 512, 29696 + 512]]
    np.testing.assert_array_equal(coarse.quantise_xy(base + np.uint16(300)), coarse.xy)
    with pytest.raises(TopolocError, match="position_bits"):
        CoocModel(n_locations=1, n_words=4, position_bits=0)

# -- memory: the feature table is merged, extended and indexed without int64 copies of it ------
# At 100,000 places the table has tens of millions of rows (benchmarks/bench_cluster.py); the client
# of `map build --shards` merges it and `map add` extends it, so their peak stays a small multiple of
# the model's own bytes.  tracemalloc sees NumPy's allocations.


def _model(rng: np.random.Generator, n_locations: int, per_location: int = 60) -> CoocModel:
    m = CoocModel(n_locations=n_locations, n_words=2000)
    m.tour_names, m.tour_hours = ["a"], [None]
    loc = np.repeat(np.arange(n_locations), per_location)
    m._set_features(loc, rng.integers(0, 2000, len(loc)), rng.integers(0, 65535, (len(loc), 2)).astype(np.uint16),
                    np.ones(len(loc), np.uint64))
    return m


def _peak(fn) -> int:  # type: ignore[no-untyped-def]
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_merge_peak_is_a_small_multiple_of_the_model() -> None:
    rng = np.random.default_rng(0)
    parts = [_model(rng, 400) for _ in range(4)]
    out: list[CoocModel] = []
    peak = _peak(lambda: out.append(merge_models(parts)))
    # The merged arrays and their inverted files and nothing else: the counting sort of _index fills
    # them directly (1.0x; 1.75x with argsort and bincount, 5.8x with int64 copies of the table).
    assert peak < 1.2 * out[0].nbytes


def test_add_tour_peak_is_a_small_multiple_of_the_model() -> None:
    rng = np.random.default_rng(1)
    m = _model(rng, 1500)
    obs = [(i, rng.integers(0, 2000, 60), rng.integers(0, 65535, (60, 2)).astype(np.uint16)) for i in range(1500)]
    peak = _peak(lambda: m.add_tour(obs, name="b"))
    # The merged table and its inverted files: the tour is merged into the sorted table a block of
    # locations at a time (1.15x; 1.75x when the keys of the whole table and tour were made at once,
    # 2.7x when the whole table was sorted again, 7.5x with int64 copies and a four-key lexsort).
    assert peak < 1.35 * m.nbytes


def test_add_tour_to_a_map_of_several_tours_peaks_at_the_model() -> None:
    # `map add` to a map of many tours: the tour is a fraction of the table, and with argsort and
    # bincount the peak was _index's int64 copies of the table (1.74x); the counting sort fills the
    # inverted files directly and the peak is the new model itself (1.01x).
    rng = np.random.default_rng(3)
    m = _model(rng, 1500)
    for t in range(5):
        m.add_tour([(i, rng.integers(0, 2000, 30), rng.integers(0, 65535, (30, 2)).astype(np.uint16))
                    for i in range(1500)], name=f"t{t}")
    obs = [(i, rng.integers(0, 2000, 30), rng.integers(0, 65535, (30, 2)).astype(np.uint16)) for i in range(1500)]
    peak = _peak(lambda: m.add_tour(obs, name="b"))
    assert peak < 1.2 * m.nbytes


def test_index_allocates_only_the_inverted_files() -> None:
    # No temporary of the table's length besides the outputs: argsort's int64 order, its int32 copy,
    # the gathered locations and words and bincount's int64 copies made the peak 1.23x the model and
    # 2.57x these arrays; now it is them plus the kernel's two per-word cursors (2 x 16 KB).
    m = _model(np.random.default_rng(4), 3000)
    peak = _peak(m._index)
    index_bytes = sum(getattr(m, k).nbytes for k in INDEX_ARRAYS)
    assert peak < index_bytes + (64 << 10)


@pytest.mark.parametrize("n_words", [2000, 2**31])  # one packed uint64 key; too wide to pack: lexsort
def test_sort_unique_features_orders_and_merges_like_lexsort(n_words: int) -> None:
    rng = np.random.default_rng(2)
    n = 5000
    loc = rng.integers(0, 50, n)
    word = rng.integers(0, 30, n)
    xy = (rng.integers(0, 3, (n, 2)) * 20000).astype(np.uint16)  # few positions: many duplicates
    mask = (np.uint64(1) << rng.integers(0, 5, n).astype(np.uint64)).astype(np.uint64)
    got_loc, got_word, got_xy, got_mask = sort_unique_features(loc, word, xy, mask, n_locations=50, n_words=n_words)
    rows = {}
    for i in range(n):
        k = (int(loc[i]), int(word[i]), int(xy[i, 1]), int(xy[i, 0]))
        rows[k] = rows.get(k, 0) | int(mask[i])
    want = sorted(rows)
    assert len(got_loc) == len(want) < n
    assert [(int(a), int(b), int(c[1]), int(c[0])) for a, b, c in zip(got_loc, got_word, got_xy, strict=True)] == want
    assert [int(v) for v in got_mask] == [rows[k] for k in want]


# -- add_tour merges the tour into the sorted table: the same model as sorting everything again ----


def _add_tour_by_sorting(m: CoocModel, observations: list, name: str, position: int) -> CoocModel:
    """The slow reference: add_tour as it was, the whole table and the tour concatenated and sorted again."""
    m = copy.deepcopy(m)
    n_old = m.n_tours
    mask_dt = _mask_dtype(n_old + 1)
    old = m.tours.astype(mask_dt)
    low = mask_dt.type((1 << position) - 1)
    old = (old & low) | ((old & ~low) << mask_dt.type(1))
    m.tour_names.insert(position, name)
    m.tour_hours.insert(position, None)
    locs = [np.full(len(w), loc, m.loc.dtype) for loc, w, _ in observations]
    words = [np.asarray(w).astype(m.word.dtype) for _, w, _ in observations]
    xys = [m.quantise_xy(xy) for _, _, xy in observations]
    n_new = sum(len(w) for w in words)
    m._set_features(np.concatenate([m.loc, *locs]), np.concatenate([m.word, *words]),
                    np.concatenate([m.xy, *xys]), np.concatenate([old, np.full(n_new, mask_dt.type(1 << position))]))
    return m


def _assert_same_model(got: CoocModel, want: CoocModel) -> None:
    assert got.tour_names == want.tour_names and got.tour_hours == want.tour_hours
    for key, a in want._arrays().items():
        b = got._arrays()[key]
        assert b.dtype == a.dtype and b.shape == a.shape, key
        np.testing.assert_array_equal(b, a, err_msg=key)


def _tour_with_repeats(rng: np.random.Generator, m: CoocModel, n_loc: int, n_words: int) -> list[Observation]:
    """Images with features of the map (features already present), features repeated within the tour,
    several images of one location, images without features, and new features."""
    obs: list[Observation] = []
    for _ in range(int(rng.integers(0, 2 * n_loc + 1))):
        loc = int(rng.integers(0, n_loc))
        s, e = int(m.loc_ptr[loc]), int(m.loc_ptr[loc + 1])
        seen = rng.integers(s, e, int(rng.integers(0, 4))) if e > s else np.zeros(0, np.int64)
        n = int(rng.integers(0, 5))
        w = np.r_[m.word[seen].astype(np.int64), rng.integers(0, n_words, n)]
        xy = np.r_[m.xy[seen], (rng.integers(0, 4, (n, 2)) * 16384).astype(np.uint16)]  # few positions
        if len(w) and rng.random() < 0.5:
            w, xy = np.r_[w, w[:2]], np.r_[xy, xy[:2]]
        obs.append((loc, w, xy))
    return obs


# Tour counts on both sides of each mask dtype's width (8, 16, 32 bits) and the widest, 64.
@pytest.mark.parametrize("n_old", [0, 1, 3, 7, 8, 15, 16, 31, 32, 63])
@pytest.mark.parametrize("position_bits", [16, 2])
def test_add_tour_merge_equals_sorting_everything(n_old: int, position_bits: int) -> None:
    rng = np.random.default_rng(100 * n_old + position_bits)
    n_loc, n_words = 5, 6
    m = CoocModel(n_locations=n_loc, n_words=n_words, position_bits=position_bits, **G)
    tours: list[list[Observation]] = []
    for t in range(n_old):
        tours.append(_tour_with_repeats(rng, m, n_loc, n_words))
        m.add_tour(tours[-1], name=f"t{t}")
    for position in sorted({0, n_old // 2, n_old}):
        obs = _tour_with_repeats(rng, m, n_loc, n_words)
        want = _add_tour_by_sorting(m, obs, "new", position)
        got = copy.deepcopy(m).add_tour(obs, name="new", position=position)
        _assert_same_model(got, want)
        assert got.tours.dtype == _mask_dtype(n_old + 1)
        # And the model built from all tours in time order.
        in_order = [*tours[:position], obs, *tours[position:]]
        names = [*(f"t{t}" for t in range(position)), "new", *(f"t{t}" for t in range(position, n_old))]
        built = CoocModel.build(in_order, n_locations=n_loc, n_words=n_words, position_bits=position_bits,
                                tour_names=names, **G)
        _assert_same_model(got, built)
    # An empty tour only moves and widens the masks.
    empty = copy.deepcopy(m).add_tour([], name="none", position=0)
    _assert_same_model(empty, _add_tour_by_sorting(m, [], "none", 0))


def test_add_tour_without_a_packed_key_sorts_everything() -> None:
    # 2^17 + 1 locations and 2^16 + 1 words need 18 + 17 + 32 bits: no 64-bit key, the lexsort path.
    rng = np.random.default_rng(8)
    n_loc, n_words = 2**17 + 1, 2**16 + 1
    m = CoocModel(n_locations=n_loc, n_words=n_words)
    hi = [0, 1, n_loc - 1]
    for t in range(3):
        obs = [(loc, rng.integers(n_words - 3, n_words, 4), (rng.integers(0, 2, (4, 2)) * 999).astype(np.uint16))
               for loc in hi]
        want = _add_tour_by_sorting(m, obs, f"t{t}", t // 2)
        m.add_tour(obs, name=f"t{t}", position=t // 2)
        _assert_same_model(m, want)
    assert m.n_features > 0 and m.word.dtype == np.int32


@pytest.mark.parametrize(("n_table", "n_new"), [(0, 0), (0, 50), (300, 0), (300, 100), (40, 300)])
def test_merge_sorted_features_equals_sorting_the_concatenation(n_table: int, n_new: int) -> None:
    rng = np.random.default_rng(n_table + n_new)

    def table(n: int, bit: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        xy = (rng.integers(0, 3, (n, 2)) * 20000).astype(np.uint16)
        mask = np.full(n, 1 << bit, np.uint16)
        return sort_unique_features(rng.integers(0, 7, n), rng.integers(0, 5, n), xy, mask, n_locations=7, n_words=5)

    a, b = table(n_table, 9), table(n_new, 3)  # 7 x 5 x 9 possible features: many in both
    want = sort_unique_features(*(np.concatenate([x, y]) for x, y in zip(a, b, strict=True)), n_locations=7,
                                n_words=5)
    got = merge_sorted_features(a, b, n_locations=7, n_words=5)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype and g.shape == w.shape
        np.testing.assert_array_equal(g, w)


# -- the inverted files: a counting sort gives what argsort and bincount gave, bit for bit ----------


def _index_by_argsort(loc: np.ndarray, word: np.ndarray, n_locations: int, n_words: int) -> dict[str, np.ndarray]:
    """The reference: CoocModel._index as it was, a stable argsort of the words and bincounts."""
    loc_ptr = np.zeros(n_locations + 1, np.int64)
    np.cumsum(np.bincount(loc, minlength=n_locations), out=loc_ptr[1:])
    by_word = np.argsort(word, kind="stable").astype(np.int32)
    word_ptr = np.zeros(n_words + 1, np.int64)
    np.cumsum(np.bincount(word, minlength=n_words), out=word_ptr[1:])
    loc_w, word_w = loc[by_word], word[by_word]
    keep = np.ones(len(loc_w), bool)
    keep[1:] = (loc_w[1:] != loc_w[:-1]) | (word_w[1:] != word_w[:-1])
    wloc_ptr = np.zeros(n_words + 1, np.int64)
    np.cumsum(np.bincount(word_w[keep], minlength=n_words), out=wloc_ptr[1:])
    return {"loc_ptr": loc_ptr, "by_word": by_word, "word_ptr": word_ptr, "wloc": loc_w[keep].astype(np.int32),
            "wloc_ptr": wloc_ptr}


def _assert_index_is_the_reference(m: CoocModel) -> None:
    want = _index_by_argsort(m.loc, m.word, m.n_locations, m.n_words)
    assert set(want) == set(INDEX_ARRAYS)
    for key, a in want.items():
        b = getattr(m, key)
        assert b.dtype == a.dtype and b.shape == a.shape, key
        np.testing.assert_array_equal(b, a, err_msg=key)


# Locations and words on both sides of 2^16 (uint16 or int32 arrays), few of them used (empty
# locations and words), few positions (the same word several times at a location), and no feature.
@pytest.mark.parametrize(("n_loc", "n_words", "n"), [(40, 30, 3000), (40, 30, 0), (70_000, 20, 2000),
                                                     (30, 70_000, 2000), (1, 1, 50), (5, 2000, 1)])
def test_index_equals_argsort_construction(n_loc: int, n_words: int, n: int) -> None:
    rng = np.random.default_rng(n_loc + n_words + n)
    m = CoocModel(n_locations=n_loc, n_words=n_words)
    m.tour_names, m.tour_hours = ["a", "b"], [None, None]
    used_loc = rng.choice(n_loc, max(n_loc // 2, 1), replace=False)
    used_word = rng.choice(n_words, max(n_words // 3, 1), replace=False)
    xy = (rng.integers(0, 3, (n, 2)) * 9000).astype(np.uint16)
    m._set_features(rng.choice(used_loc, n), rng.choice(used_word, n), xy, rng.integers(1, 4, n).astype(np.uint8))
    assert m.loc.dtype == (np.int32 if n_loc > 65536 else np.uint16)
    assert m.word.dtype == (np.int32 if n_words > 65536 else np.uint16)
    _assert_index_is_the_reference(m)
    # add_tour and merge_models index through the same kernel.
    m.add_tour([(int(used_loc[0]), np.repeat(used_word[:1], 3), np.zeros((3, 2), np.uint16))], name="c")
    _assert_index_is_the_reference(m)
    _assert_index_is_the_reference(merge_models([m, m]))


@pytest.mark.parametrize(("n_loc", "per"), [(20_000, 170), (100_000, 40)])
def test_index_equals_argsort_construction_at_map_scale(n_loc: int, per: int) -> None:
    # The shapes of a map of 20,000 places (uint16 locations) and of 100,000 (int32), 2,000 words;
    # the table is sorted by location and word as the model keeps it.
    rng = np.random.default_rng(n_loc)
    m = CoocModel(n_locations=n_loc, n_words=2000)
    m.loc = np.repeat(np.arange(n_loc), per).astype(m.loc.dtype)
    assert m.loc.dtype == (np.uint16 if n_loc <= 65536 else np.int32)
    m.word = np.sort(rng.integers(0, 2000, (n_loc, per)), axis=1).astype(np.uint16).ravel()
    m._index()
    _assert_index_is_the_reference(m)


def test_inverted_files_need_no_order_and_refuse_ids_outside_the_model() -> None:
    # The kernel's definition does not rest on the table's order: any order gives the reference's arrays.
    rng = np.random.default_rng(5)
    loc, word = rng.integers(0, 9, 500).astype(np.int32), rng.integers(0, 7, 500).astype(np.uint16)
    got = inverted_files(loc, word, 9, 7)
    for (key, want), g in zip(_index_by_argsort(loc, word, 9, 7).items(), got, strict=True):
        assert g.dtype == want.dtype, key
        np.testing.assert_array_equal(g, want, err_msg=key)
    for bad_loc, bad_word in ((9, 0), (-1, 0), (0, 7)):
        with pytest.raises(ValueError, match="outside the model"):
            inverted_files(np.r_[loc, bad_loc].astype(np.int32), np.r_[word, bad_word].astype(np.int32), 9, 7)


def _tour(rng: np.random.Generator, n_loc: int, per: int, *, skip: int = 1) -> list[Observation]:
    return [(i, rng.integers(0, 2000, per), rng.integers(0, 65535, (per, 2)).astype(np.uint16))
            for i in range(0, n_loc, skip)]


@pytest.mark.parametrize("spill", [False, True])
def test_add_tour_block_by_block_equals_sorting_everything(tmp_path: Any, spill: bool) -> None:
    # A table of ~1 MB is merged in 16 blocks of locations; a tour that re-observes some features (to
    # be OR-ed), skips locations and is given out of location order crosses every block boundary.
    rng = np.random.default_rng(11)
    m = _model(rng, 1500)
    obs = _tour(rng, 1500, 20, skip=3)[::-1]
    obs += [(int(loc), m.word[m.loc_ptr[loc]:m.loc_ptr[loc] + 5], m.xy[m.loc_ptr[loc]:m.loc_ptr[loc] + 5])
            for loc in range(0, 1500, 7)]
    want = _add_tour_by_sorting(m, obs, "b", 0)
    if spill:
        with spill_to(tmp_path, min_bytes=0):
            got = copy.deepcopy(m).add_tour(obs, name="b", position=0)
        # The table and the inverted files; the offsets (one per location and word) stay in memory.
        assert all(file_backed(got.__dict__[k]) for k in ('loc', 'word', 'xy', 'tours', 'by_word', 'wloc'))
        assert list(tmp_path.iterdir()) == []
    else:
        got = copy.deepcopy(m).add_tour(obs, name="b", position=0)
    _assert_same_model(got, want)


def test_merge_models_spilled_equals_in_memory(tmp_path: Any) -> None:
    rng = np.random.default_rng(12)
    parts = [_model(rng, n) for n in (300, 1, 500)]
    want = merge_models(parts)
    with spill_to(tmp_path, min_bytes=0):
        got = merge_models(parts)
    assert all(file_backed(got.__dict__[k]) for k in ('loc', 'word', 'xy', 'tours', 'by_word', 'wloc'))
    _assert_same_model(got, want)
    assert got.n_locations == 801


def test_renumber_locations_equals_building_with_the_new_numbers(tmp_path: Any) -> None:
    rng = np.random.default_rng(13)
    tour = _tour(rng, 400, 30)
    rows = np.sort(rng.choice(1000, 400, replace=False))
    m = CoocModel.build([tour], n_locations=400, n_words=2000, tour_names=["a"])
    want = CoocModel.build([[(int(rows[i]), w, xy) for i, w, xy in tour]], n_locations=1000, n_words=2000,
                           tour_names=["a"])
    with spill_to(tmp_path, min_bytes=0):
        got = copy.deepcopy(m).renumber_locations(rows, 1000)
    _assert_same_model(got, want)
    # 2^16 + 1 locations widen the location dtype.
    wide = copy.deepcopy(m).renumber_locations(rows + 65536 - 1000 + 1, 65537)
    assert wide.loc.dtype == np.int32 and int(wide.loc.max()) == int(rows.max()) + 65536 - 1000 + 1
    for bad in (rows[::-1], np.r_[rows[:-1], 1000], rows[:-1]):
        with pytest.raises(TopolocError, match="renumbered"):
            copy.deepcopy(m).renumber_locations(bad, 1000)


def test_within_spill_to_a_merge_and_a_tour_hold_blocks_of_the_map_not_the_map(tmp_path: Any) -> None:
    # The heap a merge and an added tour use within spill_to is blocks (io.scratch.CHUNK_BYTES), not the
    # map: its arrays are scratch files, which tracemalloc does not count (in memory, both peak above
    # 1x the model: test_add_tour_peak_is_a_small_multiple_of_the_model).
    rng = np.random.default_rng(14)
    parts = [_model(rng, 6000, 60) for _ in range(3)]
    out: list[CoocModel] = []
    with spill_to(tmp_path, min_bytes=0):
        merge_peak = _peak(lambda: out.append(merge_models(parts)))
        m = out[0]
        tour = _tour(rng, 18000, 15, skip=2)
        add_peak = _peak(lambda: m.add_tour(tour, name="b"))
    assert m.nbytes > 16 << 20
    # Measured: 0.04x and 0.14x the 20 MB model.
    assert merge_peak < 0.1 * m.nbytes and add_peak < 0.25 * m.nbytes, (merge_peak >> 20, add_peak >> 20)
