"""Location models: word-co-occurrence matrices M_i (Cooc-Map, Sec. II-B and II-E).

Johns & Yang (ICRA 2013), Sec. II-B: location ``y_i`` is a word-co-occurrence
matrix ``M_i`` whose element ``(V, W)`` is the *set* of spatial words observed
between a feature of visual word ``V`` and one of ``W`` in a training image of
the location; further tours add their pairs; only words seen at the location
are stored.  Sec. II-E: with tours ordered by time, the features of adjacent
tours are merged into "virtual" images whose pair statistics are added to M.

What M is, exactly
------------------
With ``pairs(G) = {(word(a), word(b), s(a -> b)) : a, b in G, a != b}`` for a
set of features ``G`` (``s`` from :mod:`topoloc.coocmap.spatial`):

* without interpolation, ``M_i = U_t pairs(X_i^t)`` over the tours ``t``;
* with interpolation (Sec. II-E) and tours ``t_0 < ... < t_{T-1}`` in time,
  ``M_i = U_k pairs(X_i^{t_k} U X_i^{t_{k+1}})``, which contains every single
  tour's pairs plus the cross-tour pairs of *adjacent* tours only ("the tour
  at 4pm is merged with the tour at 2pm ... and also with the tour at 6pm").
  A feature that "occurs in both" tours (same word at the same position) is
  one feature of the virtual image.  With one tour, ``M_i = pairs(X_i^t0)``.

Representation (why it is compact)
----------------------------------
Storing M explicitly costs one key per observed pair: ~n^2/2 keys for an
image of n features (~125,000 for n = 500, ~1 MB per tour per location as
int64).  We store instead the *generators* of M, which determine it exactly:
per location the set of distinct features ``(word, x, y)`` over all tours,
each with a bit mask of the tours it was seen in.  A feature seen in several
tours is stored once; no image, descriptor or per-tour feature list is kept.
Then ``(V, W, S) in M_i`` iff two distinct stored features ``a, b`` with words
``V, W`` and ``s(a -> b) = S`` share a *group*: a tour (no interpolation) or
a pair of adjacent tours (interpolation, group mask ``m | m >> 1``).  The
cost is ~12 bytes per distinct feature (see :attr:`CoocModel.nbytes`); the
explicit key set is available through :meth:`CoocModel.pair_keys` for
inspection and tests.  Positions are 16-bit normalised image coordinates.

Arrays (N distinct features over all locations, sorted by location, word, y, x)
-----------------------------------------------------------------------------
``loc_ptr`` (L+1,) int64: features of location ``i`` are ``loc_ptr[i]:loc_ptr[i+1]``;
``word`` (N,) uint16/int32; ``xy`` (N, 2) uint16; ``tours`` (N,) uint8..uint64
tour bit mask; ``loc`` (N,) uint16/int32 the location of each feature;
inverted files: ``word_ptr`` (n_words+1,) int64 with ``by_word`` (N,) int32
(features of each word, by location) and ``wloc_ptr``/``wloc`` (word ->
locations containing it, Sec. II-C).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from typing import Any, ClassVar

import numpy as np

from topoloc._params import Configurable, Constraint, Interval
from topoloc.coocmap.spatial import n_spatial_words, spatial_words
from topoloc.errors import TopolocError
from topoloc.io.scratch import CHUNK_BYTES, chunk_rows, empty, release

MAX_TOURS = 64
#: The arrays :meth:`CoocModel._index` derives from the features (the inverted files of Sec. II-C).
INDEX_ARRAYS = ("loc_ptr", "by_word", "word_ptr", "wloc", "wloc_ptr")

#: One image's observation: (location row, word ids (n,), normalised xy (n, 2) uint16).
Observation = tuple[int, np.ndarray, np.ndarray]


def _mask_dtype(n_tours: int) -> np.dtype:
    for dt in (np.uint8, np.uint16, np.uint32, np.uint64):
        if n_tours <= 8 * np.dtype(dt).itemsize:
            return np.dtype(dt)
    raise TopolocError(f"coocmap: at most {MAX_TOURS} tours are supported, got {n_tours}")


def _small_uint(n: int) -> np.dtype:
    return np.dtype(np.uint16) if n <= 65536 else np.dtype(np.int32)


def _ranges(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Concatenation of ``arange(s, s + n)`` for each start ``s`` and length ``n``."""
    lengths = np.asarray(lengths, dtype=np.int64)
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    offsets = np.cumsum(lengths) - lengths
    return np.repeat(np.asarray(starts, np.int64) - offsets, lengths) + np.arange(total, dtype=np.int64)


