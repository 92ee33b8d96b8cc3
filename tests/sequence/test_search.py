"""Sequence search on small hand-made difference matrices (SeqSLAM and Cooc-Map II-F)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

import topoloc.sequence.search as search
from topoloc.sequence import (
    acceleration_search,
    constant_velocity_search,
    contrast_enhance,
    sequence_similarity,
    similarity_to_difference,
    uniqueness_margin,
    velocity_offsets,
)


# ----------------------------------------------------------------- brute force
def at(D: np.ndarray, row: int, col: int) -> float:
    """D[row, col], or the column's mean over the map for a row before place 0."""
    return float(D[row, col]) if row >= 0 else float(D[:, col].astype(np.float64).mean())


def brute_constant(D: np.ndarray, ds: int, velocities: list[float]) -> np.ndarray:
    """Straight lines ending at (p, T), neutral before place 0, mean over real frames."""
    n, m = D.shape
    out = np.full((n, m), np.inf)
    for T, p, v in itertools.product(range(m), range(n), velocities):
        end = int(np.floor(ds * v + 1e-9))
        vals = [
            at(D, p - end + int(np.floor(k * v + 1e-9)), T - ds + k)
            for k in range(ds + 1)
            if T - ds + k >= 0
        ]
        out[p, T] = min(out[p, T], float(np.mean(vals)))
    return out


def brute_acceleration(
    D: np.ndarray, ds: int, max_step: int, v_min: float, v_max: float, penalty: float = 0.0
) -> np.ndarray:
    """Every forward path of steps of 0..max_step places over the real frames of the window.

    Query T has n = min(T, ds) steps behind it; the path's total advance lies in
    [ceil(n v_min), min(n max_step, floor(n v_max))].
    """
    n_db, m = D.shape
    out = np.full((n_db, m), np.inf)
    for T in range(m):
        n = min(T, ds)
        lo = int(np.ceil(n * v_min - 1e-9))
        hi = n * max_step if not np.isfinite(v_max) else min(n * max_step, int(np.floor(n * v_max + 1e-9)))
        for steps in itertools.product(range(max_step + 1), repeat=n):
            a = sum(steps)
            if not lo <= a <= hi:
                continue
            pos = np.r_[0, np.cumsum(steps)].astype(int)
            pen = penalty * sum(abs(s - 1) for s in steps)
            for p in range(n_db):
                tot = pen + sum(at(D, p - a + int(pos[k]), T - n + k) for k in range(n + 1))
                out[p, T] = min(out[p, T], tot / (n + 1))
    return out


