"""The inverted files of a Cooc-Map model (Sec. II-C), built by counting sort.

:meth:`CoocModel._index <topoloc.coocmap.model.CoocModel._index>` derives
``loc_ptr``, ``by_word``, ``word_ptr``, ``wloc`` and ``wloc_ptr`` from the
feature table.  Words and locations are small integers, so a counting sort
in two passes over the table fills the int32 outputs directly; the NumPy way
(``argsort`` of the words, ``bincount``) made an int64 array of the table's
length for each step, and at 100,000 places (tens of millions of features)
those were the peak of ``map add`` and of merging shard models.

The table is walked in chunks (:func:`topoloc.io.scratch.chunk_rows`), its
pages and those of the outputs let go of after each (:func:`topoloc.io.scratch.release`):
within a :func:`topoloc.io.scratch.spill_to` block the outputs are
file-backed, and the process then holds a chunk of the table, not all of it.

Kept apart from :mod:`topoloc.coocmap.model` and imported on first use, so
that importing the model (or listing methods) does not load numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from topoloc.io.scratch import chunk_rows, empty, release


@njit(cache=True)
def _count(loc: np.ndarray, word: np.ndarray, n_locations: int, n_words: int, loc_ptr: np.ndarray,
           word_ptr: np.ndarray, wloc_ptr: np.ndarray, last: np.ndarray) -> None:
    # Counts into slot k + 1; `last` (the location of each word's previous feature) carries over
    # from chunk to chunk, so a word's next feature at the same location adds no location.
    for i in range(len(word)):
        lo = np.int64(loc[i])
        w = np.int64(word[i])
        if lo < 0 or lo >= n_locations or w < 0 or w >= n_words:
            raise ValueError("coocmap: a feature's location or word lies outside the model")
        loc_ptr[lo + 1] += 1
        word_ptr[w + 1] += 1
        if last[w] != lo:
            last[w] = lo
            wloc_ptr[w + 1] += 1


@njit(cache=True)
def _scatter_features(word: np.ndarray, first: int, by_word: np.ndarray, at: np.ndarray) -> None:
    # Taking features in index order keeps each word's run ascending, as a stable sort would.
    for i in range(len(word)):
        w = np.int64(word[i])
        by_word[at[w]] = first + i
        at[w] += 1


@njit(cache=True)
def _scatter_locations(loc: np.ndarray, word: np.ndarray, wloc: np.ndarray, at: np.ndarray,
                       last: np.ndarray) -> None:
    for i in range(len(word)):
        lo = np.int64(loc[i])
        w = np.int64(word[i])
        if last[w] != lo:
            last[w] = lo
            wloc[at[w]] = lo
            at[w] += 1


def inverted_files(loc: np.ndarray, word: np.ndarray, n_locations: int,
                   n_words: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Offsets and inverted files of a feature table.

    Parameters
    ----------
    loc, word : ndarray of int, shape (N,)
        Location row and word id of each feature.  No order is assumed, but
        the table's (location, word, y, x) order is what makes ``by_word``
        "by location within a word" and ``wloc`` ascending within a word.
    n_locations, n_words : int
        Bounds of ``loc`` and ``word``.

    Returns
    -------
    loc_ptr : ndarray of int64, shape (n_locations + 1,)
        Features of location ``i`` are ``loc_ptr[i]:loc_ptr[i+1]`` (for a
        table sorted by location).
    by_word : ndarray of int32, shape (N,)
        Feature indices grouped by word, ascending within a word: the stable
        ``argsort`` of ``word``.  File-backed within ``io.scratch.spill_to``
        when large.
    word_ptr : ndarray of int64, shape (n_words + 1,)
        Features of word ``w`` are ``by_word[word_ptr[w]:word_ptr[w+1]]``.
    wloc : ndarray of int32
        Per word, the locations of its features in ``by_word`` order with a
        location equal to the one before it (within the word) dropped.
        File-backed like ``by_word``.
    wloc_ptr : ndarray of int64, shape (n_words + 1,)
        Locations of word ``w`` are ``wloc[wloc_ptr[w]:wloc_ptr[w+1]]``.

    Raises
    ------
    ValueError
        For a location or word outside its bounds: the scatters do not check
        their indices, so they are checked while counting.
    """
    n = len(word)
    n_locations, n_words = int(n_locations), int(n_words)
    loc_ptr = np.zeros(n_locations + 1, np.int64)
    word_ptr = np.zeros(n_words + 1, np.int64)
    wloc_ptr = np.zeros(n_words + 1, np.int64)
    last = np.full(n_words, -1, np.int64)
    row = np.asarray(loc).itemsize + np.asarray(word).itemsize + 8
    chunks = list(chunk_rows(n, row))
    for s, e in chunks:
        _count(np.asarray(loc[s:e]), np.asarray(word[s:e]), n_locations, n_words, loc_ptr, word_ptr, wloc_ptr,
               last)
        release(loc, word)
    np.cumsum(loc_ptr, out=loc_ptr)
    np.cumsum(word_ptr, out=word_ptr)
    np.cumsum(wloc_ptr, out=wloc_ptr)
    # Next free slot of each word in by_word, then in wloc.  Two walks, not one: each keeps one
    # write cursor per word live instead of two.
    by_word = empty(n, np.int32)
    at = word_ptr[:n_words].copy()
    for s, e in chunks:
        _scatter_features(np.asarray(word[s:e]), s, np.asarray(by_word), at)
        release(word, by_word)
    wloc = empty(int(wloc_ptr[n_words]), np.int32)
    at[:] = wloc_ptr[:n_words]
    last[:] = -1
    for s, e in chunks:
        _scatter_locations(np.asarray(loc[s:e]), np.asarray(word[s:e]), np.asarray(wloc), at, last)
        release(loc, word, wloc)
    return loc_ptr, by_word, word_ptr, wloc, wloc_ptr