class CoocModel(Configurable):
    """All locations' word-co-occurrence models plus the inverted files.

    Build with :meth:`build`, extend with :meth:`add_tour`; a fitted Cooc-Map
    keeps it in its map file (:class:`~topoloc.maps.Map`, the arrays through
    :mod:`topoloc.io.state`).  See the module docstring for the exact
    definition of ``M_i`` and the representation.

    Parameters
    ----------
    n_locations, n_words : int
        Locations (rows of ``S``) and visual words.
    grid_x, grid_y : int
        Spatial grid (Sec. III-B: 12 x 8, i.e. 384 spatial words).
    interpolate : bool
        Whether ``M`` includes the virtual images of adjacent tours (Sec. II-E).
    position_bits : int
        Positions are kept to this many bits per axis (16: as given; 6: a
        64 x 64 lattice, ~10 px on a 640 px image).  Coarser positions make a
        feature re-observed by another tour with a few pixels of jitter "the
        same feature" (stored once, Sec. II-E's "occurs in both") at the cost
        of that much spatial precision; queries are quantised alike.
    """

    #: Checked, after conversion to int, by :meth:`validate_params` in ``__init__``.
    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {
        "n_locations": Interval(int, 0), "n_words": Interval(int, 1), "grid_x": Interval(int, 1),
        "grid_y": Interval(int, 1), "position_bits": Interval(int, 1, 16),
    }

    @classmethod
    def param_owner(cls) -> str:
        return "coocmap"

    def __init__(self, *, n_locations: int, n_words: int, grid_x: int = 12, grid_y: int = 8,
                 interpolate: bool = True, position_bits: int = 16) -> None:
        self.n_locations = int(n_locations)
        self.n_words = int(n_words)
        self.grid_x = int(grid_x)
        self.grid_y = int(grid_y)
        self.interpolate = bool(interpolate)
        self.position_bits = int(position_bits)
        self.validate_params()
        self.tour_names: list[str] = []
        self.tour_hours: list[float | None] = []
        self.vocabulary: dict[str, Any] = {}
        #: What the model was built from (tour fingerprints, feature settings), recorded by its user.
        self.built_from: dict[str, Any] = {}
        self._set_features(np.zeros(0, np.int64), np.zeros(0, np.int64),
                           np.zeros((0, 2), np.uint16), np.zeros(0, np.uint64))

    # -- construction ------------------------------------------------------------------
    @classmethod
    def build(
        cls,
        tours: Sequence[Sequence[Observation]],
        *,
        n_locations: int,
        n_words: int,
        grid_x: int = 12,
        grid_y: int = 8,
        interpolate: bool = True,
        position_bits: int = 16,
        tour_names: Sequence[str] | None = None,
        tour_hours: Sequence[float | None] | None = None,
    ) -> CoocModel:
        """Build all location models from tours given in time order (Sec. II-B).

        Parameters
        ----------
        tours : sequence of sequences of (location, words, xy)
            ``tours[t]`` lists the images of tour ``t``: location row in
            ``[0, n_locations)``, word ids of shape (n,), normalised positions
            of shape (n, 2) uint16.  Several images of one location in a tour
            are pooled into that tour's feature set.
        """
        model = cls(n_locations=n_locations, n_words=n_words, grid_x=grid_x, grid_y=grid_y,
                    interpolate=interpolate, position_bits=position_bits)
        names = list(tour_names) if tour_names is not None else [f"tour{t}" for t in range(len(tours))]
        hours = list(tour_hours) if tour_hours is not None else [None] * len(tours)
        for obs, name, hour in zip(tours, names, hours, strict=True):
            model.add_tour(obs, name=name, hour=hour)
        return model

    def add_tour(self, observations: Sequence[Observation], *, name: str = "",
                 hour: float | None = None, position: int | None = None) -> CoocModel:
        """Update every location model with a further tour (Sec. II-B).

        Parameters
        ----------
        observations : sequence of (location, words, xy)
            As in :meth:`build`.
        name, hour : str, float or None
            Label and time of day of the tour.
        position : int, optional
            Index of the tour in time order (default: after all existing tours).
            Later tours' bits move up by one, so adjacency (Sec. II-E) follows.

        Notes
        -----
        Only the tour's features are sorted; they are merged into the stored
        table (:func:`merge_sorted_features`), which is sorted and unique
        already, and the result is the table that sorting both together gives.
        Both are taken a block of consecutive locations at a time
        (:func:`_merge_by_locations`), and ``observations`` is read once to
        check it and once more, block by block, to merge it: within
        :func:`topoloc.io.scratch.spill_to` the new table is written to
        scratch files and this holds a block of the map and of the tour.
        Where location, word and position do not fit one 64-bit key
        (:func:`sort_unique_features`) the whole table is sorted again.
        """
        n_old = len(self.tour_names)
        if n_old + 1 > MAX_TOURS:
            raise TopolocError(f"coocmap: at most {MAX_TOURS} tours are supported")
        k = n_old if position is None else int(position)
        if not 0 <= k <= n_old:
            raise TopolocError(f"coocmap: tour position {k} out of range 0..{n_old}")
        # Checked here, read again a block of locations at a time (_tour_block): nothing of the tour is
        # kept from here but its locations, so that a tour whose words are in scratch files (a
        # methods.cooc_map._TourObservations within io.scratch.spill_to) is never all in memory.
        if not isinstance(observations, Sequence):
            observations = list(observations)
        obs_loc = np.empty(len(observations), np.int64)
        for i, (loc, w, xy) in enumerate(observations):
            w = np.asarray(w).ravel()
            if len(w) != len(np.asarray(xy).reshape(-1, 2)):
                raise TopolocError("coocmap: words and positions differ in length")
            if not 0 <= int(loc) < self.n_locations:
                raise TopolocError(f"coocmap: location {loc} out of range 0..{self.n_locations - 1}")
            if len(w) and (w.min() < 0 or w.max() >= self.n_words):
                raise TopolocError(f"coocmap: word ids must lie in [0, {self.n_words})")
            obs_loc[i] = int(loc)
            release(w, xy)
        mask_dt = _mask_dtype(n_old + 1)
        self.tour_names.insert(k, name or f"tour{n_old}")
        self.tour_hours.insert(k, hour)
        if _key_word_bits(self.n_locations, self.n_words) is None:
            # No packed key to search the table with (see sort_unique_features): sort it whole.
            new = self._tour_block(observations, range(len(observations)), k, mask_dt)
            self._set_features(np.concatenate([self.loc, new[0]]).astype(new[0].dtype, copy=False),
                               np.concatenate([self.word, new[1]]).astype(new[1].dtype, copy=False),
                               np.concatenate([self.xy, new[2]]),
                               np.concatenate([_insert_bit(self.tours, k, mask_dt), new[3]]))
            return self
        # The table is sorted and unique already (bit insertion keeps that), so only the tour's own
        # features are sorted, a block of locations at a time, and merged into the table's block.
        self._set_sorted(*_merge_by_locations(self, observations, obs_loc, k, mask_dt))
        return self

    def _tour_block(self, obs: Sequence[Observation], which: Sequence[int], k: int,
                    mask_dt: np.dtype) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The features of the observations ``which`` of a tour as the table holds them: quantised, tour bit ``k``.

        Returns
        -------
        loc, word, xy, mask
            Sorted and unique (:func:`sort_unique_features`), except where
            the features do not fit a packed key (the caller sorts the table whole).
        """
        loc_dt, word_dt = _small_uint(self.n_locations), _small_uint(self.n_words)
        read = [obs[i] for i in which]
        sizes = [len(np.asarray(w).ravel()) for _, w, _ in read]
        n = int(sum(sizes))
        loc = np.repeat(np.asarray([o[0] for o in read], np.int64), sizes).astype(loc_dt)
        word = (np.concatenate([np.asarray(w).ravel() for _, w, _ in read]).astype(word_dt) if n
                else np.zeros(0, word_dt))
        xy = (self.quantise_xy(np.concatenate([np.asarray(p, np.uint16).reshape(-1, 2) for _, _, p in read])) if n
              else np.zeros((0, 2), np.uint16))
        release(*(w for _, w, _ in read))
        del read
        mask = np.full(n, mask_dt.type(1 << k), mask_dt)
        if n == 0 or _key_word_bits(self.n_locations, self.n_words) is None:
            return loc, word, xy, mask
        return sort_unique_features(loc, word, xy, mask, n_locations=self.n_locations, n_words=self.n_words)

    def renumber_locations(self, rows: np.ndarray, n_locations: int) -> CoocModel:
        """Location ``i`` becomes location ``rows[i]`` of ``n_locations`` (new locations get no feature).

        Parameters
        ----------
        rows : ndarray of int, shape (n_locations_before,)
            Increasing, so that the table stays sorted by location.
        n_locations : int
            Locations after the change.
        """
        rows = np.asarray(rows, np.int64)
        if len(rows) != self.n_locations or (len(rows) and (rows.min() < 0 or rows.max() >= n_locations)) \
                or np.any(np.diff(rows) <= 0):
            raise TopolocError("coocmap: renumbered locations must be increasing and within the new count")
        self.n_locations = int(n_locations)
        loc_dt = _small_uint(self.n_locations)
        out = empty(len(self.loc), loc_dt)
        for s, e in chunk_rows(len(self.loc), 12):
            out[s:e] = rows[np.asarray(self.loc[s:e])]
            release(self.loc, out)
        self._set_sorted(out, self.word, self.xy, self.tours)
        return self

    def _set_features(self, loc: np.ndarray, word: np.ndarray, xy: np.ndarray,
                      mask: np.ndarray) -> None:
        """Deduplicate features (OR-ing tour masks) and rebuild the inverted files.

        Features are sorted by (location, word, y, x); equal ones become one
        feature whose tour mask is the OR of theirs.
        """
        if len(loc):
            loc, word, xy, mask = sort_unique_features(loc, word, xy, mask, n_locations=self.n_locations,
                                                       n_words=self.n_words)
        self._set_sorted(loc, word, xy, mask)

    def _set_sorted(self, loc: np.ndarray, word: np.ndarray, xy: np.ndarray, mask: np.ndarray) -> None:
        """Store features already sorted and unique (as :meth:`_set_features` leaves them); index them."""
        n_tours = max(len(self.tour_names), 1)
        self.loc = np.asarray(loc).astype(_small_uint(self.n_locations), copy=False)
        self.word = np.asarray(word).astype(_small_uint(self.n_words), copy=False)
        self.xy = np.ascontiguousarray(xy, dtype=np.uint16).reshape(-1, 2)
        self.tours = np.asarray(mask).astype(_mask_dtype(n_tours), copy=False)
        self._index()

    def _index(self) -> None:
        """Build the inverted files (:data:`INDEX_ARRAYS`) from the sorted feature table.

        Notes
        -----
        A counting sort (:func:`topoloc.coocmap.inverted.inverted_files`)
        writes the int32 outputs directly: at 100,000 places the table has
        tens of millions of rows, and the ``argsort`` and ``bincount`` this
        replaces each made an int64 copy of it, the peak of ``map add`` and of
        merging shard models (benchmarks/bench_cluster.py).  The arrays are
        those construction gave, value for value and dtype for dtype
        (tests/coocmap/test_cooc_model.py keeps it as the reference), so map
        files written before still hold the index this model builds.
        """
        # Imported here: numba's import is not needed to import the model or load a map file,
        # whose inverted files are stored in it.
        from topoloc.coocmap.inverted import inverted_files

        (self.loc_ptr, self.by_word, self.word_ptr, self.wloc,
         self.wloc_ptr) = inverted_files(self.loc, self.word, self.n_locations, self.n_words)
        self._groups: dict[bool, np.ndarray] = {}

    def quantise_xy(self, xy: np.ndarray) -> np.ndarray:
        """Normalised positions kept to ``position_bits`` per axis (bin centres).

        Parameters
        ----------
        xy : ndarray of uint16, shape (n, 2)

        Returns
        -------
        ndarray of uint16, shape (n, 2)
        """
        xy = np.asarray(xy, dtype=np.uint16).reshape(-1, 2)
        shift = 16 - self.position_bits
        if shift == 0:
            return xy
        return ((xy >> np.uint16(shift)) << np.uint16(shift)) | np.uint16(1 << (shift - 1))

    # -- queries of the model -------------------------------------------------------------
    @property
    def n_tours(self) -> int:
        return len(self.tour_names)

    @property
    def n_spatial(self) -> int:
        """Size of the spatial dictionary (384 for 12 x 8)."""
        return n_spatial_words(self.grid_x, self.grid_y)

    @property
    def n_features(self) -> int:
        """Distinct stored features over all locations."""
        return len(self.word)

    def group_masks(self, interpolate: bool | None = None) -> np.ndarray:
        """Per feature, the bit mask of groups (virtual images) it belongs to.

        Without interpolation a group is a tour; with it (Sec. II-E) group ``k``
        is tours ``k`` and ``k + 1``, so a feature of tour ``t`` is in groups
        ``t - 1`` and ``t``: ``(m | m >> 1)`` restricted to ``T - 1`` bits.

        Returns
        -------
        ndarray, shape (N,)
            In the dtype of the tour masks (uint8 up to 8 tours): a copy of
            the table's length, so kept as narrow as the masks themselves.
        """
        interp = self.interpolate if interpolate is None else bool(interpolate)
        if interp not in self._groups:
            m = np.asarray(self.tours)
            if interp and self.n_tours >= 2:
                one = m.dtype.type(1)
                keep = m.dtype.type((1 << (self.n_tours - 1)) - 1)
                m = (m | (m >> one)) & keep
            self._groups[interp] = m
        return self._groups[interp]

    def location_words(self, location: int) -> np.ndarray:
        """Sorted unique visual words stored for a location (the rows of M_i)."""
        s, e = self.loc_ptr[location], self.loc_ptr[location + 1]
        return np.unique(self.word[s:e]).astype(np.int64)

    def pair_keys(self, location: int, interpolate: bool | None = None) -> np.ndarray:
        """The explicit set M_i as sorted unique packed keys (Sec. II-B).

        ``key = (V * n_words + W) * n_spatial + S`` for each ordered pair of
        distinct stored features (words ``V, W``, spatial word ``S``) that
        share a group.  Memory O(n^2): for inspection and tests.

        Returns
        -------
        ndarray of int64, shape (n_keys,)
        """
        s, e = int(self.loc_ptr[location]), int(self.loc_ptr[location + 1])
        g = self.group_masks(interpolate)[s:e]
        n = e - s
        i, j = np.nonzero(~np.eye(n, dtype=bool))
        ok = (g[i] & g[j]) != 0
        i, j = i[ok] + s, j[ok] + s
        sw = spatial_words(self.xy[i], self.xy[j], grid_x=self.grid_x, grid_y=self.grid_y)
        keys = ((self.word[i].astype(np.int64) * self.n_words + self.word[j].astype(np.int64))
                * self.n_spatial + sw.astype(np.int64))
        return np.unique(keys)

    def pack_keys(self, wa: np.ndarray, wb: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Pack ``(V, W, S)`` triples like :meth:`pair_keys`."""
        return ((np.asarray(wa, np.int64) * self.n_words + np.asarray(wb, np.int64)) * self.n_spatial
                + np.asarray(s, np.int64))

    @property
    def nbytes(self) -> int:
        """Bytes of all arrays held (features, masks and both inverted files)."""
        return int(sum(a.nbytes for a in self._arrays().values()))

    @property
    def bytes_per_location(self) -> float:
        return self.nbytes / max(self.n_locations, 1)

    def _arrays(self) -> dict[str, np.ndarray]:
        return {"loc": self.loc, "word": self.word, "xy": self.xy, "tours": self.tours,
                "loc_ptr": self.loc_ptr, "by_word": self.by_word, "word_ptr": self.word_ptr,
                "wloc": self.wloc, "wloc_ptr": self.wloc_ptr}


