"""tf-idf bag of visual words with an inverted file (Sivic & Zisserman, "Video Google", ICCV 2003).

With ``n_id`` the count of word ``i`` in document ``d``, ``n_d`` the number of
words in ``d``, ``N`` the number of documents and ``N_i`` the number of
documents containing word ``i``, the weights are

    t_id = (n_id / n_d) * log(N / N_i),

each document vector is L2-normalised and the similarity of a query to a
document is the cosine (dot product of normalised vectors), evaluated through
the inverted file (word -> documents) so that a query touches only the
postings of its own words.  Pure functions on word-id arrays and SciPy sparse
matrices; :class:`topoloc.methods.bag_of_words.BagOfWords` is the recogniser.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp


def term_counts(words: Sequence[np.ndarray], n_words: int) -> sp.csr_matrix:
    """Word-count matrix of shape (n_documents, n_words) from word-id arrays."""
    indptr = np.r_[0, np.cumsum([len(w) for w in words])]
    indices = np.concatenate(words).astype(np.int64) if len(words) else np.zeros(0, np.int64)
    m = sp.csr_matrix(
        (np.ones(len(indices), np.float32), indices, indptr), shape=(len(words), n_words)
    )
    m.sum_duplicates()
    return m


def merge_documents(parts: Sequence[sp.csr_matrix], order: np.ndarray) -> sp.csr_matrix:
    """The documents of partial collections (map shards) as one collection, in map order.

    Document frequencies need no merging of their own: ``N_i`` of the merged
    collection is the sum of the parts' ``N_i`` and ``N`` the sum of their
    ``N``, so :func:`inverse_document_frequency` of the result is the idf of
    the map built in one piece.

    Parameters
    ----------
    parts : sequence of csr_matrix, each (n_documents_k, n_words)
        Word counts (:func:`term_counts`) of each part.
    order : ndarray of int64, shape (sum n_documents_k,)
        Row ``j`` of the result is row ``order[j]`` of the parts stacked in order.

    Returns
    -------
    csr_matrix, shape (len(order), n_words)
        Built like :func:`term_counts` (same dtypes, sorted indices), so it equals
        the counts of the whole map bit for bit.
    """
    n_words = int(parts[0].shape[1])
    stacked = sp.csr_matrix(sp.vstack(list(parts), format="csr"))[np.asarray(order, np.int64)]
    m = sp.csr_matrix((stacked.data.astype(np.float32), stacked.indices.astype(np.int64),
                       stacked.indptr.astype(np.int64)), shape=(len(order), n_words))
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


def inverted_file(counts: sp.csr_matrix, idf: np.ndarray) -> sp.csr_matrix:
    """The inverted file, shape (n_words, n_documents): row ``i`` holds the normalised
    tf-idf weights of the documents that contain word ``i``."""
    return sp.csr_matrix(tfidf(counts, idf).T)


def cosine_scores(words: Sequence[np.ndarray], idf: np.ndarray, inverted: sp.csr_matrix) -> np.ndarray:
    """Cosine similarity of every query (word-id array) to every document.

    Returns
    -------
    ndarray of float32, shape (n_documents, len(words))
    """
    q = tfidf(term_counts(list(words), inverted.shape[0]), idf)
    # (queries x words) @ (words x docs): walks only the postings of the query's words.
    return (q @ inverted).toarray().T.astype(np.float32)
