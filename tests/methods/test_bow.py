"""tf-idf bag of words with an inverted file."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.bow import inverse_document_frequency, term_counts, tfidf
from topoloc.datasets.traverse import Traverse
from topoloc.errors import NotFittedError
from topoloc.methods.bag_of_words import BagOfWords
from topoloc.resources import InMemoryResources
from topoloc.testing import word_vocabulary


def _trav(name: str, words: list[np.ndarray], places: list[int]) -> Traverse:
    return Traverse.from_words(words, places, name=name)


def _res(n_words: int) -> InMemoryResources:
    return InMemoryResources(vocabulary=word_vocabulary(n_words))


def test_tfidf_by_hand() -> None:
    counts = term_counts([np.array([0, 0, 1]), np.array([1, 2])], 3)
    assert counts.toarray().tolist() == [[2, 1, 0], [0, 1, 1]]
    idf = inverse_document_frequency(counts)
    np.testing.assert_allclose(idf, [np.log(2), 0, np.log(2)], rtol=1e-6)
    w = tfidf(counts, idf).toarray()
    # doc 0: tf (2/3, 1/3, 0) * idf -> (2/3 log2, 0, 0) -> normalised (1, 0, 0)
    np.testing.assert_allclose(w[0], [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(w[1], [0, 0, 1], atol=1e-6)


def test_inverted_file_equals_dense_cosine() -> None:
    rng = np.random.default_rng(0)
    n_words = 50
    map_words = [rng.integers(0, n_words, 30) for _ in range(8)]
    q_words = [rng.integers(0, n_words, 30) for _ in range(3)]
    res = _res(n_words)
    bow = BagOfWords(confidence="raw").fit([_trav("m", map_words, list(range(8)))], resources=res)
    S = bow.score(bow.encode(_trav("q", q_words, [0, 1, 2]), resources=res))
    counts = term_counts(map_words, n_words)
    idf = inverse_document_frequency(counts)
    M = tfidf(counts, idf).toarray()
    Q = tfidf(term_counts(q_words, n_words), idf).toarray()
    np.testing.assert_allclose(S, M @ Q.T, atol=1e-6)
    assert S.shape == (8, 3) and S.dtype == np.float32


def test_places_merged_over_traverses() -> None:
    # Place 1 looks like words {0,1} on tour a and {5,6} on tour b.
    words = {
        "a": [np.array([2, 3]), np.array([0, 1]), np.array([7, 8])],
        "b": [np.array([2, 3]), np.array([5, 6]), np.array([7, 8])],
        "q": [np.array([5, 6]), np.array([0, 1])],
    }
    res = _res(10)
    maps = [_trav("a", words["a"], [0, 1, 2]), _trav("b", words["b"], [0, 1, 2])]
    for merge in ("max", "sum"):
        bow = BagOfWords(merge=merge).fit(maps, resources=res)
        S = bow.score(bow.encode(_trav("q", words["q"], [1, 1]), resources=res))
        assert S.shape == (3, 2)
        assert np.argmax(S, axis=0).tolist() == [1, 1]
    assert bow.place_ids_.tolist() == [0, 1, 2]


def test_not_fitted_and_bad_param() -> None:
    with pytest.raises(NotFittedError):
        BagOfWords().score([np.array([1])])
    with pytest.raises(Exception, match="merge"):
        BagOfWords(merge="mean").fit([_trav("a", [np.array([0])], [0])], resources=_res(2))