def _key_word_bits(n_locations: int, n_words: int) -> int | None:
    """Bits of the word field in the packed feature key, or None where the key exceeds 64 bits.

    The key (:func:`_feature_keys`) is location, word, y and x side by side:
    the location's bits, then these, then 16 + 16 for the position.
    """
    lb = max(int(n_locations - 1).bit_length(), 1)
    wb = max(int(n_words - 1).bit_length(), 1)
    return None if lb + wb + 32 > 64 else wb


def _feature_keys(loc: np.ndarray, word: np.ndarray, xy: np.ndarray, word_bits: int) -> np.ndarray:
    """Features packed into ``uint64`` keys whose order is that of (location, word, y, x).

    Parameters
    ----------
    loc, word : ndarray of int, shape (n,)
        Location row and word id of each feature.
    xy : ndarray of uint16, shape (n, 2)
        Quantised positions.
    word_bits : int
        From :func:`_key_word_bits` (not None).

    Returns
    -------
    ndarray of uint64, shape (n,)
    """
    xy = np.asarray(xy, np.uint16).reshape(-1, 2)
    # Shifted and OR-ed in place with one uint64 temporary: for a whole map's feature table
    # (add_tour's search) each extra temporary is another 8 bytes per feature at the peak.
    key = np.asarray(loc).astype(np.uint64)
    key <<= np.uint64(word_bits + 32)
    part = np.asarray(word).astype(np.uint64)
    part <<= np.uint64(32)
    key |= part
    part[:] = xy[:, 1]
    part <<= np.uint64(16)
    key |= part
    del part
    key |= xy[:, 0]
    return key


