"""Sequence matching on a difference matrix: SeqSLAM and the Cooc-Map extension.

All functions work on a *difference* matrix ``D`` of shape ``(n_db, n_q)``:
row ``p`` is the ``p``-th database place along the route (the map's place ids
in ascending order, consecutive rows = consecutive places), column ``T`` is
the ``T``-th query in traverse order, and lower values mean "more alike".

The steps are those of SeqSLAM (Milford & Wyeth, "SeqSLAM: Visual route-based
navigation for sunny summer days and stormy winter nights", ICRA 2012) and of
the Cooc-Map paper's Section II-F ("Matching to sequences"):

* :func:`contrast_enhance` -- SeqSLAM's local contrast enhancement of every
  difference against its neighbours along the database axis (OpenSeqSLAM
  ``enhanceContrast.m``);
* :func:`constant_velocity_search` -- SeqSLAM's localised sequence search
  (OpenSeqSLAM ``findSingleMatch.m``): straight lines through ``D`` at a
  range of velocities;
* :func:`acceleration_search` -- Cooc-Map II-F: any *forward-only* path, which
  may repeat a database place (the query decelerates or stops) or skip places
  (it accelerates), found exactly by dynamic programming;
* :func:`sequence_similarity` -- the reusable stage: turns any method's
  similarity ``S`` (higher = better) into a difference, runs one of the two
  searches and returns a sequence-matched similarity of the same shape.

Conventions shared by both searches
-----------------------------------
*Causal window (the paper, not the released code).*  The trajectory that
scores query ``T`` covers the ``ds + 1`` queries ``T - ds, ..., T`` and *ends*
at the scored place: ``cost[p, T]`` is the best trajectory whose position at
query ``T`` is place ``p``.  This is the search space of the SeqSLAM paper,
``S = sum_{t=T-ds}^{T} D_k^t`` with ``k = s + V (ds - T + t)``, which looks
back over the last ``ds`` frames so that a robot can localise online.  OpenSeqSLAM instead centres the
window on the query (frames ``T - ds/2 .. T + ds/2``, using future frames) and
reports the place at the centre; we follow the paper.  Both use ``ds + 1``
frames (OpenSeqSLAM's ``0:ds`` offsets), so ``ds = 10`` matches the release.

*Mean, not sum.*  ``cost`` is the mean of ``D`` along the trajectory, i.e.
the paper's sum divided by the number of frames used.  For full windows this
is a constant factor (same ranking and the same PR curve); it keeps short
windows comparable, see the next point.

*Start of the query traverse.*  Query ``T < ds`` has only ``T + 1`` frames of
history.  Its trajectory uses those frames only (a shorter window) and the
cost is their mean, so scores of early queries are on the scale of the rest;
they are naturally noisier, as a shorter sequence carries less evidence.
Implemented by padding ``D`` with ``ds`` columns of zeros before query 0 and
dividing by ``min(T, ds) + 1``.  A constant-velocity line keeps its velocity
over the shorter window; an acceleration path's bound on its average
velocity applies to its ``T`` real steps (it waits, at no cost, through the
padding), so it cannot meet the bound in frames that do not exist and sit on
one place for all of its real frames.

*Start of the database.*  A trajectory ending near the start of the route
may reach back before place 0 (a constant-velocity line ending on place
``p < ds * v``, or an acceleration path that starts there).  Those frames
have no map place to compare with, so they count with the *neutral* value,
the query's mean difference over the whole map (what a place drawn at random
scores against that query), and the cost is still divided by all the frames of
the window.  A place near the start is thus scored on the scale of the others
but only with the evidence the map holds: a true match there keeps its own
frames (the query traverse normally starts where the map does, and then no
frame of the true trajectory is off the map), and no frame can count twice.
Rows before place 0 are the route extended backwards by places about which
nothing is known.

Earlier versions clamped such lines to place 0 (the trajectory "waited" at
the start of the route), which scored place 0 with the *same* map image for
all ``ds + 1`` frames.  One degenerate first image then captures the search
(issue #12): an almost uniform dark frame patch-normalises to nearly all
zeros, the centre of every normalised image, so its difference to *any*
query (about 0.82 on Nordland) is below that of the true place (0.87), it is
the lowest row of every column after contrast enhancement (on average -1.9
against -1.5 for true matches), and a line that sits on it for 11 frames beat
the true trajectory for 1,344 of 1,772 Nordland queries (R@1 0.82 -> 0.23;
with the neutral value 0.83, and no query takes place 0).  These numbers are
the ``seqslam_nordland`` and ``seqslam_dark_frame`` rows of
``../shared/scorecard`` (the issue's recipe), before and after this change;
``tests/sequence`` holds the recipe as a test.
Anywhere else in the route a single image is one frame of any trajectory
and is diluted by the ``ds`` others; the neutral value makes the start of
the route behave like the rest of it.  (OpenSeqSLAM instead gives lines
that leave the database an infinite cost, which leaves the first ``ds v_min``
places without any score; the neutral value keeps them scored.)  The
acceleration search pads the same way, so its paths may start before
place 0 but, like everywhere else, repeat a place only as often as their
bound on the average velocity allows.

*Locality.*  Column ``T`` of every result depends only on columns
``T - ds .. T`` of ``D`` (the neutral value of a column is computed from that
column alone, so online matching over the last ``ds + 1`` queries agrees).
The searches therefore run over tiles of at most ``chunk_queries`` queries
(plus a ``ds``-column halo) and a bounded number of database rows (plus
the rows a trajectory can reach back over), so memory beyond the output
stays bounded for long routes, and tiles are spread over ``n_jobs`` threads
(numpy releases the GIL in the array operations).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Literal

import cv2
import numpy as np

from topoloc._parallel import n_workers
from topoloc.sequence.confidence import (
    SEQUENCE_CONFIDENCES,
    SequenceConfidence,
    sequence_stretch,
    stretch_margin,
)

Mode = Literal["constant", "acceleration"]
Normalize = Literal["zscore", "rank", "none"]

# Tile of the output computed at once: this many database rows (plus the halo
# of rows a trajectory can reach back over) by ``chunk_queries`` columns.
# 1024 x 128 float32 is 0.5 MiB, small enough to stay in a core's L2 cache
# across the dozens of passes a search makes over it (measured fastest on
# 10,000 x 10,000 among 256-2048 rows x 128-512 queries).
_ROW_TILE = 1024
DEFAULT_CHUNK_QUERIES = 128
#: Most bytes the working arrays of one sequence search may hold at once (1 GiB), all threads
#: together.  The tiles' arrays grow with the square of ``ds`` (constant velocity: a tile of
#: ``(ds v_max + 1024) x (ds + 128)`` differences) or its cube (acceleration: ``ds v_max + 1``
#: planes of ``(ds v_max + 256) x 128`` states), so a sequence length of a million frames would
#: take terabytes: :func:`search_memory_bytes` is checked before anything is allocated, a search
#: whose one tile exceeds the budget is refused, and fewer threads run at once where several
#: tiles would (a tile's result does not depend on the thread that computes it).  The defaults
#: (``ds = 10``) take under 4 MiB a tile.
SEQUENCE_MEMORY_BUDGET = 1 << 30


# --------------------------------------------------------------------------- helpers
def _as_difference_matrix(D: np.ndarray, name: str = "D") -> np.ndarray:
    D = np.asarray(D)
    if D.ndim != 2:
        raise ValueError(f"{name} must be 2-D (n_db, n_queries), got shape {D.shape}")
    if not np.issubdtype(D.dtype, np.number) or np.issubdtype(D.dtype, np.complexfloating):
        raise ValueError(f"{name} must be real-valued, got dtype {D.dtype}")
    if D.dtype != np.float32:
        D = D.astype(np.float32)
    if np.isnan(D).any():
        raise ValueError(f"{name} contains NaN")
    return D


def _check_ds(ds: int) -> int:
    if int(ds) != ds or ds < 0:
        raise ValueError(f"ds must be a non-negative integer, got {ds!r}")
    return int(ds)




def search_memory_bytes(
    ds: int,
    *,
    mode: Mode = "constant",
    n_db: int | None = None,
    n_q: int | None = None,
    v_min: float = 0.8,
    v_max: float = 1.2,
    v_step: float = 0.1,
    max_skip: int = 1,
    chunk_queries: int = DEFAULT_CHUNK_QUERIES,
) -> int:
    """Bytes of the working arrays of one tile of a sequence search, computed without allocating them.

    An upper bound of what :func:`constant_velocity_search` (``mode="constant"``)
    or :func:`acceleration_search` (``"acceleration"``) allocates per tile
    besides their output (the size of ``D``), to be compared with
    :data:`SEQUENCE_MEMORY_BUDGET` before a search starts.

    Parameters
    ----------
    ds : int
        Sequence length.
    mode : {"constant", "acceleration"}
    n_db, n_q : int, optional
        Places and queries of ``D``; unknown (None) counts a full tile.
    v_min, v_max, v_step, max_skip, chunk_queries
        As for the searches.

    Returns
    -------
    int
    """
    ds = max(int(ds), 0)
    w = min(n_q, chunk_queries) if n_q is not None else chunk_queries
    w = max(int(w), 1)
    cols = ds + w
    if mode == "acceleration":
        a_max = ds * (int(max_skip) + 1)
        if math.isfinite(v_max):
            a_max = min(a_max, math.floor(ds * v_max + 1e-9))
        row_tile = max(_ROW_TILE // 4, 4)
        rows = min(n_db, row_tile) if n_db is not None else row_tile
        nb = a_max + rows
        # The padded tile, its +inf extension, and the state planes (E, new and a temporary).
        cells = nb * cols + (nb + a_max) * cols + 3 * (a_max + 1) * nb * w
        return 4 * cells
    # One more than the last velocity's offset: v_min + k v_step may round past v_max.
    halo = math.floor(ds * v_max + 1e-9) + 1 if math.isfinite(v_max) else ds
    rows = min(n_db, _ROW_TILE) if n_db is not None else _ROW_TILE
    n_v = math.floor((v_max - v_min) / v_step + 1e-9) + 1 if v_step > 0 and v_max >= v_min else 1
    # The padded tile, the accumulator and the best so far (float32), and the velocity offsets
    # (int64, twice over while they are made unique).
    return 4 * ((halo + rows) * cols + 2 * rows * w) + 16 * max(n_v, 1) * (ds + 1)


def _memory_checked(tile_bytes: int, ds: int, mode: str) -> int:
    """Threads that fit :data:`SEQUENCE_MEMORY_BUDGET` at ``tile_bytes`` each; refuse a tile that does not fit."""
    if tile_bytes > SEQUENCE_MEMORY_BUDGET:
        raise ValueError(
            f"a {mode} sequence search over ds={ds} frames needs {tile_bytes / 2**30:.1f} GiB of working memory, "
            f"more than its budget of {SEQUENCE_MEMORY_BUDGET / 2**30:.0f} GiB (SEQUENCE_MEMORY_BUDGET)")
    return max(1, SEQUENCE_MEMORY_BUDGET // max(tile_bytes, 1))


def _tiles(
    n_rows: int, n_cols: int, chunk_queries: int, row_tile: int
) -> Iterator[tuple[int, int, int, int]]:
    if chunk_queries < 1:
        raise ValueError(f"chunk_queries must be >= 1, got {chunk_queries}")
    for c0 in range(0, n_cols, chunk_queries):
        for r0 in range(0, n_rows, row_tile):
            yield r0, min(r0 + row_tile, n_rows), c0, min(c0 + chunk_queries, n_cols)


def _run_tiles(
    out: np.ndarray,
    chunk_queries: int,
    n_jobs: int,
    work: Callable[[int, int, int, int], np.ndarray],
    row_tile: int | None = None,
    max_workers: int | None = None,
) -> np.ndarray:
    """Fill ``out`` tile by tile with ``work(r0, r1, c0, c1)``, in parallel (at most ``max_workers`` threads)."""
    tiles = list(_tiles(out.shape[0], out.shape[1], chunk_queries, row_tile or _ROW_TILE))

    def run(t: tuple[int, int, int, int]) -> None:
        r0, r1, c0, c1 = t
        out[r0:r1, c0:c1] = work(r0, r1, c0, c1)

    workers = min(n_workers(n_jobs), len(tiles), max_workers or len(tiles))
    if workers <= 1:
        for t in tiles:
            run(t)
    else:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            # list() re-raises the first exception of any tile.
            list(pool.map(run, tiles))
    return out


def _padded_tile(
    D: np.ndarray, r0: int, r1: int, c0: int, c1: int, halo_rows: int, ds: int,
    neutral: np.ndarray,
) -> np.ndarray:
    """Rows ``r0 - halo_rows .. r1`` and columns ``c0 - ds .. c1`` of ``D``, padded.

    Columns before query 0 are zeros (no frame; see "Start of the query
    traverse" in the module docstring, they are divided out).  Rows before
    place 0 hold ``neutral`` (each query's mean difference over the map; see
    "Start of the database").

    Returns
    -------
    ndarray of float32, shape (halo_rows + r1 - r0, ds + c1 - c0)
    """
    g_r0, g_c0 = r0 - halo_rows, c0 - ds
    rs, cs = max(g_r0, 0), max(g_c0, 0)
    blk = np.zeros((r1 - g_r0, c1 - g_c0), dtype=np.float32)
    blk[rs - g_r0 :, cs - g_c0 :] = D[rs:r1, cs:c1]
    n_above = rs - g_r0
    if n_above:
        blk[:n_above, cs - g_c0 :] = neutral[cs:c1]
    return blk


def neutral_difference(D: np.ndarray) -> np.ndarray:
    """The value of a frame that falls before place 0: each query's mean difference over the map.

    The mean of the finite entries of each column of ``D`` (0 for a column
    with none), i.e. the expected difference of a map place drawn at random:
    such a frame is evidence neither for nor against the trajectory.  For a
    contrast-enhanced ``D`` it is close to 0; for raw differences (or any
    method's normalised scores) it is that query's typical difference.

    Parameters
    ----------
    D : array_like, shape (n_db, n_q)

    Returns
    -------
    ndarray of float32, shape (n_q,)
    """
    return _neutral(_as_difference_matrix(D))


def _neutral(D: np.ndarray) -> np.ndarray:
    """:func:`neutral_difference` of a checked float32 matrix (one pass when all is finite)."""
    if D.shape[0] == 0:
        return np.zeros(D.shape[1], dtype=np.float32)
    mu = D.mean(axis=0, dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(mu))  # columns holding +-inf
    if bad.size:
        X = D[:, bad]
        fin = np.isfinite(X)
        cnt = fin.sum(axis=0)
        tot = np.where(fin, X, 0.0).sum(axis=0, dtype=np.float64)
        mu[bad] = np.where(cnt > 0, tot / np.maximum(cnt, 1), 0.0)
    return mu.astype(np.float32)


def _frames_used(c0: int, c1: int, ds: int) -> np.ndarray:
    """Number of real (non-padding) frames in the window of queries ``c0 .. c1-1``."""
    return (np.minimum(np.arange(c0, c1), ds) + 1).astype(np.float32)


# --------------------------------------------------------------- contrast enhancement
def contrast_enhance(
    D: np.ndarray,
    *,
    window: int = 10,
    spread_floor: bool = False,
    chunk_queries: int = DEFAULT_CHUNK_QUERIES,
    n_jobs: int = -1,
) -> np.ndarray:
    """SeqSLAM's local contrast enhancement along the database axis.

    Each difference is standardised against the differences of the same query
    to the neighbouring database places::

        D_hat[i, T] = (D[i, T] - mean(D[w_i, T])) / std(D[w_i, T]),
        w_i = max(0, i - window // 2) .. min(n_db - 1, i + window // 2)

    exactly as OpenSeqSLAM's ``enhanceContrast.m`` (``R_window = 10``: 5 rows
    either side, 11 in all, clipped at the ends of the route; sample standard
    deviation, ``ddof=1``, as MATLAB's ``std``; the release then subtracts
    the global minimum, a constant that changes no ranking and is left out
    here).  This removes the slowly varying part of the differences (one
    query resembling a whole stretch of the route) so that only places that
    stand out locally score low.  A window without spread (constant
    differences, or a single row) gives 0.  The window sums are OpenCV box
    filters over tiles of the matrix, in float64.

    The window is truncated at the ends of the route (6 rows for the first
    and last place with the defaults) rather than shifted inwards to keep 11
    rows.  This is deliberate: a row's own value is part of its window, so its
    enhanced value is bounded by ``(n - 1) / sqrt(n)`` for a window of ``n``
    rows (2.04 for 6, 3.02 for 11), and a truncated window makes an
    outlying first place (issue #12: a uniform dark frame, nearer to every
    query than its true place) stand out *less*, not more: with the old
    clamped start of the searches, shifted windows took R@1 on Nordland with
    such a first frame from 0.24 to 0.002.  With the neutral start they
    change nothing (R@1 0.829 either way, 0.839 with the dark first frame;
    best place of the costs within 2 places), so the release's rule is kept.
    (Measured with the ``seqslam_nordland`` and ``seqslam_dark_frame`` rows of
    ``../shared/scorecard``, the windows switched by hand.)

    Parameters
    ----------
    D : array_like, shape (n_db, n_q)
        Difference matrix, lower = more alike.
    window : int
        ``R_window``; ``0`` returns ``D`` unchanged (as float32).
    spread_floor : bool
        Not in the release: divide by ``max(std(D[w_i, T]), std(D[:, T]))``,
        the local spread floored at the query's spread over the whole
        database.  Eleven rows give a noisy spread; where it comes out small
        the release turns small local differences into large scores, and on
        a route whose differences barely vary (Gardens Point) that noise
        decides the best place.  The floor only shrinks scores, so the bound
        above still holds.  Measured in ``docs/results/seqslam.md``
        (``benchmarks/bench_sequence.py``, rows ``enhance_floor``).
    chunk_queries : int
        Queries per tile (bounds the float64 work arrays; results do not
        depend on it).
    n_jobs : int
        Threads (``-1``: all cores).

    Returns
    -------
    ndarray of float32, shape (n_db, n_q)
    """
    D = _as_difference_matrix(D)
    if int(window) != window or window < 0:
        raise ValueError(f"window must be a non-negative integer, got {window!r}")
    if window == 0:
        return D.copy()
    n_db = D.shape[0]
    half = int(window) // 2
    if not np.isfinite(D).all():
        raise ValueError("D must be finite for contrast enhancement")
    # The whole column's sample spread (float64), the floor of every window's.
    col_sd = D.std(axis=0, ddof=1, dtype=np.float64) if spread_floor and n_db > 1 else None

    def work(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        # Rows g0..g1 are every row the windows of rows r0..r1 touch.
        g0, g1 = max(r0 - half, 0), min(r1 + half, n_db)
        # Shifting each column by a constant (its mean over the tile) keeps
        # the one-pass variance E[x^2] - E[x]^2 accurate when differences
        # have a large offset; sums are accumulated in float64.
        X = D[g0:g1, c0:c1] - D[g0:g1, c0:c1].mean(axis=0, dtype=np.float64).astype(np.float32)
        # Window sums along the database axis with OpenCV's box filters
        # (running sums, SIMD).  Zero padding outside the tile only reaches
        # rows within `half` of its edges: those are either outside r0..r1
        # (the halo) or at the ends of the route, where the window is
        # clipped, which is what zeros and the counts below implement.
        ksize = (1, 2 * half + 1)
        s1 = cv2.boxFilter(X, cv2.CV_64F, ksize, normalize=False, borderType=cv2.BORDER_CONSTANT)
        s2 = cv2.sqrBoxFilter(X, cv2.CV_64F, ksize, normalize=False,
                              borderType=cv2.BORDER_CONSTANT)
        a, b = r0 - g0, r1 - g0
        s1, s2, x = s1[a:b], s2[a:b], X[a:b]
        rows = np.arange(r0, r1)
        cnt = (np.minimum(rows + half, n_db - 1) - np.maximum(rows - half, 0) + 1)
        cntf = cnt.astype(np.float64)[:, None]
        mean = s1 / cntf
        ss = s2 - s1 * mean
        # Rounding leaves a tiny spread on constant windows (or a negative
        # one); treat anything below 1e-9 of the sum of squares as none.
        flat = (cntf < 2.0) | (ss <= 1e-9 * s2)
        np.divide(ss, np.maximum(cntf - 1.0, 1.0), out=ss)
        ss[flat] = 1.0
        np.sqrt(ss, out=ss)
        if col_sd is not None:
            np.maximum(ss, col_sd[None, c0:c1], out=ss)
        res = (x - mean) / ss
        res[flat] = 0.0
        return res

    out = np.empty(D.shape, dtype=np.float32)
    return _run_tiles(out, chunk_queries, n_jobs, work)


# ---------------------------------------------------------- constant-velocity search
def _check_velocities(v_min: float, v_max: float, v_step: float) -> None:
    if not (math.isfinite(v_min) and math.isfinite(v_max) and math.isfinite(v_step)):
        raise ValueError("velocities must be finite")
    if v_min < 0:
        raise ValueError(f"v_min must be >= 0 (trajectories only move forward), got {v_min}")
    if v_max < v_min:
        raise ValueError(f"v_max ({v_max}) must be >= v_min ({v_min})")
    if v_step <= 0:
        raise ValueError(f"v_step must be > 0, got {v_step}")


def velocity_offsets(
    ds: int, v_min: float = 0.8, v_max: float = 1.2, v_step: float = 0.1
) -> np.ndarray:
    """Place offsets of SeqSLAM's straight trajectories, counted back from the end.

    OpenSeqSLAM places the ``k``-th frame of a trajectory starting at place
    ``s`` with velocity ``v`` on place ``s + floor(k v)``, ``k = 0..ds``.  A
    trajectory that *ends* on place ``p`` (at frame ``k = ds``) therefore
    visits ``p - (floor(ds v) - floor(k v))`` at frame ``k``; this returns
    those back offsets.

    Velocities are ``v_min, v_min + v_step, ..., v_max`` (OpenSeqSLAM
    defaults 0.8, 0.1, 1.2; its code steps by ``1 / ds``, which equals
    ``v_step`` for the defaults).  Velocities that give identical offsets
    (possible for short ``ds``) are kept once.

    Returns
    -------
    ndarray of int64, shape (n_trajectories, ds + 1)
        ``[j, k]``: how many places before the end place trajectory ``j`` is
        at frame ``k`` (query ``T - ds + k``); column ``ds`` is all zeros.
    """
    ds = _check_ds(ds)
    _check_velocities(v_min, v_max, v_step)
    n_v = math.floor((v_max - v_min) / v_step + 1e-9) + 1
    v = v_min + v_step * np.arange(n_v)
    k = np.arange(ds + 1)
    # The small epsilon keeps e.g. 10 * 1.1 = 10.999999999999998 on 11.
    pos = np.floor(k[None, :] * v[:, None] + 1e-9).astype(np.int64)
    back = pos[:, -1:] - pos
    return np.unique(back, axis=0)


def constant_velocity_search(
    D: np.ndarray,
    *,
    ds: int = 10,
    v_min: float = 0.8,
    v_max: float = 1.2,
    v_step: float = 0.1,
    chunk_queries: int = DEFAULT_CHUNK_QUERIES,
    n_jobs: int = -1,
) -> np.ndarray:
    """SeqSLAM's trajectory search at constant velocity.

    For every query ``T`` and place ``p``, the cost of the best straight
    trajectory over queries ``T - ds .. T`` that ends on ``p``::

        cost[p, T] = min_v  mean_{k=0..ds}  D[p - floor(ds v) + floor(k v), T - ds + k]

    with the conventions of the module docstring (causal window, shorter
    window for the first ``ds`` queries, frames before place 0 counted with
    the query's mean difference over the map, :func:`neutral_difference`).  Vectorised
    over places and queries: one array addition per trajectory frame, no loop
    over places.

    Parameters
    ----------
    D : array_like, shape (n_db, n_q)
        Difference matrix, lower = more alike (normally contrast-enhanced).
    ds : int
        Sequence length ``d_s``: the trajectory spans ``ds + 1`` queries.
        ``0`` returns ``D``.
    v_min, v_max, v_step : float
        Range of velocities in places per query (SeqSLAM ``V_min``,
        ``V_max``, ``V_step``).
    chunk_queries : int
        Queries per tile (bounds memory; results do not depend on it).
    n_jobs : int
        Threads (``-1``: all cores).

    Returns
    -------
    ndarray of float32, shape (n_db, n_q)
        Mean difference along the best trajectory; lower = better match.
    """
    D = _as_difference_matrix(D)
    ds = _check_ds(ds)
    _check_velocities(v_min, v_max, v_step)
    # Before the offsets and tiles are allocated (both grow with ds).
    max_workers = _memory_checked(search_memory_bytes(
        ds, mode="constant", n_db=D.shape[0], n_q=D.shape[1], v_min=v_min, v_max=v_max, v_step=v_step,
        chunk_queries=chunk_queries), ds, "constant-velocity")
    offsets = velocity_offsets(ds, v_min, v_max, v_step)
    halo = int(offsets.max()) if offsets.size else 0
    neutral = _neutral(D)

    def work(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        blk = _padded_tile(D, r0, r1, c0, c1, halo, ds, neutral)
        nr, w = r1 - r0, c1 - c0
        best: np.ndarray | None = None
        acc = np.empty((nr, w), dtype=np.float32)
        for back in offsets:
            b0 = halo - int(back[0])
            np.copyto(acc, blk[b0 : b0 + nr, 0:w])
            for k in range(1, ds + 1):
                b = halo - int(back[k])
                acc += blk[b : b + nr, k : k + w]
            if best is None:
                best = acc.copy()
            else:
                np.minimum(best, acc, out=best)
        assert best is not None
        best /= _frames_used(c0, c1, ds)
        return best

    out = np.empty(D.shape, dtype=np.float32)
    return _run_tiles(out, chunk_queries, n_jobs, work, max_workers=max_workers)


# --------------------------------------------------------- acceleration (Cooc-Map)
def _advance_range(ds: int, max_step: int, v_min: float, v_max: float) -> tuple[int, int]:
    """Smallest and largest total advance (places) of an acceleration path."""
    if not (math.isfinite(v_min) and v_min >= 0):
        raise ValueError(f"v_min must be finite and >= 0, got {v_min}")
    if math.isnan(v_max) or v_max < v_min:
        raise ValueError(f"v_max ({v_max}) must be >= v_min ({v_min})")
    a_max = ds * max_step
    if math.isfinite(v_max):
        a_max = min(a_max, math.floor(ds * v_max + 1e-9))
    a_min = math.ceil(ds * v_min - 1e-9)
    if a_min > a_max:
        raise ValueError(
            f"no path of {ds} steps of at most {max_step} places averages "
            f"{v_min}..{v_max} places per query"
        )
    return a_min, a_max


def _advance_bounds(
    n_steps: np.ndarray, max_step: int, v_min: float, v_max: float
) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest total advance of a path of ``n_steps`` steps, per query.

    ``ceil(n v_min) .. min(n max_step, floor(n v_max))``, the rule of
    :func:`_advance_range` for a window of ``n`` real steps (the first queries
    of a traverse have fewer than ``ds``).  Where rounding leaves that empty
    (``v_max - v_min`` under ``1 / n``), the integers nearest to it,
    ``floor(n v_min) .. ceil(n v_max)``, clipped to ``n max_step``.
    """
    n = n_steps.astype(np.float64)
    cap = n_steps * max_step
    lo = np.ceil(n * v_min - 1e-9).astype(np.int64)
    hi = cap if not math.isfinite(v_max) else np.minimum(cap, np.floor(n * v_max + 1e-9).astype(np.int64))
    empty = lo > hi
    if empty.any():
        lo = np.where(empty, np.floor(n * v_min + 1e-9).astype(np.int64), lo)
        up = cap if not math.isfinite(v_max) else np.minimum(cap, np.ceil(n * v_max - 1e-9).astype(np.int64))
        hi = np.where(empty, up, hi)
    return np.minimum(lo, cap), hi


def acceleration_search(
    D: np.ndarray,
    *,
    ds: int = 10,
    max_skip: int = 1,
    v_min: float = 0.8,
    v_max: float = 1.2,
    step_penalty: float = 0.0,
    chunk_queries: int = DEFAULT_CHUNK_QUERIES,
    n_jobs: int = -1,
) -> np.ndarray:
    """Forward-only paths that may repeat or skip places (Cooc-Map II-F).

    Cooc-Map drops SeqSLAM's constant-velocity assumption: "we consider all
    forward-moving paths through the matrix, such that the database
    locations may be skipped or repeated if the query image sequence is
    accelerating or decelerating ... no other constraints on the path shape
    other than that it must not reverse".  Between consecutive queries the
    path advances by ``0`` (repeat: the query slowed down or stopped), ``1``
    or up to ``1 + max_skip`` places (skip: it sped up).

    "Other than allowing for non-zero acceleration, the same parameters as in
    SeqSLAM were used": the path's *average* velocity over the window, its
    total advance ``a`` divided by ``ds``, must lie in ``[v_min, v_max]``
    like SeqSLAM's lines, while its shape is free.  This is needed in
    practice: with no bound, a path can sit on one "hub" place that resembles
    every query (a blank or generic image stands out after contrast
    enhancement) and beat the true sequence; on Nordland summer -> winter
    that takes R@1 from 0.8 to under 0.01 (``topoloc evaluate --method seqslam
    --param search=acceleration --param v_min=0 --param v_max=inf`` on
    nordland_64x32 summer -> winter, tolerance 0:2).  ``v_min=0, v_max=inf``
    gives the paper's unconstrained paths.

    Flexibility has a price where speeds do match: every wrong place can
    also bend its path towards low differences.  On Nordland (both traverses
    at the same speed) R@1 is 0.51 with these bounds against 0.82 for
    straight lines, 0.73 with ``step_penalty=0.5`` (docs/results/seqslam.md,
    written by ``benchmarks/bench_sequence.py``).  ``step_penalty`` (0, as in
    the paper) adds that much cost per place of deviation from a unit step
    (a repeat costs ``step_penalty``, skipping ``j`` places ``j *
    step_penalty``), trading acceleration tolerance for discrimination.

    Dynamic programme over (start place ``s``, advance so far ``a``) for the
    window ``t_k = T - ds + k``, ``k = 0..ds``::

        E_0[0, s] = D[s, t_0],            E_0[a > 0, s] = inf
        E_k[a, s] = D[s + a, t_k]
                    + min_{j = 0..min(a, 1+max_skip)} (E_{k-1}[a - j, s] + step_penalty |j - 1|)
        cost[p, T] = min_{a_min <= a <= a_max} E_ds[a, p - a] / (ds + 1)

    with ``a_min = ceil(ds v_min)``, ``a_max = min(ds (1+max_skip),
    floor(ds v_max))``.  Indexing states by their start place makes every
    transition a plain elementwise minimum (no shifts), vectorised over
    (advance, place, query).  The paper builds the path greedily, picking the
    lowest dissimilarity at each step, and notes this "almost always provides
    the global optimum"; the programme computes that optimum exactly.
    Conventions at the start of the route and of the traverse are those of
    the module docstring (a path may start before place 0, where every frame
    counts with the query's mean difference over the map; early queries use
    the frames they have).  For a query ``T < ds`` the path has ``T`` steps
    and the bound applies to them, ``ceil(T v_min) <= a <= floor(T v_max)``:
    it may not meet its bound in frames before query 0 (which would let it
    repeat one place for all of its real frames, so that a single image
    resembling every query captured the first ``ds`` queries).

    Parameters
    ----------
    D : array_like, shape (n_db, n_q)
        Difference matrix, lower = more alike (normally contrast-enhanced).
    ds : int
        Sequence length: the path spans ``ds + 1`` queries (as SeqSLAM's).
    max_skip : int
        Most places skipped between two consecutive queries; ``1`` allows
        steps of 0, 1 and 2 places.
    v_min, v_max : float
        Bounds of the average velocity over the window (SeqSLAM's 0.8 and
        1.2 by default; ``0`` and ``inf`` for no bound).
    step_penalty : float
        Cost per place of deviation from a unit step, >= 0 (in units of
        ``D``; 0 = the paper's free path shape).
    chunk_queries : int
        Queries per tile (bounds memory; results do not depend on it).
    n_jobs : int
        Threads (``-1``: all cores).

    Returns
    -------
    ndarray of float32, shape (n_db, n_q)
        Mean difference along the best forward path ending at each place;
        lower = better match.

    Notes
    -----
    Work is at most ``ds (max_skip + 2) (a_max + 1)`` passes over ``D``
    (unreachable advances are skipped), about 10 times the constant-velocity
    search for the defaults.
    """
    D = _as_difference_matrix(D)
    ds = _check_ds(ds)
    if int(max_skip) != max_skip or max_skip < 0:
        raise ValueError(f"max_skip must be a non-negative integer, got {max_skip!r}")
    max_step = int(max_skip) + 1
    a_min, a_max = _advance_range(ds, max_step, float(v_min), float(v_max))
    lam = float(step_penalty)
    if not (math.isfinite(lam) and lam >= 0):
        raise ValueError(f"step_penalty must be finite and >= 0, got {step_penalty}")
    halo = a_max
    n_a = a_max + 1
    max_workers = _memory_checked(search_memory_bytes(
        ds, mode="acceleration", n_db=D.shape[0], n_q=D.shape[1], v_min=v_min, v_max=v_max,
        max_skip=int(max_skip), chunk_queries=chunk_queries), ds, "acceleration")
    neutral = _neutral(D)

    def work(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        blk = _padded_tile(D, r0, r1, c0, c1, halo, ds, neutral)
        nb, w = blk.shape[0], c1 - c0
        # V[a, s, c] = blk[s + a, c]: the difference at the place a path
        # that started on block row s reaches after advancing a places.
        # Rows past the tile are +inf: such paths end outside the output.
        padded = np.vstack([blk, np.full((a_max, blk.shape[1]), np.inf, np.float32)])
        st = padded.strides
        V = np.lib.stride_tricks.as_strided(
            padded, shape=(n_a, nb, blk.shape[1]), strides=(st[0], st[0], st[1]), writeable=False
        )
        E = np.full((n_a, nb, w), np.inf, dtype=np.float32)
        E[0] = V[0, :, 0:w]
        new = np.full_like(E, np.inf)
        early = c0 < ds  # the tile holds queries with fewer than ds steps behind them
        for k in range(1, ds + 1):
            # Only advances reachable after k steps that can still reach
            # a_min in the remaining ones: about 40 % less work for the
            # defaults.  Both bounds only grow with k, so every state read
            # below was written at step k - 1 or is still +inf.  (Early
            # queries have smaller bounds: no pruning from below there.)
            lo = 0 if early else max(0, a_min - (ds - k) * max_step)
            hi = min(k * max_step, a_max)
            out = new[lo : hi + 1]
            if lam:
                np.add(E[lo : hi + 1], np.float32(lam), out=out)  # repeat a place
            else:
                np.copyto(out, E[lo : hi + 1])
            for j in range(1, max_step + 1):
                a0 = max(lo, j)
                if a0 > hi:
                    continue
                prev = E[a0 - j : hi + 1 - j]
                if lam and j > 1:
                    prev = prev + np.float32(lam * (j - 1))  # skip j - 1 places
                np.minimum(new[a0 : hi + 1], prev, out=new[a0 : hi + 1])
            out += V[lo : hi + 1, :, k : k + w]
            # Queries whose frame k is query 0 or before it: the path waits
            # on its start place (no step, no penalty), so its steps are
            # those between real frames only.
            jf = min(w, max(0, ds - k - c0 + 1))
            if jf:
                np.add(E[lo : hi + 1, :, :jf], V[lo : hi + 1, :, k : k + jf],
                       out=new[lo : hi + 1, :, :jf])
            E, new = new, E
        res = np.full((r1 - r0, w), np.inf, dtype=np.float32)
        if not early:
            for a in range(a_min, a_max + 1):
                # Output row p (block row halo + p - r0) started on row p - a.
                np.minimum(res, E[a, halo - a : halo - a + r1 - r0], out=res)
        else:
            steps = np.minimum(np.arange(c0, c1), ds)
            a_lo, a_hi = _advance_bounds(steps, max_step, float(v_min), float(v_max))
            for a in range(0, a_max + 1):
                ok = (a_lo <= a) & (a <= a_hi)
                if ok.any():
                    cand = np.where(ok, E[a, halo - a : halo - a + r1 - r0], np.float32(np.inf))
                    np.minimum(res, cand, out=res)
        res /= _frames_used(c0, c1, ds)
        return res

    out = np.empty(D.shape, dtype=np.float32)
    # Row tiles a quarter as tall: the state holds a_max + 1 planes per tile.
    return _run_tiles(out, chunk_queries, n_jobs, work, row_tile=max(_ROW_TILE // 4, 4), max_workers=max_workers)


# ------------------------------------------------------------- uniqueness margin
def uniqueness_margin(cost: np.ndarray, *, window: int = 10) -> np.ndarray:
    """How much better each place is than the best place outside its window.

    OpenSeqSLAM rates the best match of a query by the ratio of its
    trajectory cost to the lowest cost more than ``Rwindow / 2`` places away
    (``findSingleMatch.m``, ``Rwindow = 10``): a match is trusted when no
    other stretch of the route comes close.  As a similarity for every cell::

        M[p, T] = min_{|p' - p| > window // 2} cost[p', T] - cost[p, T]

    (a difference, not a ratio, because contrast-enhanced costs are
    negative).  The best place of each query keeps the highest value in its
    column and that value is the release's margin, so the PR curve
    thresholds on uniqueness instead of raw cost.  Places whose window
    covers the whole route are compared with the column's highest cost.

    Parameters
    ----------
    cost : array_like, shape (n_db, n_q)
        Sequence costs, lower = better (e.g. :func:`constant_velocity_search`).
    window : int
        ``Rwindow``; must be >= 0.

    Returns
    -------
    ndarray of float32, shape (n_db, n_q)
        Higher = more unique match.
    """
    C = _as_difference_matrix(cost, "cost")
    if int(window) != window or window < 0:
        raise ValueError(f"window must be a non-negative integer, got {window!r}")
    n = C.shape[0]
    g = int(window) // 2 + 1  # nearest row outside the window
    out = np.empty_like(C)
    for c0 in range(0, C.shape[1], DEFAULT_CHUNK_QUERIES):
        X = C[:, c0 : c0 + DEFAULT_CHUNK_QUERIES]
        far = np.full(X.shape, np.inf, dtype=np.float32)
        if g < n:
            pre = np.minimum.accumulate(X, axis=0)  # min over rows 0..i
            suf = np.minimum.accumulate(X[::-1], axis=0)[::-1]  # min over rows i..n-1
            np.minimum(far[g:], pre[: n - g], out=far[g:])
            np.minimum(far[: n - g], suf[g:], out=far[: n - g])
        far = np.where(np.isinf(far), X.max(axis=0) if n else 0.0, far)
        out[:, c0 : c0 + DEFAULT_CHUNK_QUERIES] = far - X
    return out


# ------------------------------------------------------------------ reusable stage
def similarity_to_difference(S: np.ndarray, *, normalize: Normalize = "zscore") -> np.ndarray:
    """Turn a similarity matrix (higher = better) into a difference matrix.

    Methods score on unrelated scales (cosine similarities in [0, 1],
    log-likelihoods in the hundreds, negated distances), so each query column
    is normalised on its own before differences of different queries are
    summed along a trajectory:

    * ``"zscore"`` (default): ``D = (mean(S[:, T]) - S[:, T]) / std(S[:, T])``;
      invariant to any positive affine change of a column's scale.
    * ``"rank"``: ``D`` = rank of the place in its column divided by
      ``n_db - 1`` (0 = best, 1 = worst, ties averaged); invariant to any
      monotone change, robust to heavy-tailed scores where one frame's
      extreme value would otherwise dominate a trajectory.
    * ``"none"``: ``D = -S``.

    Non-finite similarities (``-inf`` log-likelihoods, NaN) count as the worst
    finite value of their column, ``+inf`` as the best.

    Parameters
    ----------
    S : array_like, shape (n_db, n_q)

    Returns
    -------
    ndarray of float32, shape (n_db, n_q)
    """
    S = np.asarray(S, dtype=np.float64)
    if S.ndim != 2:
        raise ValueError(f"S must be 2-D (places, queries), got shape {S.shape}")
    if not np.isfinite(S).all():
        fin = np.isfinite(S)
        lo = np.where(fin, S, np.inf).min(axis=0)
        hi = np.where(fin, S, -np.inf).max(axis=0)
        lo = np.where(np.isfinite(lo), lo, 0.0)
        hi = np.where(np.isfinite(hi), hi, 0.0)
        S = np.where(np.isposinf(S), hi, np.where(fin, S, lo))
    if normalize == "zscore":
        mu = S.mean(axis=0) if S.shape[0] else np.zeros(S.shape[1])
        sd = S.std(axis=0) if S.shape[0] else np.ones(S.shape[1])
        sd = np.where(sd > 0, sd, 1.0)
        return ((mu - S) / sd).astype(np.float32)
    if normalize == "rank":
        from scipy.stats import rankdata

        r = rankdata(-S, axis=0, method="average") - 1.0
        return (r / max(S.shape[0] - 1, 1)).astype(np.float32)
    if normalize == "none":
        return (-S).astype(np.float32)
    raise ValueError(f"normalize must be 'zscore', 'rank' or 'none', got {normalize!r}")


def sequence_similarity(
    S: np.ndarray,
    *,
    ds: int = 10,
    mode: Mode = "constant",
    normalize: Normalize = "zscore",
    enhance_window: int = 0,
    v_min: float = 0.8,
    v_max: float = 1.2,
    v_step: float = 0.1,
    max_skip: int = 1,
    step_penalty: float = 0.0,
    chunk_queries: int = DEFAULT_CHUNK_QUERIES,
    n_jobs: int = -1,
    confidence: SequenceConfidence = "margin",
) -> np.ndarray:
    """Sequence-matched similarity for any method's ``S`` (``evaluate --sequence``).

    ``S`` is converted to a difference with :func:`similarity_to_difference`
    (per-column normalisation), optionally contrast-enhanced
    (:func:`contrast_enhance`, SeqSLAM's step, off by default because other
    methods' scores are not raw image differences), then searched with the
    constant-velocity trajectories of SeqSLAM or the forward-only paths of
    Cooc-Map II-F.  The result is ``-cost`` (higher = better, the negated mean
    normalised difference along the best trajectory ending at each place),
    shifted per query by the best path outside the best path's stretch
    (``confidence="margin"``, :mod:`topoloc.sequence.confidence`) so that the
    best scores of different queries threshold on one scale.

    Parameters
    ----------
    S : array_like, shape (n_db, n_q)
        Similarities, higher = more similar; rows = map places in route order,
        columns = queries in traverse order.
    ds : int
        Sequence length: the current query and the ``ds`` before it
        (``ds + 1`` frames, as SeqSLAM's ``d_s``); ``0`` returns the
        normalised single-image similarity.
    mode : {"constant", "acceleration"}
        :func:`constant_velocity_search` or :func:`acceleration_search`.
    normalize : {"zscore", "rank", "none"}
        Per-query normalisation of ``S``.
    enhance_window : int
        SeqSLAM contrast-enhancement window; ``0`` = none.
    v_min, v_max, v_step : float
        Velocities of the constant-velocity search; ``v_min`` and ``v_max``
        also bound the average velocity of acceleration paths.
    max_skip, step_penalty
        Of the acceleration search.
    chunk_queries, n_jobs : int
        Tiling and threads, as in the searches.
    confidence : {"margin", "raw"}
        ``"margin"`` (default): each column minus its best value more than
        :func:`~topoloc.sequence.confidence.sequence_stretch` places from its
        best place (the best score is the margin, the order of the column is
        kept), times ``k / (ds + 1)`` for a query with ``k <= ds + 1`` frames
        up to it (the first ``ds`` queries: a short window is not evidence);
        ``"raw"``: the negated cost.

    Returns
    -------
    ndarray of float32, shape (n_db, n_q)
    """
    if confidence not in SEQUENCE_CONFIDENCES:
        raise ValueError(f"confidence must be one of {', '.join(SEQUENCE_CONFIDENCES)}, got {confidence!r}")
    D = similarity_to_difference(S, normalize=normalize)
    if enhance_window:
        D = contrast_enhance(
            D, window=enhance_window, chunk_queries=chunk_queries, n_jobs=n_jobs
        )
    cost = sequence_search(
        D, ds=ds, mode=mode, v_min=v_min, v_max=v_max, v_step=v_step, max_skip=max_skip,
        step_penalty=step_penalty, chunk_queries=chunk_queries, n_jobs=n_jobs,
    )
    np.negative(cost, out=cost)
    if confidence == "raw":
        return cost
    stretch = sequence_stretch(ds, v_max)
    if mode == "acceleration":  # a path advances at most max_skip + 1 places a frame
        stretch = min(stretch, ds * (int(max_skip) + 1))
    margin = stretch_margin(cost, stretch=stretch)
    # A query with fewer than ds frames behind it (the start of a stream) has a path of fewer real
    # frames, whose mean difference is as noisy as that of fewer frames: its margin counts the missing
    # frames as giving no evidence, (k / (ds + 1)) x margin for k real frames, so that no answer is
    # confident merely because its window is short (issue 40; online and batch scale alike).
    if ds:
        margin *= (_frames_used(0, margin.shape[1], ds) / np.float32(ds + 1))[None, :]
    return margin


def sequence_search(
    D: np.ndarray,
    *,
    ds: int = 10,
    mode: Mode = "constant",
    v_min: float = 0.8,
    v_max: float = 1.2,
    v_step: float = 0.1,
    max_skip: int = 1,
    step_penalty: float = 0.0,
    chunk_queries: int = DEFAULT_CHUNK_QUERIES,
    n_jobs: int = -1,
) -> np.ndarray:
    """Dispatch to :func:`constant_velocity_search` or :func:`acceleration_search`.

    Returns
    -------
    ndarray of float32, shape (n_db, n_q)
        Cost, lower = better.
    """
    if mode == "constant":
        return constant_velocity_search(
            D, ds=ds, v_min=v_min, v_max=v_max, v_step=v_step,
            chunk_queries=chunk_queries, n_jobs=n_jobs,
        )
    if mode == "acceleration":
        return acceleration_search(
            D, ds=ds, max_skip=max_skip, v_min=v_min, v_max=v_max,
            step_penalty=step_penalty, chunk_queries=chunk_queries, n_jobs=n_jobs,
        )
    raise ValueError(f"mode must be 'constant' or 'acceleration', got {mode!r}")
