"""FAB-MAP 2.0 (Cummins & Newman, RSS 2009 / IJRR 2011): two-level place models (Eq. 4-5, 11).

:class:`InvertedIndex`.  Place models are restricted to two levels per word:
``e_hi = p(e_q = 1 | z_q = 1)`` if the word belongs to the place's word set
``W_i``, ``e_lo = p(e_q = 1 | z_q = 0)`` otherwise (one detector-only
application of Eq. 11 from the prior).  Then (Eq. 4-5)

    log p(Z | L_i) = log p(Z | L_lo) + sum_{q in W_i} D[c_q, q],
    D[c, q] = log p(z_q | z_p, e_hi) - log p(z_q | z_p, e_lo),

a sum over the place's words only: the inverted index.  Each word gets a
default state ``c*_q`` (its most frequent state in training; state 0 for the
rare words, "present" for near-stop-words), the per-place sums of
``D[c*_q, q]`` are precomputed, and a query only touches the postings of the
words whose state differs from the default, adding ``D[c_q, q] - D[c*_q, q]``
(the sparse log-likelihood-ratio increments).  Two exact engineering measures
keep this fast for very common words: a word in more than half of the places
stores the complement of its postings (adding the increment to all places and
subtracting it from the complement), and the mid-frequency words whose
postings would be long *and* often touched are stored as bit-sliced
signatures (8 words per byte column) and scored with 256-entry lookup tables.
Both give exactly the same numbers as walking the postings.

With several observations of a place (Eq. 11 merging, :class:`WordCounts`),
``W_i`` is the set of words whose merged belief exceeds the prior: under the
detector-only update the posterior odds are the prior odds times
``LR1^k LR0^(n-k)`` after seeing a word in ``k`` of ``n`` observations
(``LR1 = (1 - p_fn) / p_fp``, ``LR0 = p_fn / (1 - p_fp)``), i.e.
``k / n > log(1/LR0) / (log LR1 + log(1/LR0))`` (about 10 % with the default
detector; :func:`merge_threshold`).  For a single observation ``W_i`` is
exactly the observed words.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import scipy.sparse as sp

from topoloc.fabmap.chowliu import as_occurrence, occurrence_matrix
from topoloc.fabmap.observation import Observation, ObservationModel


def merge_threshold(p_fp: float, p_fn: float) -> float:
    """Fraction ``k / n`` of observations above which a word is in a merged place's word set.

    See the module docstring (FAB-MAP 2.0 with Eq. 11 merging).
    """
    lr1 = np.log((1.0 - p_fn) / p_fp)
    lr0 = np.log((1.0 - p_fp) / p_fn)
    return float(lr0 / (lr1 + lr0))


class WordCounts:
    """Per-place word counts over merged observations (FAB-MAP 2.0 appearance update).

    Parameters
    ----------
    p_fp, p_fn : float
        Detector model, which sets the merge threshold (:func:`merge_threshold`).
    """

    def __init__(self, *, p_fp: float, p_fn: float) -> None:
        self.threshold = merge_threshold(p_fp, p_fn)
        self._words: list[np.ndarray] = []
        self._counts: list[np.ndarray] = []
        self._n_obs: list[int] = []

    def __len__(self) -> int:
        return len(self._words)

    def add(self, words: np.ndarray) -> int:
        """New place observed once with ``words``; returns its index."""
        w = np.unique(np.asarray(words, dtype=np.int64))
        self._words.append(w)
        self._counts.append(np.ones(w.size, dtype=np.int64))
        self._n_obs.append(1)
        return len(self._words) - 1

    def update(self, i: int, words: np.ndarray) -> None:
        """Merge one more observation into place ``i``."""
        w = np.unique(np.asarray(words, dtype=np.int64))
        allw = np.concatenate([self._words[i], w])
        allc = np.concatenate([self._counts[i], np.ones(w.size, dtype=np.int64)])
        uw, inv = np.unique(allw, return_inverse=True)
        self._words[i] = uw
        self._counts[i] = np.bincount(inv, weights=allc).astype(np.int64)
        self._n_obs[i] += 1

    def word_set(self, i: int) -> np.ndarray:
        """``W_i``: words seen in more than the threshold fraction of the place's observations."""
        n = self._n_obs[i]
        if n == 1:
            return self._words[i]
        return self._words[i][self._counts[i] > self.threshold * n]