def sort_unique_features(loc: np.ndarray, word: np.ndarray, xy: np.ndarray, mask: np.ndarray, *,
                         n_locations: int, n_words: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Features sorted by (location, word, y, x), equal ones merged by OR-ing their tour masks.

    Parameters
    ----------
    loc, word : ndarray of int, shape (n,)
        Location row and word id of each feature (``0 <= loc < n_locations``,
        ``0 <= word < n_words``).
    xy : ndarray of uint16, shape (n, 2)
        Quantised positions.
    mask : ndarray of uint, shape (n,)
        Tour bit masks.

    Returns
    -------
    loc, word, xy, mask
        The ``m <= n`` distinct features in that order.

    Notes
    -----
    When location, word and both coordinates fit in 64 bits (up to 2^16
    locations x 2^16 words, or 2^20 x 2^12, ...) the four keys are packed
    into one ``uint64`` and sorted once, which needs a third of the memory of
    a four-key ``lexsort`` on int64 copies; the order is the same.
    """
    wb = _key_word_bits(n_locations, n_words)
    xy = np.asarray(xy, np.uint16).reshape(-1, 2)
    if wb is None:
        order = np.lexsort((xy[:, 0], xy[:, 1], word, loc))
        loc, word, xy, mask = loc[order], word[order], xy[order], mask[order]
        new = np.ones(len(loc), bool)
        new[1:] = ((loc[1:] != loc[:-1]) | (word[1:] != word[:-1])
                   | (xy[1:, 0] != xy[:-1, 0]) | (xy[1:, 1] != xy[:-1, 1]))
        starts = np.flatnonzero(new)
        return loc[starts], word[starts], xy[starts], np.bitwise_or.reduceat(mask, starts)
    key = _feature_keys(loc, word, xy, wb)
    order = np.argsort(key)
    key = key[order]
    new = np.ones(len(key), bool)
    np.not_equal(key[1:], key[:-1], out=new[1:])
    starts = np.flatnonzero(new)
    del new
    mask = np.bitwise_or.reduceat(np.asarray(mask)[order], starts)
    del order
    key = key[starts]
    out_xy = np.empty((len(key), 2), np.uint16)
    out_xy[:, 0] = key & np.uint64(0xFFFF)
    out_xy[:, 1] = (key >> np.uint64(16)) & np.uint64(0xFFFF)
    out_word = ((key >> np.uint64(32)) & np.uint64((1 << wb) - 1)).astype(_small_uint(n_words))
    out_loc = (key >> np.uint64(wb + 32)).astype(_small_uint(n_locations))
    return out_loc, out_word, out_xy, mask


def merge_sorted_features(table: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                          new: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], *, n_locations: int,
                          n_words: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Two feature tables, each sorted and unique by (location, word, y, x), merged into one.

    What :func:`sort_unique_features` gives for the two tables concatenated,
    without sorting them again: the new features' places in the table are
    found by binary search on the packed keys, a feature already in the table
    takes the OR of both tour masks, the others are inserted.

    Parameters
    ----------
    table, new : tuple of (loc, word, xy, mask)
        As :func:`sort_unique_features` returns them.  ``table``'s mask is
        updated in place (pass a copy you own); ``new`` is usually much smaller.
    n_locations, n_words : int
        As for :func:`sort_unique_features`; the packed key must fit in 64 bits
        (:func:`_key_word_bits` not None).

    Returns
    -------
    loc, word, xy, mask
        In ``_small_uint`` dtypes for locations and words, uint16 positions and
        ``table``'s mask dtype.
    """
    loc, word, xy, mask = table
    wb = _key_word_bits(n_locations, n_words)
    if wb is None:
        raise TopolocError("coocmap: features too wide for a 64-bit key; use sort_unique_features")
    new_key = _feature_keys(new[0], new[1], new[2], wb)
    table_key = _feature_keys(loc, word, xy, wb)
    at = np.searchsorted(table_key, new_key)
    seen = np.zeros(len(new_key), bool)
    inside = np.flatnonzero(at < len(table_key))
    seen[inside] = table_key[at[inside]] == new_key[inside]
    del table_key, new_key, inside
    # New keys are unique, so the rows they hit are distinct and the fancy OR loses nothing.
    mask[at[seen]] |= np.asarray(new[3])[seen].astype(mask.dtype, copy=False)
    added = np.flatnonzero(~seen)
    # The i-th inserted feature lands after the i features inserted before it.
    dest = at[added] + np.arange(len(added))
    from_table = np.ones(len(loc) + len(added), bool)
    from_table[dest] = False

    def merged(old: np.ndarray, extra: np.ndarray, dtype: np.dtype) -> np.ndarray:
        # A 1-d boolean subscript of a 1-d array is filled without an index array of the table's size.
        out = np.empty(len(from_table), dtype)
        out[from_table] = old
        out[dest] = extra[added]
        return out

    # Positions as one uint32 per feature, so that they too take the 1-d boolean path.
    xy32 = merged(np.ascontiguousarray(xy, np.uint16).reshape(-1, 2).view(np.uint32).ravel(),
                  np.ascontiguousarray(new[2], np.uint16).reshape(-1, 2).view(np.uint32).ravel(),
                  np.dtype(np.uint32))
    return (merged(np.asarray(loc), np.asarray(new[0]), _small_uint(n_locations)),
            merged(np.asarray(word), np.asarray(new[1]), _small_uint(n_words)),
            xy32.view(np.uint16).reshape(-1, 2),
            merged(mask, np.asarray(new[3]), mask.dtype))


def _insert_bit(mask: np.ndarray, k: int, dtype: np.dtype) -> np.ndarray:
    """Tour masks with a zero bit inserted at ``k`` (bits from ``k`` up move one place up), as ``dtype``.

    Widened before shifting, since the mask grows by one bit; in place on the
    widened copy, so that masks of up to 64 bits cost two temporaries, not five.
    """
    out = np.asarray(mask).astype(dtype)
    low = dtype.type((1 << k) - 1)
    high = out & ~low
    high <<= dtype.type(1)
    out &= low
    out |= high
    return out


def _merge_by_locations(model: CoocModel, obs: Sequence[Observation], obs_loc: np.ndarray, k: int,
                        mask_dt: np.dtype) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The model's table, tour bit ``k`` inserted, merged with a tour's observations, block of locations by block.

    The table is sorted by location first, so a block of consecutive
    locations merges with the tour's features of the same locations alone
    (:func:`merge_sorted_features`), and the blocks' results follow each
    other.  Blocks hold about :data:`topoloc.io.scratch.CHUNK_BYTES` of the
    table (at most a sixteenth of it); the result is written into
    :func:`topoloc.io.scratch.empty` arrays and the table's pages are let go
    of after each block, so that within ``spill_to`` this holds a block of the
    map and of the tour, not the map.  The tour's blocks are sorted twice, once
    to count the merged table (allocated once, at its size) and once to merge.
    """
    loc, word, xy, tours = model.loc, model.word, model.xy, model.tours
    n_loc = model.n_locations
    loc_dt, word_dt = _small_uint(n_loc), _small_uint(model.n_words)
    n_old = len(word)
    old_ptr = np.asarray(model.loc_ptr, np.int64)
    order = np.argsort(obs_loc, kind="stable")
    obs_ptr = np.searchsorted(obs_loc[order], np.arange(n_loc + 1), side="left")
    row = loc.itemsize + word.itemsize + 4 + tours.itemsize
    chunk = min(CHUNK_BYTES, max(64 << 10, n_old * row // 16))
    cuts = np.unique(np.searchsorted(old_ptr, [s for s, _ in chunk_rows(n_old, row, chunk_bytes=chunk)],
                                     side="right") - 1)
    bounds = [int(b) for b in cuts if 0 < b < n_loc] + [n_loc]
    wb = _key_word_bits(n_loc, model.n_words)
    assert wb is not None  # add_tour sorts the whole table otherwise

    def blocks() -> Iterator[tuple[int, int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]]:
        first = 0
        for last in bounds:
            yield (int(old_ptr[first]), int(old_ptr[last]),
                   model._tour_block(obs, order[obs_ptr[first]:obs_ptr[last]].tolist(), k, mask_dt))
            first = last

    n_out = n_old
    for ts, te, new in blocks():
        n_out += len(new[1])
        if len(new[1]) and te > ts:
            keys = _feature_keys(loc[ts:te], word[ts:te], xy[ts:te], wb)
            new_key = _feature_keys(*new[:3], wb)
            hit = np.minimum(np.searchsorted(keys, new_key), len(keys) - 1)
            n_out -= int(np.count_nonzero(keys[hit] == new_key))
            release(loc, word, xy)
    out_loc, out_word = empty(n_out, loc_dt), empty(n_out, word_dt)
    out_xy, out_mask = empty((n_out, 2), np.uint16), empty(n_out, mask_dt)
    at = 0
    for ts, te, new in blocks():
        block = (np.array(loc[ts:te]), np.array(word[ts:te]), np.array(xy[ts:te]),
                 _insert_bit(tours[ts:te], k, mask_dt))
        release(loc, word, xy, tours)
        if len(new[1]):
            block = merge_sorted_features(block, new, n_locations=n_loc, n_words=model.n_words)
        m = len(block[0])
        out_loc[at:at + m], out_word[at:at + m], out_xy[at:at + m], out_mask[at:at + m] = block
        del block
        release(out_loc, out_word, out_xy, out_mask)
        at += m
    if at != n_out:
        raise AssertionError(f"coocmap: merged {at} features, counted {n_out}")
    return out_loc, out_word, out_xy, out_mask


def merge_models(parts: Sequence[CoocModel]) -> CoocModel:
    """One model from the models of consecutive location ranges (map shards), locations in order.

    ``M_i`` (Sec. II-B, II-E) depends only on the features of location ``i``
    in every tour, so a model built per range of locations holds exactly the
    generators of those locations; concatenating the ranges (part ``k``'s
    location ``j`` becomes ``j`` plus the locations of parts ``0..k-1``) gives
    the model built in one piece, array for array.  Every part must have the
    same tours in the same time order (their bit in the tour masks).

    Parameters
    ----------
    parts : sequence of CoocModel
        Models of consecutive location ranges, in order.

    Returns
    -------
    CoocModel

    Raises
    ------
    TopolocError
        For no part, or parts that differ in vocabulary size, grid, position
        lattice, interpolation or tours.
    """
    if not parts:
        raise TopolocError("coocmap: no model to merge")
    first = parts[0]
    for k, p in enumerate(parts[1:], start=1):
        for what in ("n_words", "grid_x", "grid_y", "interpolate", "position_bits", "tour_names", "tour_hours",
                     "vocabulary"):
            if getattr(p, what) != getattr(first, what):
                raise TopolocError(f"coocmap: shard model {k} has another {what} than shard model 0; "
                                   "build every shard with the same settings and tours")
    out = CoocModel(n_locations=sum(p.n_locations for p in parts), n_words=first.n_words, grid_x=first.grid_x,
                    grid_y=first.grid_y, interpolate=first.interpolate, position_bits=first.position_bits)
    out.tour_names = list(first.tour_names)
    out.tour_hours = list(first.tour_hours)
    out.vocabulary = dict(first.vocabulary)
    out.built_from = dict(first.built_from)
    offsets = np.cumsum([0] + [p.n_locations for p in parts[:-1]])
    loc_dt = _small_uint(out.n_locations)
    n = sum(p.n_features for p in parts)
    mask_dt = _mask_dtype(max(len(first.tour_names), 1))
    loc, word = empty(n, loc_dt), empty(n, _small_uint(out.n_words))
    xy, tours = empty((n, 2), np.uint16), empty(n, mask_dt)
    # Each part is sorted and unique by (location, word, y, x) and the parts' locations are
    # consecutive ranges, so their concatenation already is: no sort.  Copied a chunk at a time,
    # each part's pages and the output's let go of after each (io.scratch), so that merging holds
    # a chunk of the map, not the shards and the map.
    at = 0
    for p, o in zip(parts, offsets, strict=True):
        row = p.loc.itemsize + p.word.itemsize + 4 + p.tours.itemsize
        for s, e in chunk_rows(p.n_features, row):
            loc[at + s:at + e] = np.asarray(p.loc[s:e]).astype(loc_dt) + loc_dt.type(o)
            word[at + s:at + e] = p.word[s:e]
            xy[at + s:at + e] = np.asarray(p.xy[s:e], np.uint16).reshape(-1, 2)
            tours[at + s:at + e] = p.tours[s:e]
            release(p.loc, p.word, p.xy, p.tours, loc, word, xy, tours)
        at += p.n_features
    out._set_sorted(loc, word, xy, tours)
    return out
