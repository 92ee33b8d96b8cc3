"""The inverted files of a Cooc-Map model (Sec. II-C), built by counting sort.

:meth:`CoocModel._index <topoloc.coocmap.model.CoocModel._index>` derives
``loc_ptr``, ``by_word``, ``word_ptr``, ``wloc`` and ``wloc_ptr`` from the
feature table.  Words and locations are small integers, so a counting sort
in two passes over the table fills the int32 outputs directly; the NumPy way
(``argsort`` of the words, ``bincount``) made an int64 array of the table's
length for each step, and at 100,000 places (tens of millions of features)
those were the peak of ``map add`` and of merging shard models.

Kept apart from :mod:`topoloc.coocmap.model` and imported on first use, so
that importing the model (or listing methods) does not load numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
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
        ``argsort`` of ``word``.
    word_ptr : ndarray of int64, shape (n_words + 1,)
        Features of word ``w`` are ``by_word[word_ptr[w]:word_ptr[w+1]]``.
    wloc : ndarray of int32
        Per word, the locations of its features in ``by_word`` order with a
        location equal to the one before it (within the word) dropped.
    wloc_ptr : ndarray of int64, shape (n_words + 1,)
        Locations of word ``w`` are ``wloc[wloc_ptr[w]:wloc_ptr[w+1]]``.

    Raises
    ------
    ValueError
        For a location or word outside its bounds: the scatter below does not
        check its indices, so they are checked while counting.
    """
    n = len(word)
    loc_ptr = np.zeros(n_locations + 1, np.int64)
    word_ptr = np.zeros(n_words + 1, np.int64)
    wloc_ptr = np.zeros(n_words + 1, np.int64)
    # The location of each word's previous feature: a word's next feature at the same location
    # adds nothing to its list of locations.
    last = np.full(n_words, -1, np.int64)
    for i in range(n):
        lo = np.int64(loc[i])
        w = np.int64(word[i])
        if lo < 0 or lo >= n_locations or w < 0 or w >= n_words:
            raise ValueError("coocmap: a feature's location or word lies outside the model")
        loc_ptr[lo + 1] += 1
        word_ptr[w + 1] += 1
        if last[w] != lo:
            last[w] = lo
            wloc_ptr[w + 1] += 1
    for k in range(n_locations):
        loc_ptr[k + 1] += loc_ptr[k]
    for k in range(n_words):
        word_ptr[k + 1] += word_ptr[k]
        wloc_ptr[k + 1] += wloc_ptr[k]
    # Next free slot of each word in by_word, then in wloc; taking features in index order keeps
    # each word's run ascending, which is what a stable sort gives.  Two loops, not one: each
    # keeps one write cursor per word live instead of two.
    by_word = np.empty(n, np.int32)
    at = word_ptr[:n_words].copy()
    for i in range(n):
        w = np.int64(word[i])
        by_word[at[w]] = i
        at[w] += 1
    wloc = np.empty(wloc_ptr[n_words], np.int32)
    at[:] = wloc_ptr[:n_words]
    last[:] = -1
    for i in range(n):
        lo = np.int64(loc[i])
        w = np.int64(word[i])
        if last[w] != lo:
            last[w] = lo
            wloc[at[w]] = lo
            at[w] += 1
    return loc_ptr, by_word, word_ptr, wloc, wloc_ptr