try:  # scipy's compiled CSC mat-vec kernel: y[Ai[k]] += Ax[k] * x[j] for k in [Ap[j], Ap[j+1])
    from scipy.sparse._sparsetools import csc_matvec as _csc_matvec
except ImportError:  # pragma: no cover - private scipy API; numpy fallback below
    _csc_matvec = None


def _scatter_postings(
    s: np.ndarray,
    indptr: np.ndarray,
    indices: np.ndarray,
    ones: np.ndarray | None,
    words: np.ndarray,
    weights: np.ndarray,
) -> None:
    """``s[postings(q)] += w_q`` for every word ``q`` of ``words``, in place.

    The postings of word ``q`` are ``indices[indptr[q]:indptr[q+1]]`` (distinct
    places).  With scipy's compiled ``csc_matvec`` this is one C loop over the
    touched postings: the selected lists are presented as the columns of a CSC
    matrix whose column pointers are ``[s_1, e_1, s_2, e_2, ...]`` with lists in
    *decreasing* order of start, so that every in-between "gap column"
    ``[e_i, s_{i+1})`` is empty (``s_{i+1} < s_i <= e_i``) and gets weight 0.
    Without it, a numpy loop over the words gives the same result.
    """
    if words.size == 0:
        return
    starts = indptr[words]
    ends = indptr[words + 1]
    if _csc_matvec is not None and ones is not None:
        order = np.argsort(-starts, kind="stable")
        ap = np.empty(2 * words.size, dtype=indices.dtype)
        ap[0::2] = starts[order]
        ap[1::2] = ends[order]
        x = np.zeros(2 * words.size - 1)
        x[0::2] = weights[order]
        _csc_matvec(s.size, x.size, ap, indices, ones, x, s)
        return
    for st, en, wq in zip(starts, ends, weights, strict=True):
        s[indices[st:en]] += wq


_BITS = ((np.arange(256)[:, None] >> np.arange(8)[None, :]) & 1).astype(np.float64)  # (256, 8)