def brute_enhance(D: np.ndarray, window: int) -> np.ndarray:
    """OpenSeqSLAM enhanceContrast.m, row by row."""
    out = np.zeros(D.shape)
    n = D.shape[0]
    for i in range(n):
        v = D[max(0, i - window // 2) : min(n, i + window // 2 + 1)].astype(np.float64)
        sd = v.std(axis=0, ddof=1) if len(v) > 1 else np.zeros(D.shape[1])
        out[i] = np.where(sd > 1e-9, (D[i] - v.mean(axis=0)) / np.where(sd > 1e-9, sd, 1), 0)
    return out


def noise(n_db: int, n_q: int, seed: int = 0, lo: float = 0.6, hi: float = 1.0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(lo, hi, (n_db, n_q)).astype(np.float32)


def path_matrix(positions: list[int], n_db: int, seed: int = 0) -> np.ndarray:
    """Noise in [0.6, 1] with zeros where query t sees place positions[t]."""
    D = noise(n_db, len(positions), seed)
    D[positions, np.arange(len(positions))] = 0.0
    return D


# ---------------------------------------------------------------- exactness
@pytest.mark.parametrize("ds", [0, 1, 4, 5])
def test_constant_velocity_matches_brute_force(ds: int) -> None:
    D = noise(23, 12, seed=ds)
    got = constant_velocity_search(D, ds=ds)
    want = brute_constant(D, ds, [0.8, 0.9, 1.0, 1.1, 1.2])
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(
    ("max_skip", "v_min", "v_max", "penalty"),
    [(1, 0.8, 1.2, 0.0), (1, 0.0, np.inf, 0.0), (1, 0.5, 1.5, 0.3), (2, 0.0, 3.0, 0.2)],
)
def test_acceleration_matches_brute_force(
    max_skip: int, v_min: float, v_max: float, penalty: float
) -> None:
    ds = 4
    D = noise(19, 9, seed=7)
    got = acceleration_search(
        D, ds=ds, max_skip=max_skip, v_min=v_min, v_max=v_max, step_penalty=penalty
    )
    want = brute_acceleration(D, ds, max_skip + 1, v_min, v_max, penalty)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


def test_velocity_offsets_defaults() -> None:
    off = velocity_offsets(10)
    assert off.shape == (5, 11)  # 0.8, 0.9, 1.0, 1.1, 1.2 as OpenSeqSLAM's move = 8:12
    assert (off[:, -1] == 0).all()
    assert sorted(off[:, 0].tolist()) == [8, 9, 10, 11, 12]  # floor(ds v) places back
    assert [10 - k for k in range(11)] in off.tolist()  # v = 1: the diagonal
    # 10 * 1.1 must count as 11, not 10.999...
    assert 11 in velocity_offsets(10, 1.1, 1.1, 0.1)[:, 0]


# ---------------------------------------------------------- hand-made routes
def test_diagonal_at_velocity_one_is_recovered() -> None:
    n_q, shift = 40, 7
    D = path_matrix([t + shift for t in range(n_q)], n_db=60)
    for cost in (constant_velocity_search(D), acceleration_search(D)):
        assert cost.shape == D.shape
        np.testing.assert_array_equal(np.argmin(cost, axis=0), np.arange(n_q) + shift)
        # On the path the cost is exactly 0: every frame of the line hits it.
        np.testing.assert_allclose(cost[np.arange(n_q) + shift, np.arange(n_q)], 0.0)


def test_velocity_range_lines_are_recovered() -> None:
    # Query at 1.2 places per frame: positions floor(1.2 t), a line SeqSLAM searches.
    pos = [int(np.floor(1.2 * t + 1e-9)) for t in range(30)]
    D = path_matrix(pos, n_db=50)
    cost = constant_velocity_search(D)
    best = np.argmin(cost, axis=0)
    # Lines are anchored at the window's first frame, so the staircase of
    # floor(1.2 t) is reproduced exactly when 1.2 (T - 10) is an integer ...
    for T in (10, 15, 20, 25):
        assert best[T] == pos[T]
        assert cost[pos[T], T] == pytest.approx(0.0)
    # ... and otherwise to within one place (one frame of the line is off).
    assert (np.abs(best[10:] - np.asarray(pos[10:])) <= 1).all()


def _with_decoy(D: np.ndarray, end_place: int, value: float = 0.35) -> np.ndarray:
    """A look-alike stretch: a straight v = 1 line of moderately low differences."""
    D = D.copy()
    n_q = D.shape[1]
    for t in range(n_q):
        D[end_place - (n_q - 1) + t, t] = value
    return D


def test_route_with_a_stop() -> None:
    # The query vehicle stops at place 15 for five frames, then drives on.
    steps = [1] * 5 + [0] * 5 + [1] * 10
    pos = list(10 + np.r_[0, np.cumsum(steps)])
    T = len(pos) - 1
    D = path_matrix(pos, n_db=60, seed=3)
    D = _with_decoy(D, end_place=50)
    cv = constant_velocity_search(D)
    # Lines at 0.8-1.2 places per frame cannot follow the stop: while it
    # fills most of the window the straight look-alike wins ...
    for t in (11, 12, 13):
        assert np.argmin(cv[:, t]) == 50 - (T - t)
    # ... and most queries during and just after the stop are wrong.
    assert (np.argmin(cv[:, 6:14], axis=0) != pos[6:14]).sum() >= 6
    # Forward paths may repeat a place; a full stop needs v_min = 0 (the
    # default bound on the average velocity is SeqSLAM's 0.8).
    acc = acceleration_search(D, v_min=0.0, v_max=1.2)
    np.testing.assert_array_equal(np.argmin(acc, axis=0), pos)
    np.testing.assert_allclose(acc[pos, np.arange(len(pos))], 0.0)
    # Before the stop both searches agree with the route.
    np.testing.assert_array_equal(np.argmin(cv[:, :5], axis=0), pos[:5])


def test_acceleration_path_beats_constant_velocity() -> None:
    # Cooc-Map Fig. 7: within the window the query starts slow and speeds up
    # (steps 0,0,0,1,1,1,2,2,2,2: average 1.2 places per frame, a velocity
    # SeqSLAM searches, but not along a straight line).
    steps = [0, 0, 0, 1, 1, 1, 2, 2, 2, 2]
    pos = list(20 + np.r_[0, np.cumsum(steps)])
    D = _with_decoy(path_matrix(pos, n_db=70, seed=5), end_place=55)
    T = len(pos) - 1
    cv = constant_velocity_search(D)
    acc = acceleration_search(D)  # defaults: steps 0-2, average velocity 0.8-1.2
    assert np.argmin(cv[:, T]) == 55  # the straight look-alike wins ...
    assert np.argmin(acc[:, T]) == pos[-1]  # ... the forward path recovers the route
    assert acc[pos[-1], T] == pytest.approx(0.0)
    assert cv[pos[-1], T] > cv[55, T]


def test_bounded_velocity_ignores_a_hub_place() -> None:
    # A place that resembles every query (e.g. a blank image) is a row of low
    # differences.  Unbounded forward paths sit on it; SeqSLAM's velocity
    # bound on the average keeps them on the route.
    n_q = 25
    pos = [t + 5 for t in range(n_q)]
    D = noise(60, n_q, seed=9)
    D[pos, np.arange(n_q)] = 0.3
    D[45] = 0.2
    free = acceleration_search(D, v_min=0.0, v_max=np.inf)
    bounded = acceleration_search(D)
    assert (np.argmin(free[:, 10:], axis=0) == 45).all()
    np.testing.assert_array_equal(np.argmin(bounded[:, 10:], axis=0), pos[10:])
    np.testing.assert_array_equal(np.argmin(constant_velocity_search(D)[:, 10:], axis=0), pos[10:])


def test_step_penalty_favours_unit_steps() -> None:
    D = noise(30, 11, seed=2)
    base = acceleration_search(D, v_min=0.0, v_max=2.0)
    pen = acceleration_search(D, v_min=0.0, v_max=2.0, step_penalty=0.5)
    assert (pen >= base - 1e-6).all()
    # A huge penalty leaves only the unit-step (v = 1) path.
    huge = acceleration_search(D, v_min=0.0, v_max=2.0, step_penalty=1e6)
    line = constant_velocity_search(D, v_min=1.0, v_max=1.0)
    np.testing.assert_allclose(huge[10:, 10:], line[10:, 10:], rtol=1e-6)


# ------------------------------------------------------ start of the traverse
def test_first_queries_use_a_shorter_window() -> None:
    D = noise(20, 15, seed=4)
    for cost in (constant_velocity_search(D, ds=10), acceleration_search(D, ds=10)):
        # Query 0 has no history: its cost is its own difference.
        np.testing.assert_allclose(cost[:, 0], D[:, 0], rtol=1e-6)
    # Query 2 averages its 3 frames along the best line (v = 1 from the diagonal).
    cv = constant_velocity_search(D, ds=10, v_min=1.0, v_max=1.0)
    p = 12
    np.testing.assert_allclose(cv[p, 2], (D[p - 2, 0] + D[p - 1, 1] + D[p, 2]) / 3, rtol=1e-6)
    # Scores of early queries are means, on the scale of full windows.
    assert cv[:, :10].mean() == pytest.approx(cv[:, 10:].mean(), rel=0.25)


def test_frames_before_place_zero_count_as_the_mean_difference() -> None:
    D = noise(20, 12, seed=8)
    cv = constant_velocity_search(D, ds=10, v_min=1.0, v_max=1.0)
    # The v = 1 line ending at place 3 at query 11 is before place 0 at frames 1-7:
    # those count with their query's mean over the map, and all 11 frames divide.
    mean = D.astype(np.float64).mean(axis=0)
    want = (mean[1:8].sum() + D[0, 8] + D[1, 9] + D[2, 10] + D[3, 11]) / 11
    assert cv[3, 11] == pytest.approx(want, rel=1e-6)
    assert np.isfinite(acceleration_search(D)).all()


@pytest.mark.parametrize("mode", ["constant", "acceleration"])
def test_one_hub_at_place_zero_does_not_capture_the_search(mode: str) -> None:
    # Queries follow the diagonal (difference 0.3, noise 0.6-1); place 0 is a
    # "hub" image that resembles every query better than its true place does.
    n = 60
    D = path_matrix(list(range(n)), n_db=n, seed=3)
    D[np.arange(n), np.arange(n)] = 0.3
    D[0] = 0.2  # the best row of every column
    # The searches on D and on its enhancement, and the stage every method's
    # --sequence runs (a similarity with a "hub" row, z-scored per query).
    for best in (
        search.sequence_search(D, mode=mode).argmin(axis=0),  # type: ignore[arg-type]
        search.sequence_search(contrast_enhance(D), mode=mode).argmin(axis=0),  # type: ignore[arg-type]
        sequence_similarity(-D, mode=mode).argmax(axis=0),  # type: ignore[arg-type]
    ):
        # Only query 0, whose true place it is.  (Acceleration paths of the
        # first ds queries used to repeat the hub for all their real frames,
        # their velocity bound met in frames before query 0.)
        assert (best[1:] == 0).sum() == 0
        assert np.mean(best == np.arange(n)) >= 0.85


def test_advance_bounds_of_short_windows() -> None:
    n = np.arange(0, 11)
    lo, hi = search._advance_bounds(n, 2, 0.8, 1.2)
    assert lo.tolist() == [0, 1, 2, 3, 4, 4, 5, 6, 7, 8, 8]  # ceil(0.8 n)
    assert hi.tolist() == [0, 1, 2, 3, 4, 6, 7, 8, 9, 10, 12]  # floor(1.2 n)
    assert (lo[-1], hi[-1]) == search._advance_range(10, 2, 0.8, 1.2)
    lo, hi = search._advance_bounds(n, 2, 0.0, np.inf)
    assert lo.tolist() == [0] * 11 and hi.tolist() == (2 * n).tolist()
    # An empty range after rounding (v_min = v_max = 1.5, odd n) takes its nearest integers.
    lo, hi = search._advance_bounds(np.array([1, 2, 3]), 2, 1.5, 1.5)
    assert lo.tolist() == [1, 3, 4] and hi.tolist() == [2, 3, 5]


def test_early_acceleration_paths_keep_their_velocity_bound() -> None:
    # Query 3 has 3 steps behind it: with v in [1, 1] its path must advance
    # 3 places over its four real frames, so it can be on place 20 for two of
    # them at most, not sit on it for all four (cost 0).
    D = noise(30, 8, seed=5)
    D[20, :4] = 0.0  # place 20 resembles queries 0-3
    cost = acceleration_search(D, ds=10, v_min=1.0, v_max=1.0)
    want = brute_acceleration(D[:, :4], 10, 2, 1.0, 1.0)
    np.testing.assert_allclose(cost[:, :4], want, rtol=1e-5, atol=1e-6)
    assert cost[20, 3] >= 0.6 * 2 / 4


def test_neutral_difference() -> None:
    D = np.array([[1.0, 2.0, np.inf], [3.0, np.inf, np.inf], [5.0, 2.0, np.inf]])
    np.testing.assert_allclose(search.neutral_difference(D), [3.0, 2.0, 0.0])
    assert search.neutral_difference(np.zeros((0, 4))).tolist() == [0.0] * 4
    E = contrast_enhance(noise(40, 5))
    np.testing.assert_allclose(search.neutral_difference(E), E.mean(axis=0), atol=1e-6)


# ---------------------------------------------------------- tiling/chunking
@pytest.mark.parametrize("chunk", [1, 3, 7])
def test_chunked_equals_unchunked(monkeypatch: pytest.MonkeyPatch, chunk: int) -> None:
    D = noise(53, 41, seed=chunk)
    full = {
        "cv": constant_velocity_search(D),
        "acc": acceleration_search(D, step_penalty=0.1),
        "enh": contrast_enhance(D),
    }
    monkeypatch.setattr(search, "_ROW_TILE", 8)  # also tile the database rows
    for n_jobs in (1, 2):
        np.testing.assert_array_equal(
            constant_velocity_search(D, chunk_queries=chunk, n_jobs=n_jobs), full["cv"]
        )
        np.testing.assert_allclose(
            acceleration_search(D, step_penalty=0.1, chunk_queries=chunk, n_jobs=n_jobs),
            full["acc"], rtol=1e-6,
        )
        np.testing.assert_allclose(
            contrast_enhance(D, chunk_queries=chunk, n_jobs=n_jobs), full["enh"], atol=1e-5
        )


def test_column_depends_only_on_ds_previous_queries() -> None:
    D = noise(30, 40, seed=11)
    full = constant_velocity_search(D)
    part = constant_velocity_search(D[:, 20 - 10 :])
    np.testing.assert_array_equal(part[:, 10:], full[:, 20:])


# ------------------------------------------------------------ enhancement
@pytest.mark.parametrize("window", [2, 5, 10, 11])
def test_contrast_enhance_matches_openseqslam(window: int) -> None:
    D = (noise(37, 6, seed=window) * 50 + 1000).astype(np.float32)
    np.testing.assert_allclose(contrast_enhance(D, window=window), brute_enhance(D, window),
                               atol=2e-4)


@pytest.mark.parametrize("window", [4, 10])
def test_contrast_enhance_floors_the_local_spread_at_the_columns(window: int) -> None:
    rng = np.random.default_rng(window)
    # A column whose differences barely vary near its middle and widely elsewhere.
    D = rng.normal(1.0, 0.2, (40, 3)).astype(np.float32)
    D[15:25, :] = 1.0 + rng.normal(0, 0.001, (10, 3)).astype(np.float32)
    D[20, 1] = 0.99  # a tiny dip where the local spread is tiny
    release, floored = contrast_enhance(D, window=window), contrast_enhance(D, window=window, spread_floor=True)
    # By hand: the release's z-score with max(local sd, column sd) as the divisor.
    col = D.astype(np.float64).std(axis=0, ddof=1)
    expect = np.zeros(D.shape)
    for i in range(len(D)):
        v = D[max(0, i - window // 2): i + window // 2 + 1].astype(np.float64)
        sd = np.maximum(v.std(axis=0, ddof=1), col)
        expect[i] = (D[i] - v.mean(axis=0)) / sd
    np.testing.assert_allclose(floored, expect, atol=2e-4)
    # The noise of the flat stretch no longer outscores real dips; scores only shrink.
    assert release[20, 1] < -1.0 and abs(floored[20, 1]) < 0.2
    assert (np.abs(floored) <= np.abs(release) + 1e-5).all()
    np.testing.assert_array_equal(contrast_enhance(D, window=0, spread_floor=True), D)


def test_contrast_enhance_edge_cases() -> None:
    D = np.ones((12, 3), np.float32)
    D[:, 1] = np.arange(12)
    out = contrast_enhance(D)
    assert (out[:, 0] == 0).all()  # a flat window has no contrast
    assert out.dtype == np.float32 and out.shape == D.shape
    np.testing.assert_array_equal(contrast_enhance(D, window=0), D)
    assert (contrast_enhance(np.ones((1, 4))) == 0).all()  # one row: no spread
    with pytest.raises(ValueError, match="finite"):
        contrast_enhance(np.array([[np.inf, 1.0], [0.0, 1.0]]))


# ------------------------------------------------------- reusable stage on S
def test_sequence_similarity_recovers_diagonal_for_any_scale() -> None:
    rng = np.random.default_rng(0)
    n = 50
    S = rng.normal(0, 1, (n, n))
    S[np.arange(n), np.arange(n)] += 2.0  # weak single-image signal
    single_right = (np.argmax(S, axis=0) == np.arange(n)).mean()
    out = sequence_similarity(S, ds=10)
    assert out.shape == S.shape and out.dtype == np.float32

    def near(sim: np.ndarray, tol: int = 1) -> bool:
        # Lines at v = 0.9 or 1.1 may end one place off (SeqSLAM's tolerance),
        # freer forward paths a little more.
        return bool((np.abs(np.argmax(sim, axis=0)[10:] - np.arange(10, n)) <= tol).all())

    assert near(out)
    assert single_right < 0.9
    # z-scores per query: a positive affine change of each column's scale
    # (cosines, log-likelihoods, ...) changes nothing.
    scaled = S * rng.uniform(0.1, 100, n) + rng.uniform(-1e3, 1e3, n)
    np.testing.assert_allclose(sequence_similarity(scaled, ds=10), out, atol=1e-4)
    # ranks: any increasing transform changes nothing.
    r1 = sequence_similarity(S, ds=10, normalize="rank")
    r2 = sequence_similarity(np.exp(S), ds=10, normalize="rank", mode="acceleration")
    assert near(r1)
    assert near(r2, tol=2)


def test_similarity_to_difference_handles_non_finite() -> None:
    S = np.array([[1.0, -np.inf], [3.0, 2.0], [np.nan, np.inf]])
    D = similarity_to_difference(S, normalize="none")
    np.testing.assert_array_equal(D, -np.array([[1.0, 2.0], [3.0, 2.0], [1.0, 2.0]]))
    assert np.isfinite(similarity_to_difference(S)).all()
    with pytest.raises(ValueError, match="normalize"):
        similarity_to_difference(S, normalize="bogus")  # type: ignore[arg-type]


# ------------------------------------------------------------ uniqueness
def test_uniqueness_margin_by_hand() -> None:
    C = noise(30, 6, seed=12)
    C[[4, 17, 25], [0, 1, 2]] = -1.0
    M = uniqueness_margin(C, window=10)
    for p, t in itertools.product(range(30), range(6)):
        far = [C[q, t] for q in range(30) if abs(q - p) > 5]
        assert M[p, t] == pytest.approx(min(far) - C[p, t], abs=1e-6)
    # The best place keeps the highest value in its column, now a margin.
    np.testing.assert_array_equal(np.argmax(M[:, :3], axis=0), [4, 17, 25])
    assert (M[[4, 17, 25], [0, 1, 2]] > 1.0).all()
    # A route shorter than the window: compared with the column's worst cost.
    short = uniqueness_margin(C[:8], window=20)
    np.testing.assert_allclose(short, C[:8].max(axis=0) - C[:8], atol=1e-6)
    np.testing.assert_allclose(uniqueness_margin(C, window=0)[:, 0],
                               [np.delete(C[:, 0], p).min() - C[p, 0] for p in range(30)],
                               atol=1e-6)


# --------------------------------------------------------------- validation
def test_shapes_and_bad_input() -> None:
    D = noise(10, 4)
    assert constant_velocity_search(np.zeros((10, 0))).shape == (10, 0)
    assert acceleration_search(np.zeros((0, 5))).shape == (0, 5)
    np.testing.assert_array_equal(constant_velocity_search(D, ds=0), D)
    np.testing.assert_array_equal(acceleration_search(D, ds=0), D)
    assert sequence_similarity(D, ds=3, mode="acceleration").shape == D.shape
    with pytest.raises(ValueError, match="2-D"):
        constant_velocity_search(np.zeros(5))
    with pytest.raises(ValueError, match="NaN"):
        acceleration_search(np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="ds"):
        constant_velocity_search(D, ds=-1)
    with pytest.raises(ValueError, match="v_max"):
        constant_velocity_search(D, v_min=1.2, v_max=0.8)
    with pytest.raises(ValueError, match="no path"):
        acceleration_search(D, max_skip=0, v_min=1.5, v_max=2.0)
    with pytest.raises(ValueError, match="step_penalty"):
        acceleration_search(D, step_penalty=-1.0)
    with pytest.raises(ValueError, match="mode"):
        sequence_similarity(D, mode="zigzag")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="chunk_queries"):
        constant_velocity_search(D, chunk_queries=0)
