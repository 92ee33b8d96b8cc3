"""Test helpers: exact stand-in vocabularies, hand-made features, and the recogniser contract check.

Like scikit-learn's ``check_estimator``, :func:`check_recognizer` runs the
contract of :mod:`topoloc.methods.base` against one recogniser, so that a new
method (ours or a user's) can be checked with one call.  The contract is a
set of named checks (:func:`recognizer_checks`, chosen by the recogniser's
tags: a method that cannot add tours is checked to refuse them); the test
suite makes one pytest case of each check of each registered method with
:func:`parametrize_with_checks`.  :func:`word_vocabulary` and
:func:`features_for_words` let a test state visual words directly: word ``w``
is the descriptor ``scale * e_w``, and the vocabulary's centres are exactly
those vectors, so quantisation returns the words given.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.datasets.traverse import Traverse
from topoloc.errors import NotFittedError, TopolocError
from topoloc.features import FeatureSet
from topoloc.methods.base import PlaceRecognizer
from topoloc.methods.shards import shard_traverse, split_places
from topoloc.resources import Resources
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


@dataclass(frozen=True)
class CheckData:
    """What the recogniser checks fit and score with.

    Attributes
    ----------
    maps : sequence of Traverse
        The map tours (the first is cut in two by the ``add_tour`` check, so it
        should visit several places).
    query : Traverse
        Query images (more than three).
    resources : Resources
        Shared by every check (so in-memory resources compute each traverse's
        features once).
    tour : Traverse, optional
        A further tour of the same places for ``add_tour`` and the shards
        (default: none; the ``add_tour`` check then adds the first map tour's
        second half).
    bad_params : dict
        Parameter values the recogniser must refuse with a one-line error naming them.
    """

    maps: Sequence[Traverse]
    query: Traverse
    resources: Resources
    tour: Traverse | None = None
    bad_params: Mapping[str, Any] = field(default_factory=dict)


#: A check: ``check(recognizer, data)`` raises AssertionError naming the part of the contract that failed.
RecognizerCheck = Callable[[PlaceRecognizer, CheckData], Any]


def _clone(rec: PlaceRecognizer) -> PlaceRecognizer:
    return type(rec)(**rec.get_params())


def _fitted(rec: PlaceRecognizer, data: CheckData, maps: Sequence[Traverse] | None = None) -> PlaceRecognizer:
    return _clone(rec).fit(list(maps if maps is not None else data.maps), resources=data.resources)


def _refuses(call: Callable[[], Any], what: str, *words: str) -> None:
    try:
        call()
    except TopolocError as exc:
        assert "\n" not in str(exc), f"{what}: the error must be one line: {exc}"
        for w in words:
            assert w in str(exc), f"{what}: the error must name {w!r}: {exc}"
    else:
        raise AssertionError(f"{what} must raise TopolocError")


def check_params(rec: PlaceRecognizer, data: CheckData) -> None:
    """Parameters round-trip through the constructor, ``get_params``/``set_params`` and show in ``repr``.

    An unknown parameter and each of ``data.bad_params`` give a one-line
    :class:`TopolocError` naming it.
    """
    cls = type(rec)
    params = rec.get_params()
    assert set(params) == set(cls.param_names()), "get_params must list every keyword-only parameter"
    clone = cls(**params)
    assert clone.get_params() == params, "parameters must round-trip through the constructor"
    assert clone.set_params(**params) is clone, "set_params must return self"
    assert repr(clone).startswith(cls.__name__ + "("), "repr names the class"
    _refuses(lambda: clone.set_params(no_such_parameter=1), "set_params(no_such_parameter=1)", "no_such_parameter")
    for key, value in data.bad_params.items():
        bad = cls(**{**params, key: value})
        _refuses(lambda bad=bad: bad.fit(list(data.maps), resources=data.resources),  # type: ignore[misc]
                 f"{cls.__name__}({key}={value!r}).fit", key)


def check_not_fitted(rec: PlaceRecognizer, data: CheckData) -> None:
    """Scoring or encoding before ``fit`` raises :class:`NotFittedError`."""
    clone = _clone(rec)
    for call in (lambda: clone.score([]), lambda: clone.encode(data.query, resources=data.resources)):
        try:
            call()
        except NotFittedError:
            pass
        else:
            raise AssertionError("using a recogniser before fit must raise NotFittedError")


def check_fit(rec: PlaceRecognizer, data: CheckData) -> None:
    """``fit`` returns self, keeps the parameters, sets ``place_ids_``; public learned attributes end in ``_``."""
    clone = _clone(rec)
    params = clone.get_params()
    before = set(vars(clone))
    fitted = clone.fit(list(data.maps), resources=data.resources)
    assert fitted is clone, "fit must return self"
    assert _same_params(clone.get_params(), params), "fit must not change the parameters"
    expected = np.unique(np.concatenate([m.places for m in data.maps]))
    assert np.array_equal(clone.place_ids_, expected), "place_ids_ must be the sorted unique map places"
    new = sorted(k for k in set(vars(clone)) - before if not k.startswith("_") and not k.endswith("_"))
    assert not new, f"attributes learned by fit must end in '_': {new}"


class _NoLocalFeatures:
    """``data.resources`` for a method that says it reads no local features: reading them fails the check."""

    def __init__(self, inner: Resources) -> None:
        self._inner = inner

    def __getattr__(self, name: str) -> Any:
        if name in {"features", "words", "training_words", "vocabulary", "extractor"}:
            raise AssertionError(f"uses_local_features is False but the method reads resources.{name}")
        return getattr(self._inner, name)


def check_reads_no_local_features(rec: PlaceRecognizer, data: CheckData) -> None:
    """A method whose ``uses_local_features`` is false fits and scores without reading local features.

    Reports leave out the feature settings of such a method's runs, so the tag must be true.
    """
    res: Any = _NoLocalFeatures(data.resources)
    clone = _clone(rec).fit(list(data.maps), resources=res)
    clone.score(clone.encode(data.query, resources=res))


def check_scores(rec: PlaceRecognizer, data: CheckData) -> np.ndarray:
    """``S`` of shape (n_map_places, n_queries), floating and finite, consistent with ``encode``; returns ``S``.

    Queries are scored independently (any subset gives the same columns) unless
    the method scores whole sequences, and ``similarity`` equals
    ``score(encode(...))``.
    """
    clone = _fitted(rec, data)
    rows = len(clone.place_ids_)
    items = clone.encode(data.query, resources=data.resources)
    assert len(items) == len(data.query), "encode gives one item per query image"
    S = clone.score(items)
    assert S.shape == (rows, len(data.query)), f"S has shape {S.shape}, expected {(rows, len(data.query))}"
    assert np.issubdtype(S.dtype, np.floating), f"S must be floating, not {S.dtype}"
    assert np.isfinite(S).all(), "S must be finite"
    # Orientation: rows are map places, columns queries, whatever the number of queries.
    part = clone.score(items[:3])
    assert part.shape == (rows, min(3, len(items))), f"S of 3 queries has shape {part.shape}"
    assert clone.score([]).shape == (rows, 0), "no query gives an empty block"
    if not clone.tags.scores_whole_sequence:
        np.testing.assert_allclose(part, S[:, : part.shape[1]], rtol=1e-5, atol=1e-5)
        cols = np.concatenate([clone.score([it]) for it in items], axis=1)
        np.testing.assert_allclose(cols, S, rtol=1e-5, atol=1e-5, err_msg="queries must be scored independently")
    np.testing.assert_allclose(clone.similarity(data.query, resources=data.resources), S, rtol=1e-5, atol=1e-5,
                               err_msg="similarity must equal score(encode(query))")
    return S


def check_whole_sequence(rec: PlaceRecognizer, data: CheckData) -> None:
    """A method that scores whole sequences is causal: the first queries score as in the whole sequence.

    (Online localisation scores the last frames only, :class:`topoloc.maps.Localizer`.)
    """
    clone = _fitted(rec, data)
    items = clone.encode(data.query, resources=data.resources)
    S = clone.score(items)
    m = max(1, len(items) // 2)
    np.testing.assert_allclose(clone.score(items[:m]), S[:, :m], rtol=1e-5, atol=1e-5,
                               err_msg="a query's column must not depend on later queries")


def check_confidence(rec: PlaceRecognizer, data: CheckData) -> None:
    """``confidence="margin"`` keeps each column's ranking of ``"raw"`` and a best score >= 0; a bad mode is refused.

    The margin is :func:`topoloc.confidence.peak_margin` of the raw scores, or
    the raw scores themselves where they already are a confidence (FAB-MAP's posterior).
    """
    from topoloc.confidence import peak_margin

    params = rec.get_params()
    raw = _fitted(type(rec)(**{**params, "confidence": "raw"}), data).similarity(data.query, resources=data.resources)
    margin = _fitted(type(rec)(**{**params, "confidence": "margin"}), data).similarity(data.query,
                                                                                        resources=data.resources)
    if not np.array_equal(margin, raw):
        np.testing.assert_allclose(margin, peak_margin(raw), rtol=1e-6, atol=1e-6,
                                   err_msg='confidence="margin" must be the peak margin of the raw scores')
    assert np.array_equal(np.argsort(-margin, axis=0, kind="stable"), np.argsort(-raw, axis=0, kind="stable")), \
        "the confidence must keep each column's ranking"
    assert (margin.max(axis=0) >= 0).all(), "a margin's best score is >= 0"
    bad = type(rec)(**{**params, "confidence": "ratio"})
    _refuses(lambda: bad.fit(list(data.maps), resources=data.resources), 'confidence="ratio"', "confidence")


def check_state_round_trip(rec: PlaceRecognizer, data: CheckData) -> None:
    """``get_state`` through a memory-mapped container and ``from_state`` give the same ``S``, bit for bit.

    The same query items are scored by both (a restored map may encode
    differently on purpose: ``descriptors`` forgets the query file of its build).
    """
    fitted = _fitted(rec, data)
    items = fitted.encode(data.query, resources=data.resources)
    back = _through_container(fitted, data)
    np.testing.assert_array_equal(back.place_ids_, fitted.place_ids_)
    np.testing.assert_array_equal(back.score(items), fitted.score(items),
                                  err_msg="a restored state must score as the fitted recogniser")


def check_add_tour(rec: PlaceRecognizer, data: CheckData) -> None:
    """A tour added to a fitted (and saved) map gives a valid map covering both tours' places.

    Where the tags say so: equal to fitting on both tours (``adds_tours_exactly``),
    new places become rows (``adds_places``), or a tour with places the map
    lacks is refused with a one-line error (not ``adds_places``).
    """
    tags = rec.tags
    first, later_part = _halves(data.maps[0])
    tour = data.tour if data.tour is not None else later_part
    lo, hi = int(first.places.min()), int(first.places.max()) + 1
    extra = tour if tags.adds_places else shard_traverse(tour, (lo, hi))[0]
    old = _fitted(rec, data, [first])
    items = old.encode(data.query, resources=data.resources)
    if tags.saves_state:  # as `topoloc map add` does: the map was saved, then loaded
        old = _through_container(old, data)
    grown = old.add_tour(extra, resources=data.resources)
    assert grown is old, "add_tour must return self"
    expected = np.union1d(first.places, extra.places)
    np.testing.assert_array_equal(grown.place_ids_, expected, err_msg="place_ids_ must cover both tours")
    S = grown.score(items)
    assert S.shape == (len(expected), len(data.query)) and np.isfinite(S).all(), "S after add_tour"
    if tags.adds_tours_exactly:
        both = _fitted(rec, data, [first, extra])
        np.testing.assert_array_equal(S, both.score(items),
                                      err_msg="fit(A).add_tour(B) must score as fit([A, B])")
    if not tags.adds_places and len(np.setdiff1d(tour.places, first.places)):
        fresh = _fitted(rec, data, [first])
        _refuses(lambda: fresh.add_tour(tour, resources=data.resources), "add_tour of a tour with new places")


def check_refuses_tours(rec: PlaceRecognizer, data: CheckData) -> None:
    """A method without ``add_tour`` refuses it with a one-line error."""
    fitted = _fitted(rec, data)
    _refuses(lambda: fitted.add_tour(data.maps[0], resources=data.resources), "add_tour", "cannot add tours")


def check_shards(rec: PlaceRecognizer, data: CheckData) -> None:
    """A map merged from 3 shards (given in any order) equals the one-piece fit, state bit for bit."""
    cls = type(rec)
    maps = [*data.maps, *([data.tour] if data.tour is not None else [])]
    whole = _fitted(rec, data, maps)
    ranges = split_places(whole.place_ids_, 3)
    parts = [_clone(rec).fit_shard(maps, places=r, index=k, resources=data.resources) for k, r in enumerate(ranges)]
    merged = cls.from_shards(parts[::-1], maps, params=rec.get_params(), resources=data.resources)
    (meta_a, arrays_a), (meta_b, arrays_b) = merged.get_state(), whole.get_state()
    assert meta_a == meta_b, "shards: the merged metadata must equal the one-piece fit's"
    assert sorted(arrays_a) == sorted(arrays_b), "shards: the merged state must hold the same arrays"
    for name, a in arrays_a.items():
        x, y = np.asarray(a), np.asarray(arrays_b[name])
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), \
            f"shards: array {name!r} differs from the one-piece fit's"
    np.testing.assert_array_equal(merged.similarity(data.query, resources=data.resources),
                                  whole.similarity(data.query, resources=data.resources))


def check_refuses_shards(rec: PlaceRecognizer, data: CheckData) -> None:
    """A method without shards refuses ``fit_shard`` with a one-line error."""
    ids = np.unique(np.concatenate([m.places for m in data.maps]))
    _refuses(lambda: _clone(rec).fit_shard(list(data.maps), places=(int(ids[0]), int(ids[-1]) + 1),
                                           resources=data.resources), "fit_shard", "shards")


def check_top_k(rec: PlaceRecognizer, data: CheckData) -> None:
    """``top_k(items, k)`` gives the rows and scores of the ``k`` best places of ``score`` (ties: lower row first)."""
    fitted = _fitted(rec, data)
    items = fitted.encode(data.query, resources=data.resources)
    St = fitted.score(items).T
    k = min(3, St.shape[1])
    rows, scores = fitted.top_k(items, k)  # type: ignore[attr-defined]
    want = np.argsort(-St, axis=1, kind="stable")[:, :k]
    np.testing.assert_array_equal(rows, want, err_msg="top_k rows must be those of the top of S")
    np.testing.assert_allclose(scores, np.take_along_axis(St, want, axis=1), rtol=1e-4, atol=1e-4)


def recognizer_checks(recognizer: PlaceRecognizer) -> Iterator[RecognizerCheck]:
    """The checks that apply to ``recognizer``, chosen by its tags (scikit-learn's ``generate_only``).

    Each is a function ``check(recognizer, data)`` (:class:`CheckData`) named
    after what it checks; :func:`parametrize_with_checks` makes one pytest case
    of each.
    """
    tags = recognizer.tags
    yield from (check_params, check_not_fitted, check_fit, check_scores)
    if tags.scores_whole_sequence:
        yield check_whole_sequence
    if not tags.uses_local_features:
        yield check_reads_no_local_features
    if "confidence" in recognizer.param_names():
        yield check_confidence
    if tags.saves_state:
        yield check_state_round_trip
    yield check_add_tour if tags.adds_tours else check_refuses_tours
    yield check_shards if tags.builds_shards else check_refuses_shards
    if tags.scores_top_k:
        yield check_top_k


def check_recognizer(
    recognizer: PlaceRecognizer, maps: Sequence[Traverse], query: Traverse, *, resources: Resources,
    bad_params: Mapping[str, Any] | None = None, tour: Traverse | None = None,
) -> np.ndarray:
    """Check ``recognizer`` against the contract (every check of :func:`recognizer_checks`); returns its ``S``.

    Checked: parameters round-trip through ``get_params``/``set_params`` and
    show in ``repr``; using it before ``fit`` raises :class:`NotFittedError`;
    ``fit`` returns self and sets ``place_ids_`` (sorted unique map places);
    ``S`` has shape (n_map_places, n_queries), is finite and does not depend
    on scoring queries one by one (unless the method scores whole sequences);
    ``similarity`` equals ``score(encode(...))``; an unknown parameter and each
    of ``bad_params`` give a one-line :class:`TopolocError`; and, as the tags
    say, the ``confidence`` modes, the saved state, added tours, shards and top K.

    Raises
    ------
    AssertionError
        Naming the check and the part of the contract that failed.
    """
    data = CheckData(maps=list(maps), query=query, resources=resources, tour=tour, bad_params=dict(bad_params or {}))
    S: np.ndarray | None = None
    for check in recognizer_checks(recognizer):
        try:
            out = check(recognizer, data)
        except AssertionError as exc:
            raise AssertionError(f"{type(recognizer).__name__} fails {check.__name__}: {exc}") from exc
        if check is check_scores:
            S = out
    assert S is not None
    return S


def parametrize_with_checks(recognizers: Iterable[PlaceRecognizer]) -> Any:
    """A pytest ``parametrize`` mark: one case ``(recognizer, check)`` per recogniser and check that applies.

    The test calls ``check(recognizer, data)`` with a :class:`CheckData`
    (usually from a fixture)::

        @parametrize_with_checks([MyMethod()])
        def test_my_method(recognizer, check, data):
            check(recognizer, data)
    """
    import pytest

    cases = [(rec, check) for rec in recognizers for check in recognizer_checks(rec)]
    ids = [f"{rec.name or type(rec).__name__}-{check.__name__}" for rec, check in cases]
    return pytest.mark.parametrize(("recognizer", "check"), cases, ids=ids)


def _same_params(a: Mapping[str, Any], b: Mapping[str, Any]) -> bool:
    return a.keys() == b.keys() and all(a[k] is b[k] or _equal(a[k], b[k]) for k in a)


def _equal(a: Any, b: Any) -> bool:
    try:
        return bool(a == b)
    except (TypeError, ValueError):
        return False


def _halves(tour: Traverse) -> tuple[Traverse, Traverse]:
    """The tour's images of its first and of its other places (the first half of its place ids)."""
    ids = np.unique(tour.places)
    cut = int(ids[max(1, len(ids) // 2)]) if len(ids) > 1 else int(ids[0]) + 1
    return shard_traverse(tour, (int(ids[0]), cut))[0], shard_traverse(tour, (cut, int(ids[-1]) + 1))[0]


def _through_container(rec: PlaceRecognizer, data: CheckData) -> PlaceRecognizer:
    """``rec`` saved into a container file and restored from its memory-mapped arrays."""
    from topoloc.io.container import read_container, write_container

    meta, arrays = rec.get_state()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "state.bin"
        write_container(path, "recognizer-check", 1, arrays, meta)
        meta2, arrays2 = read_container(path, "recognizer-check", 1, mmap=True)
        # Copies: the temporary file goes away with this block.
        return type(rec).from_state(rec.get_params(), meta2, {k: np.array(v) for k, v in arrays2.items()},
                                    resources=data.resources)


__all__ = [
    "CheckData", "RecognizerCheck", "check_add_tour", "check_confidence", "check_fit", "check_not_fitted",
    "check_params", "check_reads_no_local_features", "check_recognizer", "check_refuses_shards",
    "check_refuses_tours", "check_scores",
    "check_shards", "check_state_round_trip", "check_top_k", "check_whole_sequence", "features_for_words",
    "parametrize_with_checks", "recognizer_checks", "word_vocabulary",
]