class InvertedIndex:
    """FAB-MAP 2.0 log-likelihoods through an inverted index (module docstring).

    Parameters
    ----------
    obs_model : ObservationModel
    word_sets : iterable of int arrays, or sparse (n_places, V) binary matrix, optional
        Initial places' word sets ``W_i``.
    lut_threshold : float
        A word goes to the bit-sliced lookup tables when (probability that a
        query moves it off its default state) x (fraction of places whose
        postings must be walked) exceeds this; only speed depends on it.
    rebuild_fraction : float
        Places added or changed since the last build are scored directly from
        their word sets; the index is rebuilt when they exceed this fraction.

    Notes
    -----
    :meth:`log_likelihood` returns ``log p(Z | L_i)`` under the two-level model
    (the constant ``log p(Z | L_lo)`` included), so values are comparable with
    the new-place term and across queries.
    """

    def __init__(
        self,
        obs_model: ObservationModel,
        word_sets: Iterable[np.ndarray] | sp.spmatrix = (),
        *,
        lut_threshold: float = 0.1,
        rebuild_fraction: float = 0.05,
    ) -> None:
        self.obs_model = obs_model
        self.lut_threshold = float(lut_threshold)
        self.rebuild_fraction = float(rebuild_fraction)
        v = obs_model.n_words
        q = np.arange(v)
        self.D = obs_model.d_hilo  # (4, V): log-likelihood ratio of holding q, per state
        self.default_code = np.argmax(obs_model.state_p, axis=0).astype(np.int8)
        self.D_default = self.D[self.default_code, q]
        self.p_nondefault = 1.0 - obs_model.state_p[self.default_code, q]
        # the all-"absent" place L_lo, evaluated over the query's active words only
        self._lo_terms = obs_model.state_terms(obs_model.e_lo)
        self._lo_base = float(self._lo_terms[0].sum())
        self._csr = sp.csr_matrix((0, v), dtype=np.uint8)  # word sets of the indexed places
        self._extra: list[np.ndarray] = []  # places added since the last build
        self._override: dict[int, np.ndarray] = {}  # indexed places changed since
        self._defaults = np.zeros(0)
        self._indptr = np.zeros(v + 1, dtype=np.int64)
        self._indices = np.zeros(0, dtype=np.int32)
        self._ones: np.ndarray | None = None
        self._complement = np.zeros(v, dtype=bool)
        self._slot = np.full(v, -1, dtype=np.int64)
        self._bits = np.zeros((0, 0), dtype=np.uint8)
        if sp.issparse(word_sets):
            self._build(as_occurrence(word_sets, n_words=v))
        else:
            sets = [np.asarray(w) for w in word_sets]
            if sets:
                self._build(occurrence_matrix(sets, n_words=v))

    # -- construction ---------------------------------------------------------------
    @property
    def n_places(self) -> int:
        return int(self._csr.shape[0]) + len(self._extra)

    def __len__(self) -> int:
        return self.n_places

    @property
    def _n_static(self) -> int:
        return int(self._csr.shape[0])

    def word_set(self, i: int) -> np.ndarray:
        """``W_i``, sorted word ids of place ``i``."""
        ns = self._n_static
        if i >= ns:
            return self._extra[i - ns]
        if i in self._override:
            return self._override[i]
        x = self._csr
        return x.indices[x.indptr[i]:x.indptr[i + 1]].astype(np.int64)

    def add_place(self, words: np.ndarray) -> int:
        """Append a place with word set ``words``; returns its index."""
        self._extra.append(np.unique(np.asarray(words, dtype=np.int64)))
        self._maybe_rebuild()
        return self.n_places - 1

    def set_place(self, i: int, words: np.ndarray) -> None:
        """Replace the word set of place ``i`` (after an appearance update)."""
        w = np.unique(np.asarray(words, dtype=np.int64))
        ns = self._n_static
        if i >= ns:
            self._extra[i - ns] = w
        else:
            self._override[i] = w
        self._maybe_rebuild()

    def _maybe_rebuild(self) -> None:
        pending = len(self._extra) + len(self._override)
        if pending > max(64, self.rebuild_fraction * self.n_places):
            self.rebuild()

    def rebuild(self) -> None:
        """Fold added and changed places into the index (amortised: see ``rebuild_fraction``)."""
        v = self.obs_model.n_words
        x = self._csr
        if self._override:
            rows = [self.word_set(i) for i in range(self._n_static)]
            x = occurrence_matrix(rows, n_words=v)
        if self._extra:
            x = sp.vstack([x, occurrence_matrix(self._extra, n_words=v)], format="csr")
        self._extra = []
        self._override = {}
        self._build(as_occurrence(x, n_words=v))

    def _build(self, x: sp.csr_matrix) -> None:
        """Postings, complements and bit slices for the places of ``x`` (places x words)."""
        v = self.obs_model.n_words
        p = x.shape[0]
        self._csr = x
        self._defaults = np.asarray(x @ self.D_default, dtype=np.float64).ravel()
        xt = x.T.tocsr()  # word-major: postings with ascending place ids
        xt.sort_indices()
        df = np.diff(xt.indptr)
        rho = df / max(p, 1)
        walk = np.minimum(rho, 1.0 - rho)
        lut = (self.p_nondefault * walk >= self.lut_threshold) & (df > 0)
        comp = (rho > 0.5) & ~lut
        self._complement = comp
        # postings: direct rows, complement rows, nothing for lookup-table words
        segments: list[np.ndarray] = []
        lens = np.zeros(v, dtype=np.int64)
        all_places = np.arange(p, dtype=np.int32)
        for q in range(v):
            if lut[q] or df[q] == 0:
                continue
            row = xt.indices[xt.indptr[q]:xt.indptr[q + 1]]
            if comp[q]:
                keep = np.ones(p, dtype=bool)
                keep[row] = False
                row = all_places[keep]
            segments.append(row.astype(np.int32, copy=False))
            lens[q] = row.size
        self._indptr = np.zeros(v + 1, dtype=np.int64)
        np.cumsum(lens, out=self._indptr[1:])
        self._indices = np.concatenate(segments) if segments else np.zeros(0, dtype=np.int32)
        if self._indices.size >= 2**31 - 1:
            self._indices = self._indices.astype(np.int64)
        # unit posting weights for the compiled scatter (see _scatter_postings)
        self._ones = np.ones(self._indices.size) if _csc_matvec is not None else None
        # bit slices: lookup-table word k is bit k % 8 of byte column k // 8
        lut_words = np.flatnonzero(lut)
        self._slot = np.full(v, -1, dtype=np.int64)
        self._slot[lut_words] = np.arange(lut_words.size)
        bits = np.zeros(((lut_words.size + 7) // 8, p), dtype=np.uint8)
        for k, word in enumerate(lut_words.tolist()):
            bits[k // 8, xt.indices[xt.indptr[word]:xt.indptr[word + 1]]] |= np.uint8(1 << (k % 8))
        self._bits = bits

    # -- scoring --------------------------------------------------------------------
    def increments(self, obs: Observation) -> tuple[np.ndarray, np.ndarray]:
        """Words off their default state and their log-likelihood-ratio increments.

        They depend on the observation model only, so indexes over the same model
        (the map's and the sampled training places') can share them.
        """
        codes = obs.codes
        nd = np.flatnonzero(codes != self.default_code)
        w = self.D[codes[nd], nd] - self.D_default[nd]
        return nd, w

    def relative_log_likelihood(self, obs: Observation,
                                increments: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """``log p(Z | L_i) - log p(Z | L_lo)`` for every place, shape (n_places,).

        ``increments``: :meth:`increments` of ``obs``, when already computed for an
        index over the same observation model.
        """
        p = self.n_places
        ns = self._n_static
        score = np.empty(p)
        s = score[:ns]
        s[:] = self._defaults[:ns]
        nd, w = self.increments(obs) if increments is None else increments
        if ns and nd.size:
            slot = self._slot[nd]
            in_lut = slot >= 0
            # bit-sliced lookup-table words
            if in_lut.any():
                g = self._bits.shape[0]
                wl = np.zeros(g * 8)
                wl[slot[in_lut]] = w[in_lut]
                groups = np.unique(slot[in_lut] // 8)
                # one gather from the flattened tables for all touched byte columns, instead of a
                # Python loop of one lookup per column
                tables = wl.reshape(g, 8)[groups] @ _BITS.T  # (touched, 256)
                flat = self._bits[groups] + (256 * np.arange(groups.size))[:, None]
                s += np.take(tables.ravel(), flat).sum(axis=0)
            # postings words (complement-stored ones: add to all, subtract from the complement)
            pw = nd[~in_lut]
            ww = w[~in_lut]
            comp = self._complement[pw]
            if comp.any():
                s += ww[comp].sum()
                ww = np.where(comp, -ww, ww)
            _scatter_postings(s, self._indptr, self._indices, self._ones, pw, ww)
        # places added or changed since the last build: directly from their word sets
        dirty = sorted(self._override) + list(range(ns, p))
        if dirty:
            score[dirty] = self._direct(obs, dirty)
        return score

    def _direct(self, obs: Observation, places: Sequence[int]) -> np.ndarray:
        sets = [self.word_set(i) for i in places]
        lens = np.fromiter((x.size for x in sets), dtype=np.int64, count=len(sets))
        if lens.sum() == 0:
            return np.zeros(len(sets))
        words = np.concatenate(sets)
        vals = self.D[obs.codes[words], words]
        return np.bincount(np.repeat(np.arange(len(sets)), lens), weights=vals, minlength=len(sets))

    def log_likelihood_lo(self, obs: Observation) -> float:
        """``log p(Z | L_lo)``: the place that holds none of the words (Eq. 4-5)."""
        return self.obs_model.log_likelihood_sparse(self._lo_terms, self._lo_base, obs)

    def log_likelihood(self, obs: Observation) -> np.ndarray:
        """``log p(Z | L_i)`` under the FAB-MAP 2.0 two-level place models, shape (n_places,)."""
        return self.relative_log_likelihood(obs) + self.log_likelihood_lo(obs)

    def log_likelihood_bruteforce(self, obs: Observation) -> np.ndarray:
        """Reference: Eq. 4-5 over all words with ``e = e_hi`` on ``W_i`` and ``e_lo`` elsewhere."""
        om = self.obs_model
        out = np.empty(self.n_places)
        for i in range(self.n_places):
            ws = self.word_set(i)
            e = om.e_lo.copy()
            e[ws] = om.e_hi[ws]
            out[i] = om.log_likelihood_single(e, obs)
        return out

    @property
    def n_lut_words(self) -> int:
        return int((self._slot >= 0).sum())

    @property
    def n_postings(self) -> int:
        return int(self._indices.size)
