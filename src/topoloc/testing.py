"""Test helpers: exact stand-in vocabularies, hand-made features, and the recogniser contract check.

Like scikit-learn's ``check_estimator``, :func:`check_recognizer` runs the
contract of :mod:`topoloc.methods.base` against one recogniser, so that a new
method (ours or a user's) can be checked with one call; the test suite runs it
over every registered method.  :func:`word_vocabulary` and
:func:`features_for_words` let a test state visual words directly: word ``w``
is the descriptor ``scale * e_w``, and the vocabulary's centres are exactly
those vectors, so quantisation returns the words given.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from topoloc.datasets.traverse import Traverse
from topoloc.errors import NotFittedError, TopolocError
from topoloc.features import FeatureSet
from topoloc.methods.base import PlaceRecognizer
from topoloc.methods.resources import Resources
from topoloc.vocabulary import Vocabulary

_SIFT_KIND = "sift-128-float32"
_SCALE = 100.0


def word_vocabulary(n_words: int) -> Vocabulary:
    """A vocabulary of ``n_words <= 128`` SIFT-space words, word ``w`` at ``100 * e_w`` (exact search)."""
    if not 2 <= n_words <= 128:
        raise ValueError(f"n_words must be in 2..128, got {n_words}")
    return Vocabulary.from_words(_SCALE * np.eye(n_words, 128, dtype=np.float32), descriptor_kind=_SIFT_KIND,
                                 index="flat", provenance={"source": "topoloc.testing.word_vocabulary"})


def features_for_words(words: np.ndarray, xy: np.ndarray, image_shape: tuple[int, int]) -> FeatureSet:
    """A :class:`FeatureSet` whose descriptors quantise to ``words`` under :func:`word_vocabulary`.

    Parameters
    ----------
    words : ndarray of int, shape (n,)
    xy : ndarray of float, shape (n, 2)
        Keypoint positions in pixels.
    image_shape : (height, width)
    """
    words = np.asarray(words, np.int64)
    kp = np.zeros((len(words), 5), np.float32)
    kp[:, :2] = xy
    kp[:, 2] = 4.0
    desc = np.zeros((len(words), 128), np.float32)
    desc[np.arange(len(words)), words] = _SCALE
    return FeatureSet(kp, desc, image_shape)


def check_recognizer(
    recognizer: PlaceRecognizer, maps: list[Traverse], query: Traverse, *, resources: Resources,
    bad_params: dict[str, Any] | None = None,
) -> np.ndarray:
    """Check ``recognizer`` against the contract; returns the ``S`` it scored.

    Checked: parameters round-trip through ``get_params``/``set_params`` and
    show in ``repr``; using it before ``fit`` raises :class:`NotFittedError`;
    ``fit`` returns self and sets ``place_ids_`` (sorted unique map places);
    ``S`` has shape (n_map_places, n_queries), is finite and does not depend
    on scoring queries one by one (unless the method scores whole sequences);
    ``similarity`` equals ``score(encode(...))``; an unknown parameter and each
    of ``bad_params`` give a one-line :class:`TopolocError`.

    Raises
    ------
    AssertionError
        Naming the part of the contract that failed.
    """
    cls = type(recognizer)
    params = recognizer.get_params()
    assert set(params) == set(cls.param_names()), "get_params must list every keyword-only parameter"
    clone = cls(**params)
    assert clone.get_params() == params, "parameters must round-trip through the constructor"
    assert clone.set_params(**params) is clone, "set_params must return self"
    assert repr(clone).startswith(cls.__name__ + "("), "repr names the class"
    try:
        clone.set_params(no_such_parameter=1)
    except TopolocError as exc:
        assert "\n" not in str(exc) and "no_such_parameter" in str(exc)
    else:
        raise AssertionError("set_params must refuse an unknown parameter")
    for call in (lambda: clone.score([]), lambda: clone.encode(query, resources=resources)):
        try:
            call()
        except NotFittedError:
            pass
        else:
            raise AssertionError("using a recogniser before fit must raise NotFittedError")

    fitted = clone.fit(maps, resources=resources)
    assert fitted is clone, "fit must return self"
    expected_rows = np.unique(np.concatenate([m.places for m in maps]))
    assert np.array_equal(clone.place_ids_, expected_rows), "place_ids_ must be the sorted unique map places"
    items = clone.encode(query, resources=resources)
    assert len(items) == len(query), "encode gives one item per query image"
    S = clone.score(items)
    assert S.shape == (len(expected_rows), len(query)), f"S has shape {S.shape}"
    assert np.isfinite(S).all(), "S must be finite"
    # Orientation: rows are map places, columns queries, whatever the number of queries.
    part = clone.score(items[:3])
    assert part.shape == (len(expected_rows), min(3, len(items))), f"S of 3 queries has shape {part.shape}"
    if not clone.scores_whole_sequence:
        np.testing.assert_allclose(part, S[:, : part.shape[1]], rtol=1e-5, atol=1e-5)
        cols = np.concatenate([clone.score([it]) for it in items], axis=1)
        np.testing.assert_allclose(cols, S, rtol=1e-5, atol=1e-5, err_msg="queries must be scored independently")
    np.testing.assert_allclose(clone.similarity(query), S, rtol=1e-5, atol=1e-5,
                               err_msg="similarity must equal score(encode(query))")
    for key, value in (bad_params or {}).items():
        bad = cls(**{**params, key: value})
        try:
            bad.fit(maps, resources=resources)
        except TopolocError as exc:
            assert "\n" not in str(exc) and key in str(exc), f"bad {key}: {exc}"
        else:
            raise AssertionError(f"{cls.__name__}({key}={value!r}) must be refused")
    return S


__all__ = ["check_recognizer", "features_for_words", "word_vocabulary"]
