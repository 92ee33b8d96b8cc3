"""Bag-of-words baseline: tf-idf weighting, inverted file, cosine similarity.

Sivic & Zisserman, "Video Google" (ICCV 2003).  Each map image is a document
whose words are the visual words of its local features.  With ``n_id`` the
count of word ``i`` in document ``d``, ``n_d`` the number of words in ``d``,
``N`` the number of map images and ``N_i`` the number of map images containing
word ``i``, the weights are

    t_id = (n_id / n_d) * log(N / N_i),

each document vector is L2-normalised and the similarity of a query to a map
image is the cosine (dot product of normalised vectors).  The product is
evaluated through the inverted file (word -> map images), so a query touches
only the postings of its own words.

Several images of one place (from one or several map traverses) are merged
per place by ``merge``: ``"max"`` keeps the best-matching image (a night query
can match the night tour), ``"sum"`` pools the images' word counts into one
document per place.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar, Self

import numpy as np
import scipy.sparse as sp

from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.methods.base import PlaceRecognizer, Resources, map_place_ids


def term_counts(words: Sequence[np.ndarray], n_words: int) -> sp.csr_matrix:
    """Word-count matrix of shape (n_documents, n_words) from word-id arrays."""
    indptr = np.r_[0, np.cumsum([len(w) for w in words])]
    indices = np.concatenate(words).astype(np.int64) if len(words) else np.zeros(0, np.int64)
    m = sp.csr_matrix(
        (np.ones(len(indices), np.float32), indices, indptr), shape=(len(words), n_words)
    )
    m.sum_duplicates()
    return m


def inverse_document_frequency(counts: sp.csr_matrix) -> np.ndarray:
    """``log(N / N_i)`` per word, shape (n_words,); 0 for words absent from every document."""
    n_docs = counts.shape[0]
    df = np.bincount(counts.indices, minlength=counts.shape[1]).astype(np.float64)
    with np.errstate(divide="ignore"):
        idf = np.where(df > 0, np.log(n_docs / np.maximum(df, 1)), 0.0)
    return idf.astype(np.float32)


def tfidf(counts: sp.csr_matrix, idf: np.ndarray) -> sp.csr_matrix:
    """L2-normalised tf-idf rows, ``t_id = n_id / n_d * idf_i``."""
    n_d = np.asarray(counts.sum(axis=1)).ravel()
    w = sp.diags(1.0 / np.maximum(n_d, 1)).astype(np.float32) @ counts @ sp.diags(idf)
    norms = np.sqrt(np.asarray(w.multiply(w).sum(axis=1)).ravel())
    return sp.csr_matrix(sp.diags(1.0 / np.where(norms > 0, norms, 1)) @ w, dtype=np.float32)


class BagOfWords(PlaceRecognizer):
    """tf-idf bag-of-words with an inverted file (Sivic & Zisserman 2003).

    Parameters
    ----------
    merge : {"max", "sum"}
        How images of the same place are combined (see module docstring).

    Attributes
    ----------
    place_ids_ : ndarray of int64, shape (n_places,)
    idf_ : ndarray of float32, shape (n_words,)
    inverted_ : scipy.sparse.csr_matrix, shape (n_words, n_documents)
        The inverted file: row ``i`` lists the documents containing word ``i``
        with their normalised tf-idf weights.
    doc_place_ : ndarray of int64, shape (n_documents,)
        Row of ``S`` of each document.
    """

    name: ClassVar[str] = "bow"
    uses_vocabulary: ClassVar[bool] = True

    def __init__(self, *, merge: str = "max") -> None:
        self.merge = merge

    def fit(self, maps: Sequence[Traverse], *, resources: Resources) -> Self:
        if self.merge not in ("max", "sum"):
            raise TopolocError(f"bow: merge must be 'max' or 'sum', not {self.merge!r}")
        place_ids = map_place_ids(maps)
        words = [w for m in maps for w in resources.words(m)]
        rows = np.searchsorted(place_ids, np.concatenate([m.places for m in maps]))
        n_words = resources.vocabulary.n_words_
        counts = term_counts(words, n_words)
        if self.merge == "sum":
            pool = sp.csr_matrix(
                (np.ones(len(rows), np.float32), (rows, np.arange(len(rows)))),
                shape=(len(place_ids), len(rows)),
            )
            counts = sp.csr_matrix(pool @ counts)
            rows = np.arange(len(place_ids))
        self.n_words_ = n_words
        self.idf_ = inverse_document_frequency(counts)
        self.inverted_ = sp.csr_matrix(tfidf(counts, self.idf_).T)
        order = np.argsort(rows, kind="stable")
        self.doc_order_ = order
        self.doc_place_ = rows
        # Start offset of each place's run of documents after sorting by place.
        self.place_start_ = np.searchsorted(rows[order], np.arange(len(place_ids)))
        self.place_ids_ = place_ids
        return self

    def encode(self, query: Traverse, *, resources: Resources) -> list[Any]:
        return resources.words(query)

    def score(self, items: Sequence[Any]) -> np.ndarray:
        """Cosine similarity per place, shape (n_places, len(items))."""
        self.check_fitted()
        q = tfidf(term_counts(list(items), self.n_words_), self.idf_)
        # (items x words) @ (words x docs): walks only the postings of the query's words.
        per_doc = (q @ self.inverted_).toarray().T
        S = np.maximum.reduceat(per_doc[self.doc_order_], self.place_start_, axis=0)
        return self._check_block(S.astype(np.float32), len(items))
