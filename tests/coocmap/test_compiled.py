"""The compiled matcher equals the reference matcher (Cooc-Map Sec. II-C, II-D)."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.coocmap.compiled import _one_location, _order_by_count, _prio, match_compiled
from topoloc.coocmap.matching import candidate_counts, consistency_graphs, match_lazy, match_sequential, tie_priority
from topoloc.coocmap.model import CoocModel


def _case(rng: np.random.Generator, *, n_loc: int = 30, n_tours: int = 3, nw: int = 25, n: int = 24,
          position_bits: int = 16, interpolate: bool = True) -> tuple[CoocModel, np.ndarray, np.ndarray]:
    scenes = [(rng.integers(0, nw, 2 * n), rng.integers(0, 65536, (2 * n, 2))) for _ in range(n_loc)]

    def view(loc: int) -> tuple[np.ndarray, np.ndarray]:
        w, xy = scenes[loc]
        idx = rng.choice(2 * n, n, replace=False)
        jitter = rng.integers(-300, 300, (n, 2))
        return w[idx].copy(), np.clip(xy[idx] + jitter, 0, 65535).astype(np.uint16)

    tours = [[(loc, *view(loc)) for loc in range(n_loc)] for _ in range(n_tours)]
    model = CoocModel.build(tours, n_locations=n_loc, n_words=nw, grid_x=5, grid_y=4,
                            interpolate=interpolate, position_bits=position_bits)
    w, xy = view(int(rng.integers(0, n_loc)))
    w[:5] = rng.integers(0, nw, 5)  # some noise
    return model, w, xy


@pytest.mark.parametrize("seed", range(8))
def test_compiled_equals_sequential(seed: int) -> None:
    rng = np.random.default_rng(seed)
    model, w, xy = _case(rng, position_bits=6 if seed % 2 else 16, interpolate=seed % 3 != 0)
    for tol in (0, 1, 2):
        g = consistency_graphs(model, w, xy, seed=seed, spatial_tolerance=tol)
        ref = match_sequential(g)
        for k in (1, 3, 30):
            res, group = match_compiled(model, w, xy, top_k=k, seed=seed, spatial_tolerance=tol)
            assert res.best == ref.best
            np.testing.assert_array_equal(res.scores[res.exact], ref.scores[res.exact])
            assert (res.scores >= ref.scores).all()  # dropped ones report an upper bound
            assert (res.scores[~res.exact] < np.sort(ref.scores)[-k]).all()
            np.testing.assert_array_equal(np.sort(res.scores)[::-1][:k], np.sort(ref.scores)[::-1][:k])
            np.testing.assert_array_equal(group, ref.group(g, ref.best))
            if k == 30:  # nothing can be dropped: every score exact, same elimination steps
                assert res.exact.all()
        lazy = match_lazy(model, w, xy, top_k=1, seed=seed, spatial_tolerance=tol)
        assert lazy.best == res.best


def test_compiled_prunes_and_counts() -> None:
    model, w, xy = _case(np.random.default_rng(3), n_loc=60)
    res, _ = match_compiled(model, w, xy, top_k=1, spatial_tolerance=1)
    full, _ = match_compiled(model, w, xy, top_k=60, spatial_tolerance=1)
    assert res.best == full.best and res.steps < full.steps
    assert res.locations_built <= full.locations_built  # type: ignore[attr-defined]
    assert not res.exact.all()
    # Visited: every location whose candidate count reached the threshold; with top_k = L, all with a candidate.
    n_i = candidate_counts(model, w)
    assert full.locations_visited == model.n_locations  # type: ignore[attr-defined]
    assert res.locations_built <= res.locations_visited <= full.locations_visited  # type: ignore[attr-defined]
    assert res.locations_visited >= int((n_i >= res.scores[res.best]).sum())  # type: ignore[attr-defined]


def test_tie_priority_is_the_same_hash() -> None:
    loc = np.array([0, 1, 5, 2199, 70000])
    f = np.array([0, 7, 999, 3, 123456])
    for seed in (0, 1, 2**31 + 5):
        want = tie_priority(seed, loc, f)
        got = [_prio(np.uint64(seed & 0xFFFFFFFF), np.uint64(a), np.uint64(b)) for a, b in zip(loc, f, strict=True)]
        np.testing.assert_array_equal(got, want)


def test_compiled_empty_and_unknown_words() -> None:
    model, _, _ = _case(np.random.default_rng(1), n_loc=4)
    res, group = match_compiled(model, np.zeros(0, np.int64), np.zeros((0, 2), np.uint16))
    assert res.scores.tolist() == [0.0] * 4 and len(group) == 0
    # Out-of-vocabulary words are no candidates; a single known word scores 1 where stored.
    words = np.array([-1, 10_000, int(model.word[0])])
    res, group = match_compiled(model, words, np.zeros((3, 2), np.uint16), top_k=4)
    ref = match_sequential(consistency_graphs(model, words, np.zeros((3, 2), np.uint16)))
    np.testing.assert_array_equal(res.scores, ref.scores)
    assert group.tolist() == [2]


def test_one_location_with_and_without_the_translation_bound() -> None:
    model, w, xy = _case(np.random.default_rng(5), n_loc=6)
    g = consistency_graphs(model, w, xy, seed=0, spatial_tolerance=1)
    ref = match_sequential(g)
    for loc in range(6):
        for tb_prune in (True, False):
            for pairwise_max in (0, 10**6):  # the translation histogram, and pair by pair
                score, exact, *_, group = _one_location(model, loc, -1.0, w, xy, tol=1, tb_prune=tb_prune,
                                                        pairwise_max=pairwise_max)
                assert exact and score == ref.scores[loc]
                np.testing.assert_array_equal(group, ref.group(g, loc))
        # A threshold above every bound drops the location with an upper bound on its score.
        score, exact, *_ = _one_location(model, loc, 1e9, w, xy, tol=1)
        assert not exact and score >= ref.scores[loc]


@pytest.mark.parametrize("tol", [0, 1, 2])
def test_translation_bound_counts_the_same_both_ways(tol: int) -> None:
    """Pair by pair and through the summed-area table, the same bound on every location."""
    model, w, xy = _case(np.random.default_rng(11 + tol), n_loc=40, position_bits=6)
    g = consistency_graphs(model, w, xy, seed=0, spatial_tolerance=tol)
    ref = match_sequential(g)
    bounds = []
    for pairwise_max in (0, 10**6):
        # thr above every score: each location reports its translation bound (dropped there, 1 in the last place)
        out = [_one_location(model, loc, 1e9, w, xy, tol=tol, pairwise_max=pairwise_max) for loc in range(40)]
        assert all(o[4] == 1 for o in out if o[0] > 0)
        bounds.append([o[0] for o in out])
    assert bounds[0] == bounds[1]
    assert (np.asarray(bounds[0]) >= ref.scores).all()


def test_order_by_count_is_a_stable_descending_sort() -> None:
    rng = np.random.default_rng(0)
    for n in (0, 1, 7, 1000):
        counts = rng.integers(0, 12, n).astype(np.int64)
        np.testing.assert_array_equal(_order_by_count(counts), np.lexsort((np.arange(n), -counts)))


@pytest.mark.parametrize(("seed", "n_loc"), [(0, 80), (1, 80), (2, 80), (3, 80), (4, 700), (5, 1300)])
def test_parallel_batches_give_the_same_scores(seed: int, n_loc: int) -> None:
    """Threads change which locations get finished and when, never what S says (bit for bit).

    Claims of several locations at once (8 first, then up to 1/64 of the map); 1,300 locations: the
    first 1,024 by candidate count, the rest in location order.
    """
    rng = np.random.default_rng(100 + seed)
    model, w, xy = _case(rng, n_loc=n_loc, position_bits=6)
    ref = match_sequential(consistency_graphs(model, w, xy, seed=seed, spatial_tolerance=1))
    for k in (1, 5):
        serial, g1 = match_compiled(model, w, xy, top_k=k, seed=seed, spatial_tolerance=1, parallel=False)
        for threads in (2, 3):
            par, g2 = match_compiled(model, w, xy, top_k=k, seed=seed, spatial_tolerance=1, threads=threads)
            np.testing.assert_array_equal(serial.scores, par.scores)
            np.testing.assert_array_equal(serial.exact, par.exact)
            np.testing.assert_array_equal(g1, g2)
        assert serial.best == par.best == ref.best
        T = np.sort(ref.scores)[::-1][k - 1]
        # Locations at or above the top_k-th best score are exact; the others report min(n_i, T - 1/2).
        np.testing.assert_array_equal(serial.exact, ref.scores >= T)
        assert (serial.scores[~serial.exact] < T).all()
        assert (serial.scores >= ref.scores).all()


@pytest.mark.parametrize("n_loc", [60, 1300])
def test_a_descheduled_helper_never_stalls_the_query(monkeypatch: pytest.MonkeyPatch, n_loc: int) -> None:
    """A helper that holds a chunk of locations and is never run again: the query finishes without it, same S."""
    import threading
    import time

    from topoloc.coocmap import compiled

    rng = np.random.default_rng(7)
    model, w, xy = _case(rng, n_loc=n_loc, position_bits=6)
    serial, g1 = match_compiled(model, w, xy, top_k=3, spatial_tolerance=1, parallel=False)
    claimed, release = threading.Event(), threading.Event()
    held: list[tuple[int, int, np.ndarray, int] | None] = []

    def stuck_helper(shared: compiled._Shared) -> None:  # claims the first free location, then sleeps
        job = shared.claim(helper=True)
        held.append(job)
        claimed.set()
        release.wait(30)
        if job is not None:
            shared.run(*job)  # too late: the query recorded it itself

    claim = compiled._Shared.claim

    def helper_first(shared: compiled._Shared, helper: bool) -> tuple[int, int, np.ndarray, int] | None:
        if not helper:
            claimed.wait(10)  # the helper holds a location before the calling thread starts
        return claim(shared, helper)

    monkeypatch.setattr(compiled, "_helper", stuck_helper)
    monkeypatch.setattr(compiled._Shared, "claim", helper_first)
    t0 = time.perf_counter()
    try:
        par, g2 = match_compiled(model, w, xy, top_k=3, spatial_tolerance=1, threads=2)
        assert claimed.is_set() and not release.is_set()  # it returned while the helper still held its location
        job = held[0]
        assert job is not None and job[1] - job[0] == 1  # no location had finished: one at a time
    finally:
        release.set()
    assert time.perf_counter() - t0 < 10
    np.testing.assert_array_equal(serial.scores, par.scores)
    np.testing.assert_array_equal(serial.exact, par.exact)
    np.testing.assert_array_equal(g1, g2)


@pytest.mark.parametrize("helpers", [False, True])
def test_claims_are_one_location_until_top_k_have_finished(helpers: bool) -> None:
    """With helpers, no chunk is matched without a threshold: one location a claim until top_k have finished.

    Alone, the calling thread's chunk raises its own threshold as it goes, so it claims chunks from the start.
    """
    from topoloc.coocmap import compiled

    rng = np.random.default_rng(11)
    model, w, xy = _case(rng, n_loc=300, position_bits=6)
    qptr, qf, qx, qy = compiled._query_table(model, w, xy)
    n_cand = compiled._candidate_counts(model.wloc_ptr, model.wloc, w[qf], model.n_locations)
    order = compiled._order_by_count(n_cand)
    args = compiled._kernel_args(model, qptr, qf, qx, qy, interpolate=None, spatial_tolerance=1, seed=0)
    top_k = 5
    shared = compiled._Shared(order, n_cand, args, top_k, compiled.SEED_FIRST, len(w), helpers=helpers)
    sizes, finished_before = [], []
    while (job := shared.claim(helper=False)) is not None:
        sizes.append(job[1] - job[0])
        finished_before.append(shared.n_fin)
        shared.run(*job)
    sizes_arr, fin = np.array(sizes), np.array(finished_before)
    if helpers:
        assert (sizes_arr[fin < top_k] == 1).all() and (fin < top_k).sum() >= top_k
        assert sizes_arr[fin >= top_k][0] == compiled.FIRST_CHUNK
    else:
        assert sizes_arr[0] == compiled.FIRST_CHUNK
    # Either way the same S as the serial matcher.
    scores = np.full(model.n_locations, -1.0)
    for p0, end, sc, _, _ in shared.records:
        scores[shared.order[p0:end]] = sc
    serial, _ = match_compiled(model, w, xy, top_k=top_k, spatial_tolerance=1, parallel=False)
    exact = serial.exact
    np.testing.assert_array_equal(scores[exact], serial.scores[exact])


def _textured_case(seed: int, *, n_loc: int = 40, nw: int = 12, n: int = 70, tours: int = 3) -> tuple[
        CoocModel, np.ndarray, np.ndarray]:
    """Few words, many features: each word recurs in every image (texture), tens of triples per candidate."""
    return _case(np.random.default_rng(seed), n_loc=n_loc, n_tours=tours, nw=nw, n=n, position_bits=6)


def _window_and_translation_bounds(model: CoocModel, loc: int, w: np.ndarray, xy: np.ndarray, tol: int,
                                   thr: float) -> tuple[int, int, int, int]:
    """(candidates, triples, translation bound, window bound against ``thr``) of one location."""
    from topoloc.coocmap import compiled as c

    qptr, qf, qx, qy = c._query_table(model, w, xy)
    gx, gy = int(model.grid_x), int(model.grid_y)
    stamp, cand, cof, U, t_f, t_a, t_b, t_x, t_y, P, hist, _ = c._new_scratch(
        len(qx), c._triple_capacity(model.loc_ptr, qptr), gx, gy)
    n, nt = c._triples(model.loc_ptr[loc], model.loc_ptr[loc + 1], model.word, model.xy, qptr, qf, qx, gx, 0, stamp,
                       cand, cof, t_f, t_a, t_x)
    c._triple_rows(nt, t_f, t_a, t_x, model.xy, qy, gy, t_y, t_b)
    tb = c._translation_bound(n, nt, cand, t_f, t_x, t_y, U, P, hist, gx, gy, tol + 1, c._PAIRWISE_MAX)
    wb = c._window_bound(n, nt, cand, cof, t_f, t_x, t_y, U, hist, gx, gy, tol + 1, float(thr), c._WINDOW_ROUNDS)
    return n, nt, int(tb), int(wb)


@pytest.mark.parametrize("tol", [0, 1])
def test_window_bound_bounds_every_score_and_is_tighter_than_the_translation_bound(tol: int) -> None:
    model, w, xy = _textured_case(21 + tol, n_loc=12)
    ref = match_sequential(consistency_graphs(model, w, xy, spatial_tolerance=tol))
    tighter = 0
    for loc in range(model.n_locations):
        n, nt, tb, wb = _window_and_translation_bounds(model, loc, w, xy, tol, 0.0)  # thr 0: no peeling
        assert nt >= 2 * n  # the textured case: where the matcher computes this bound
        assert ref.scores[loc] <= wb <= tb
        tighter += wb < tb
        # Peeling against a threshold: below it only when the score is below it, and still an upper bound.
        for thr in (ref.scores[loc], ref.scores[loc] + 1, wb + 1):
            _, _, _, peeled = _window_and_translation_bounds(model, loc, w, xy, tol, float(thr))
            assert peeled >= ref.scores[loc]
            if thr <= ref.scores[loc]:
                assert peeled >= thr
    assert tighter >= model.n_locations // 2


@pytest.mark.parametrize("seed", range(6))
def test_compiled_equals_the_reference_where_words_recur(seed: int) -> None:
    """Textured scenes (the slow tail, issue #38): same S as the rule every schedule follows, bit for bit.

    Locations at or above the top_k-th best score T are exact and equal the reference
    (every J built, every location eliminated to completion); the others report min(n_i, T - 1/2);
    the best location's group is the reference's.  And the bounds before J drop locations here.
    """
    model, w, xy = _textured_case(seed)
    n_i = candidate_counts(model, w)
    dropped = 0
    for tol in (0, 1, 2):
        g = consistency_graphs(model, w, xy, seed=seed, spatial_tolerance=tol)
        ref = match_sequential(g)
        for k in (1, 3):
            T = np.sort(ref.scores)[::-1][k - 1]
            want = np.where(ref.scores >= T, ref.scores, np.minimum(n_i, T - 0.5))
            for threads in (1, 2):
                res, group = match_compiled(model, w, xy, top_k=k, seed=seed, spatial_tolerance=tol, threads=threads)
                np.testing.assert_array_equal(res.exact, ref.scores >= T)
                np.testing.assert_array_equal(res.scores, want.astype(res.scores.dtype))
                np.testing.assert_array_equal(group, ref.group(g, ref.best))
                assert res.best == ref.best
                dropped += res.translation_pruned  # type: ignore[attr-defined]
    assert dropped > 0


@pytest.mark.parametrize(("seed", "n_loc", "k"), [(0, 12, 10), (1, 12, 10), (2, 14, 10), (3, 20, 10), (4, 40, 5)])
def test_scores_follow_one_rule_whatever_the_schedule_finished(seed: int, n_loc: int, k: int) -> None:
    """S is exact at or above T (the top_k-th best score) and min(n_i, T - 1/2) below, even when every
    location happened to be finished: which ones a schedule finishes depends on the threads' timing
    (issue #41: localize --sequence 10 on a 20-place map gave other lines beside a busy process)."""
    rng = np.random.default_rng(200 + seed)
    model, w, xy = _case(rng, n_loc=n_loc, position_bits=6)
    ref = match_sequential(consistency_graphs(model, w, xy, seed=seed, spatial_tolerance=1))
    T = np.sort(ref.scores)[::-1][k - 1]
    n_i = candidate_counts(model, w).astype(np.float32)
    expected = np.where(ref.scores >= T, ref.scores, np.minimum(n_i, T - 0.5)).astype(np.float32)
    for kw in ({"parallel": False}, {"threads": 2}, {"threads": 4}):
        res, _ = match_compiled(model, w, xy, top_k=k, seed=seed, spatial_tolerance=1, **kw)
        np.testing.assert_array_equal(res.scores, expected)
        np.testing.assert_array_equal(res.exact, ref.scores >= T)


@pytest.mark.parametrize(("seed", "textured", "tol"), [(0, False, 1), (1, False, 0), (2, True, 1), (3, True, 2),
                                                       (4, False, 2)])
def test_both_sweeps_of_j_give_the_same_locations(seed: int, textured: bool, tol: int) -> None:
    """Run by run or bucket by bucket, the same J: the same score, group and elimination steps on every location.

    The bucket sweep skips every pair of candidates already known consistent through bitsets, so only
    which pairs are tested (and how many) may differ; no bound drops a location here (``thr=-1``,
    no bounds before J), so every J is built and eliminated to completion.
    """
    model, w, xy = (_textured_case(seed) if textured
                    else _case(np.random.default_rng(seed), n_loc=30, position_bits=6))
    for loc in range(model.n_locations):
        kw = {"tol": tol, "seed": seed, "tb_prune": False}
        by_runs = _one_location(model, loc, -1.0, w, xy, sweep=1, **kw)
        by_buckets = _one_location(model, loc, -1.0, w, xy, sweep=2, **kw)
        chosen = _one_location(model, loc, -1.0, w, xy, **kw)
        for res in (by_buckets, chosen):
            assert res[:3] == by_runs[:3]
            np.testing.assert_array_equal(res[5], by_runs[5])
