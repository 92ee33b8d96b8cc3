"""Correspondences, J, elimination and simultaneous matching (Cooc-Map Sec. II-C, II-D)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from topoloc.coocmap.matching import (
    ConsistencyGraphs,
    consistency_graphs,
    eliminate,
    match_best_first,
    match_lazy,
    match_sequential,
    match_simultaneous,
)
from topoloc.coocmap.model import CoocModel

G: dict[str, Any] = {"grid_x": 3, "grid_y": 2}
BLUE, PURPLE, RED, GREEN, ORANGE = range(5)


def _fig5_J() -> np.ndarray:
    J = np.eye(5, dtype=bool)
    for a, b in [(PURPLE, RED), (PURPLE, GREEN), (RED, GREEN), (RED, ORANGE), (GREEN, ORANGE)]:
        J[a, b] = J[b, a] = True
    return J


def test_fig5_elimination_by_hand() -> None:
    # Scores: blue 0, purple 2, red 3, green 3, orange 2.  Blue goes first; purple and
    # orange then tie at 2 and the paper's figure eliminates purple: give it the lower key.
    keep, order = eliminate(_fig5_J(), np.array([0.5, 0.1, 0.5, 0.5, 0.9]))
    assert order.tolist() == [BLUE, PURPLE]
    assert np.flatnonzero(keep).tolist() == [RED, GREEN, ORANGE]
    # The other tie-break gives another group of the same size.
    keep, order = eliminate(_fig5_J(), np.array([0.5, 0.9, 0.5, 0.5, 0.1]))
    assert order.tolist() == [BLUE, ORANGE] and keep.sum() == 3
    # Seeded random tie-breaking: both outcomes occur, each seed is reproducible.
    groups = {tuple(eliminate(_fig5_J(), rng=np.random.default_rng(s))[0]) for s in range(20)}
    assert len(groups) == 2
    a = eliminate(_fig5_J(), rng=np.random.default_rng(7))
    b = eliminate(_fig5_J(), rng=np.random.default_rng(7))
    assert a[1].tolist() == b[1].tolist()


def test_elimination_invariants_random() -> None:
    rng = np.random.default_rng(0)
    for _ in range(30):
        n = int(rng.integers(1, 25))
        U = np.triu(rng.random((n, n)) < rng.uniform(0.1, 0.9), 1)
        J = U | U.T | np.eye(n, dtype=bool)
        prio = rng.random(n)
        keep, order = eliminate(J, prio)
        assert J[np.ix_(keep, keep)].all()  # the final group is mutually consistent
        alive = np.ones(n, bool)
        for e in order:  # every step removed the least consistent one (recomputed from scratch)
            score = (J[alive][:, alive].sum(axis=1) - 1)
            idx = np.flatnonzero(alive)
            best = idx[np.lexsort((prio[idx], score))[0]]
            assert e == best
            alive[e] = False
        assert (alive == keep).all()


def _one_location_model() -> tuple[CoocModel, np.ndarray, np.ndarray]:
    # Training image: words 1, 2, 3 in a row left to right, 10 to the far bottom-left.
    u = 65536 // 12
    words = np.array([1, 2, 3, 10])
    xy = np.array([(u, u), (3 * u, u), (5 * u, u), (u, 11 * u)], np.uint16)
    return CoocModel.build([[(0, words, xy)]], n_locations=1, n_words=12, **G), words, xy


def test_J_by_hand() -> None:
    model, _, _ = _one_location_model()
    u = 65536 // 12
    # Query: 1, 2, 3 shifted right by 2u (same offsets), 3 repeated far right, 7 unseen, 10 above.
    q_words = np.array([1, 2, 3, 3, 7, 10])
    q_xy = np.array([(3 * u, 2 * u), (5 * u, 2 * u), (7 * u, 2 * u), (11 * u, 2 * u),
                     (6 * u, 6 * u), (3 * u, 3 * u)], np.uint16)
    g = consistency_graphs(model, q_words, q_xy)
    feats, J = g.dense(0)
    assert feats.tolist() == [0, 1, 2, 3, 5]  # word 7 is not in M: no candidate
    want = np.eye(5, dtype=bool)
    # 1-2, 2-3, 1-3 keep their training offsets; the second 3 is 6u right of 2 (not 2u).
    # 1-(3 far): 8u right of 1, training 4u: other column -> inconsistent.
    # 10 is above the row in the query but below it in training -> inconsistent.
    for a, b in [(0, 1), (1, 2), (0, 2)]:
        want[a, b] = want[b, a] = True
    np.testing.assert_array_equal(J, want)
    res = match_simultaneous(g)
    assert res.scores.tolist() == [3.0]
    assert res.group(g, 0).tolist() == [0, 1, 2]


def _random_case(rng: np.random.Generator, n_loc: int = 25) -> tuple[CoocModel, np.ndarray, np.ndarray]:
    nw = 30
    tours = [[(loc, rng.integers(0, nw, 20), rng.integers(0, 65536, (20, 2)).astype(np.uint16))
              for loc in range(n_loc)] for _ in range(2)]
    model = CoocModel.build(tours, n_locations=n_loc, n_words=nw, **G)
    loc = int(rng.integers(0, n_loc))
    w, xy = tours[1][loc][1].copy(), tours[1][loc][2].copy()
    w[:8] = rng.integers(0, nw, 8)  # some noise
    return model, w, xy


@pytest.mark.parametrize("seed", range(6))
def test_simultaneous_equals_sequential(seed: int) -> None:
    model, w, xy = _random_case(np.random.default_rng(seed))
    g = consistency_graphs(model, w, xy, seed=seed)
    ref = match_sequential(g)
    full = match_simultaneous(g, prune=False)
    np.testing.assert_array_equal(full.scores, ref.scores)  # isolated shortcut is exact
    np.testing.assert_array_equal(full.kept, ref.kept)
    for k, matcher in [(1, match_simultaneous), (3, match_simultaneous), (1, match_best_first),
                       (3, match_best_first)]:
        sim = matcher(g, top_k=k)
        assert sim.best == ref.best
        assert sim.steps <= full.steps
        np.testing.assert_array_equal(sim.scores[sim.exact], ref.scores[sim.exact])
        assert (sim.scores[~sim.exact] < np.sort(ref.scores)[-k]).all()  # dropped: below top-k
        top = np.sort(ref.scores)[::-1][:k]
        np.testing.assert_array_equal(np.sort(sim.scores)[::-1][:k], top)


@pytest.mark.parametrize("seed", range(6))
def test_lazy_equals_sequential(seed: int) -> None:
    model, w, xy = _random_case(np.random.default_rng(seed), n_loc=40)
    ref = match_sequential(consistency_graphs(model, w, xy, seed=seed))
    for k in (1, 3):
        lazy = match_lazy(model, w, xy, top_k=k, seed=seed, first_batch=2)
        assert lazy.best == ref.best
        np.testing.assert_array_equal(lazy.scores[lazy.exact], ref.scores[lazy.exact])
        assert (lazy.scores[~lazy.exact] < np.sort(ref.scores)[-k]).all()
        assert (lazy.scores >= ref.scores).all()  # dropped ones report an upper bound


def test_empty_query_and_no_candidates() -> None:
    model, _, _ = _one_location_model()
    g = consistency_graphs(model, np.zeros(0, np.int64), np.zeros((0, 2), np.uint16))
    assert match_simultaneous(g).scores.tolist() == [0.0]
    g = consistency_graphs(model, np.array([7, 7]), np.zeros((2, 2), np.uint16))
    assert match_sequential(g).scores.tolist() == [0.0]
    g = consistency_graphs(model, np.array([1]), np.zeros((1, 2), np.uint16))
    assert match_simultaneous(g).scores.tolist() == [1.0]
    assert isinstance(g, ConsistencyGraphs) and g.n_locations == 1


@pytest.mark.parametrize("tol", [0, 1, 2])
def test_J_equals_brute_force_lookup(tol: int) -> None:
    """J from the bucketed enumeration == a direct search of stored feature pairs."""
    from topoloc.coocmap.spatial import signed_cells

    rng = np.random.default_rng(tol)
    gx, gy = 4, 3
    tours = [[(loc, rng.integers(0, 6, 10), rng.integers(0, 65536, (10, 2)).astype(np.uint16))
              for loc in range(3)] for _ in range(3)]
    m = CoocModel.build(tours, n_locations=3, n_words=6, grid_x=gx, grid_y=gy)
    groups = m.group_masks()
    w = rng.integers(0, 6, 12)
    xy = rng.integers(0, 65536, (12, 2)).astype(np.uint16)
    g = consistency_graphs(m, w, xy, spatial_tolerance=tol)

    def cells(p: np.ndarray, q: np.ndarray) -> tuple[int, int]:
        d = q.astype(np.int32) - p.astype(np.int32)
        sx, sy = signed_cells(d[0], d[1], gx, gy)
        return int(sx), int(sy)

    for loc in range(3):
        f, J = g.dense(loc)
        idx = range(int(m.loc_ptr[loc]), int(m.loc_ptr[loc + 1]))
        ref = np.eye(len(f), dtype=bool)
        for u in range(len(f)):
            for v in range(u + 1, len(f)):
                qs = cells(xy[f[u]], xy[f[v]])
                ref[u, v] = ref[v, u] = any(
                    a != b and m.word[a] == w[f[u]] and m.word[b] == w[f[v]]
                    and groups[a] & groups[b]
                    and max(abs(c - d) for c, d in zip(cells(m.xy[a], m.xy[b]), qs, strict=True)) <= tol
                    for a in idx for b in idx)
        np.testing.assert_array_equal(J, ref)
