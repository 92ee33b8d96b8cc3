"""The contract every place-recognition method follows (scikit-learn's estimator contract).

A method is a class with keyword-only parameters, validated in one place
(:attr:`PlaceRecognizer.parameter_constraints`, checked at the start of
``fit``), with ``get_params``/``set_params``/``repr``:

* ``fit(maps, resources=None)`` learns from one or more map traverses of the
  same places and returns ``self``; learned state lives in attributes ending
  in ``_``, in particular ``place_ids_`` (sorted unique map place ids: the
  rows of ``S``) and ``resources_`` (where its features came from, reused by
  ``encode``).  A traverse may hold image files, images in memory, features
  or word ids (:class:`~topoloc.datasets.traverse.Traverse`); without
  ``resources`` an :class:`~topoloc.resources.InMemoryResources` with
  default settings is used.
* ``encode(query, resources=None)`` turns a query traverse into one item per
  image (local features, a downsampled image...).  This is the per-image
  "feature extraction" and is timed separately from matching.
* ``score(items)`` returns the similarity block ``S`` of shape
  ``(len(place_ids_), len(items))``, higher = more similar.  The evaluation
  times it query by query; methods that need the whole query sequence at once
  (SeqSLAM) set ``scores_whole_sequence = True`` and are timed as total / n.
  ``score`` is final: it checks the recogniser is fitted, calls the method's
  ``_score(items)`` (its own scores) and applies ``confidence`` and the shape
  check, so that no method can forget either.
* ``similarity(query)`` is ``score(encode(query))``.
* A keyword-only ``confidence`` parameter (``"margin"`` or ``"raw"``; the
  default is the method's choice) says whether ``score`` returns the method's
  own scores or shifts each query's column so that its best score is a
  confidence comparable across queries (:mod:`topoloc.confidence`); ``score``
  applies it with ``_confident(S)``, which a method may override (FAB-MAP
  keeps a posterior as it is).
* What a method can do beyond this (add tours, be built from shards, find
  the top places without ``S``...) is its :class:`RecognizerTags`
  (``cls.tags``, scikit-learn's estimator tags), derived from the hooks it
  overrides; :func:`topoloc.testing.recognizer_checks` chooses its checks
  from them.

Subclasses implement ``_fit``, ``_encode`` and ``_score``, and set ``name``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any, ClassVar, Self

import numpy as np

from topoloc._params import Configurable, Constraint, convert_param, keyword_defaults
from topoloc.confidence import apply_confidence
from topoloc.datasets.traverse import Traverse
from topoloc.errors import NotFittedError, TopolocError
from topoloc.io.state import object_state, restore_state
from topoloc.methods.shards import ShardPart, check_parts, shard_maps
from topoloc.resources import InMemoryResources, Resources


@dataclass(frozen=True)
class RecognizerTags:
    """What a recogniser can do beyond the contract (scikit-learn's estimator tags).

    Read them as ``cls.tags`` (or ``rec.tags``).  They are derived when the
    class is defined: the first two from the class attributes of the same
    name, the abilities from the hooks the class overrides; a class corrects
    what the hooks cannot show with ``tag_overrides`` (e.g.
    ``{"adds_places": False}``).  :func:`topoloc.testing.recognizer_checks`
    chooses its checks from them, and a map refuses what its method cannot do
    before any image is read.

    Attributes
    ----------
    uses_vocabulary : bool
        ``fit`` needs resources with a visual vocabulary (class attribute
        ``uses_vocabulary``).
    uses_local_features : bool
        The method reads the local features of the run's feature settings
        (``resources.features``/``words``), so those settings and the
        photometric preprocessing decide its scores (class attribute
        ``uses_local_features``, true unless a method says otherwise; a method
        with a vocabulary uses local features).  Reports show the feature
        settings only for methods that use them.
    scores_whole_sequence : bool
        A column of ``S`` depends on the queries before it, so ``score`` is
        given the whole query sequence (class attribute ``scores_whole_sequence``).
    verifies_geometry : bool
        The method's own score already counts the inliers of a geometric check
        of its candidates (class attribute ``verifies_geometry``): the
        verification stage (:mod:`topoloc.verification`) is then not added by
        default, only when asked.
    saves_state : bool
        ``get_state``/``from_state`` restore the fitted model (a saved map);
        the default ``_get_state`` saves every learned attribute that is JSON,
        an array or sparse.
    adds_tours : bool
        ``add_tour`` extends a fitted map (the class overrides ``_add_tour``).
    adds_places : bool
        An added tour may visit places the map has not seen (new rows of
        ``S``); by default as ``adds_tours``.
    adds_tours_exactly : bool
        ``fit(A).add_tour(B)`` scores exactly as ``fit([A, B])``; by default as
        ``adds_tours``.
    builds_shards : bool
        ``fit_shard``/``from_shards`` build the one-piece model bit for bit
        (the class overrides ``_fit_shard`` and ``_merge_shards``).
    scores_top_k : bool
        A ``top_k(items, k)`` method gives each query's best rows and scores
        without forming ``S`` (the class defines ``top_k``).
    """

    uses_vocabulary: bool = False
    uses_local_features: bool = True
    scores_whole_sequence: bool = False
    verifies_geometry: bool = False
    saves_state: bool = True
    adds_tours: bool = False
    adds_places: bool = False
    adds_tours_exactly: bool = False
    builds_shards: bool = False
    scores_top_k: bool = False


# Tags that only a class attribute declares, so that there is one way to say each.
_ATTRIBUTE_TAGS = ("uses_vocabulary", "uses_local_features", "scores_whole_sequence", "verifies_geometry")


class PlaceRecognizer(Configurable, ABC):
    """Base class of all methods; see the module docstring for the contract."""

    #: The registry name (``get_method(name)``, ``--method``); a class without one is not registered.
    name: ClassVar[str] = ""
    uses_vocabulary: ClassVar[bool] = False
    #: False for a method that never reads local features (its own per-image work, or descriptors from elsewhere).
    uses_local_features: ClassVar[bool] = True
    scores_whole_sequence: ClassVar[bool] = False
    #: True for a method whose score already counts RANSAC inliers of its candidates (see :class:`RecognizerTags`).
    verifies_geometry: ClassVar[bool] = False
    #: The class's abilities, derived when it is defined (see :class:`RecognizerTags`).
    tags: ClassVar[RecognizerTags] = RecognizerTags()
    #: Tags the hooks cannot show, e.g. an ``add_tour`` that refuses new places.
    tag_overrides: ClassVar[Mapping[str, bool]] = {}
    #: What each keyword-only parameter accepts (see :mod:`topoloc._params`).
    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {}
    #: Parameters added after maps were first saved, with the value that reproduces
    #: how such a map scored before (a saved map without them loads with these; a key
    #: the method does not have is ignored).  A map saved before ``confidence``
    #: existed scored, and was calibrated, on raw scores.
    legacy_defaults: ClassVar[Mapping[str, Any]] = {"confidence": "raw"}

    place_ids_: np.ndarray
    resources_: Resources

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls.tags = _derive_tags(cls)

    # -- the contract ---------------------------------------------------------------------
    def _checked_inputs(self, maps: Traverse | Sequence[Traverse],
                        resources: Resources | None) -> tuple[list[Traverse], Resources]:
        """Parameters validated, the map traverses as a list and the resources (in memory by default).

        Raises
        ------
        TopolocError
            For a bad parameter, no map traverse, or a method that needs a
            vocabulary the resources lack.
        """
        self.validate_params()
        maps = [maps] if isinstance(maps, Traverse) else list(maps)
        if not maps:
            raise TopolocError(f"{self.name}: at least one map traverse is needed")
        res = resources if resources is not None else InMemoryResources()
        if self.uses_vocabulary and not res.has_vocabulary:
            raise TopolocError(f"method {self.name!r} needs a visual vocabulary")
        return maps, res

    def fit(self, maps: Sequence[Traverse] | Traverse, *, resources: Resources | None = None) -> Self:
        """Learn the map from one or more traverses of the same places.

        Parameters
        ----------
        maps : Traverse or sequence of Traverse
            The map tours (folders, or in-memory traverses).
        resources : Resources, optional
            Where features, words and the vocabulary come from (default: in
            memory, default feature settings, no vocabulary).

        Returns
        -------
        self

        Raises
        ------
        TopolocError
            For a bad parameter (one line naming it), no map traverse, or a
            method that needs a vocabulary the resources lack.
        """
        maps, res = self._checked_inputs(maps, resources)
        self._fit(maps, res)
        self.resources_ = res
        return self

    def encode(self, query: Traverse, *, resources: Resources | None = None) -> list[Any]:
        """Per-image query representation (timed as feature extraction).

        ``resources`` defaults to the ones the map was fitted with (same
        features, same vocabulary).
        """
        self.check_fitted()
        return self._encode(query, resources if resources is not None else self.resources_)

    def score(self, items: Sequence[Any]) -> np.ndarray:
        """Similarity block of shape (n_map_places, len(items)), higher = more similar.

        The method's own scores (``_score``) after its ``confidence`` mode;
        subclasses implement ``_score``, not this.

        Raises
        ------
        NotFittedError
            Before ``fit``.
        """
        self.check_fitted()
        return self._check_block(self._confident(self._score(items)), len(items))

    @abstractmethod
    def _score(self, items: Sequence[Any]) -> np.ndarray:
        """The method's own scores of ``items`` (from ``encode``), shape (n_map_places, len(items)).

        Called by :meth:`score` once the recogniser is known to be fitted;
        ``confidence`` is applied to what it returns.
        """

    def similarity(self, query: Traverse, *, resources: Resources | None = None) -> np.ndarray:
        """``S`` of shape (n_map_places, len(query)) for a query traverse: ``score(encode(query))``."""
        return self.score(self.encode(query, resources=resources))

    # -- saved maps and later tours ------------------------------------------------------------
    @property
    def add_tour_refits(self) -> bool:
        """Whether :meth:`add_tour` on these parameters scores otherwise than fitting on all tours.

        A map (:meth:`topoloc.Map.add_tour`) then refits the method on its
        earlier tours and the new one, so that the map is the same however its
        tours came in (issue 27).  By default: when the method cannot add
        tours exactly (``tags.adds_tours_exactly``) but can add them.
        """
        return self.tags.adds_tours and not self.tags.adds_tours_exactly

    def add_tour(self, tour: Traverse, *, resources: Resources | None = None) -> Self:
        """Add a further tour to the fitted map without revisiting the earlier images.

        Each method updates its model the way its paper does (see the
        method's ``_add_tour``); places the map has not seen become new rows of
        ``S`` (in sorted place-id order) where the method can add places.

        Raises
        ------
        TopolocError
            If the method cannot add this tour (e.g. new places to a landmark map).
        """
        self.check_fitted()
        if not self.tags.adds_tours:
            raise TopolocError(f"method {self.name!r} cannot add tours to a fitted map: build it from all tours")
        self._add_tour(tour, resources if resources is not None else self.resources_)
        return self

    def get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The learned state as JSON metadata and named arrays (what a map file stores; nothing pickled)."""
        self.check_fitted()
        if not self.tags.saves_state:
            raise TopolocError(f"method {self.name!r} cannot save its fitted model")
        return self._get_state()

    @classmethod
    def from_state(
        cls, params: Mapping[str, Any], meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray], *,
        resources: Resources | None = None,
    ) -> Self:
        """A fitted recogniser from ``get_state()``'s output and its parameters.

        ``resources`` are those ``encode`` will use (default: in memory, default settings).
        """
        rec = cls(**params)
        rec.validate_params()
        # Set first, so that a state can be checked against the resources (a vocabulary's size).
        rec.resources_ = resources if resources is not None else InMemoryResources()
        rec._set_state(meta, arrays)
        return rec

    # -- maps built from shards (see topoloc.methods.shards) ---------------------------------
    def fit_shard(self, maps: Sequence[Traverse] | Traverse, *, places: tuple[int, int], index: int = 0,
                  resources: Resources | None = None) -> ShardPart:
        """The partial model of one shard: every map tour cut to the place ids in ``[lo, hi)``.

        An independent task (:func:`topoloc.methods.shard_build.build_from_shards`
        runs one per shard); :meth:`from_shards` merges the parts.

        Raises
        ------
        TopolocError
            For a bad parameter, no map traverse, or a method that cannot be built from shards.
        """
        maps, res = self._checked_inputs(maps, resources)
        self._check_builds_shards()
        subs, positions = shard_maps(maps, places)
        meta, arrays = self._fit_shard(maps, subs, positions, res)
        return ShardPart(index=int(index), places=(int(places[0]), int(places[1])), positions=positions,
                         meta=meta, arrays=arrays)

    @classmethod
    def from_shards(cls, parts: Sequence[ShardPart], maps: Sequence[Traverse] | Traverse, *,
                    params: Mapping[str, Any] | None = None, resources: Resources | None = None) -> Self:
        """One fitted recogniser from the shards' partial models, equal to fitting on ``maps`` in one piece.

        Parameters
        ----------
        parts : sequence of ShardPart
            One per shard (any order), from :meth:`fit_shard` on the same ``maps``.
        maps : sequence of Traverse
            The map tours (their places and image counts; landmarks and
            FAB-MAP also finish their model from them here).
        params : dict, optional
            The method's parameters (those the shards were built with).
        resources : Resources, optional
            Kept for ``encode``, as in ``fit``.
        """
        rec = cls(**(params or {}))
        rec.validate_params()
        maps = [maps] if isinstance(maps, Traverse) else list(maps)
        res = resources if resources is not None else InMemoryResources()
        rec._check_builds_shards()
        ordered = check_parts(parts, cls.name)
        rec._merge_shards(ordered, maps, res)
        rec.resources_ = res
        return rec

    def _check_builds_shards(self) -> None:
        if not self.tags.builds_shards:
            raise TopolocError(f"method {self.name!r} cannot be built from shards: build it in one piece")

    def _fit_shard(self, maps: list[Traverse], shard: list[Traverse], positions: np.ndarray,
                   resources: Resources) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The shard's partial model from the tours cut to its places (``shard``); default: none."""
        raise TopolocError(f"method {self.name!r} cannot be built from shards: build it in one piece")

    def _merge_shards(self, parts: list[ShardPart], maps: list[Traverse], resources: Resources) -> None:
        raise TopolocError(f"method {self.name!r} cannot be built from shards: build it in one piece")

    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """Default: every learned attribute (name ending in ``_``) that is JSON, an array or sparse."""
        names = [k for k in vars(self) if k.endswith("_") and not k.startswith("_") and k != "resources_"]
        return object_state(self, only=names)

    def _set_state(self, meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> None:
        restore_state(self, meta, arrays)

    def _add_tour(self, tour: Traverse, resources: Resources) -> None:
        raise TopolocError(f"method {self.name!r} cannot add tours to a fitted map: build it from all tours")

    @abstractmethod
    def _fit(self, maps: list[Traverse], resources: Resources) -> None:
        """Learn the map; parameters are already validated."""

    @abstractmethod
    def _encode(self, query: Traverse, resources: Resources) -> list[Any]:
        """Per-image query items."""

    # -- parameters (scikit-learn style) ----------------------------------------------------
    @classmethod
    def param_owner(cls) -> str:
        """The method's name, which starts its parameter errors (``"coocmap: top_k must be ..."``)."""
        return cls.name

    @classmethod
    def _unknown_owner(cls) -> str:
        return f"method {cls.name!r}"

    @classmethod
    def default_params(cls) -> dict[str, Any]:
        """The constructor parameters and their defaults."""
        return keyword_defaults(cls)

    def __repr__(self) -> str:
        defaults = self.default_params()
        changed = [f"{k}={v!r}" for k, v in self.get_params().items() if not _same(v, defaults.get(k))]
        return f"{type(self).__name__}({', '.join(changed)})"

    # -- helpers for subclasses ---------------------------------------------------------------
    def check_fitted(self) -> None:
        """Raise :class:`NotFittedError` unless ``fit`` has been called."""
        if not hasattr(self, "place_ids_"):
            raise NotFittedError(f"{type(self).__name__} is not fitted yet: call fit() first")

    def _confident(self, S: np.ndarray) -> np.ndarray:
        """``S`` after the method's ``confidence`` mode (:func:`topoloc.confidence.apply_confidence`).

        ``confidence="margin"`` shifts each column by the best score outside
        the best place's peak (same order within a column, a best score that
        thresholds across queries); ``"raw"`` (and a method without the
        parameter) keeps the method's own scores.
        """
        return apply_confidence(S, getattr(self, "confidence", "raw"), owner=self.name)

    def _check_block(self, S: np.ndarray, n_items: int) -> np.ndarray:
        expected = (len(self.place_ids_), n_items)
        if S.shape != expected:
            raise AssertionError(f"{self.name}: S has shape {S.shape}, expected {expected}")
        return S


def _overrides(cls: type[PlaceRecognizer], hook: str) -> bool:
    return getattr(cls, hook) is not getattr(PlaceRecognizer, hook)


def _derive_tags(cls: type[PlaceRecognizer]) -> RecognizerTags:
    """The tags of a recogniser class: its class attributes, its hooks, then its ``tag_overrides``.

    Raises
    ------
    TypeError
        For an unknown tag, a tag that a class attribute declares, or an
        ability claimed without the hook that provides it (at class definition,
        rather than far from the cause when a map is built).
    """
    adds = _overrides(cls, "_add_tour")
    shards = _overrides(cls, "_fit_shard") and _overrides(cls, "_merge_shards")
    top_k = callable(getattr(cls, "top_k", None))
    if cls.uses_vocabulary and not cls.uses_local_features:
        raise TypeError(f"{cls.__name__}: a method with a vocabulary quantises local features "
                        "(uses_vocabulary needs uses_local_features)")
    derived = {"uses_vocabulary": bool(cls.uses_vocabulary), "uses_local_features": bool(cls.uses_local_features),
               "scores_whole_sequence": bool(cls.scores_whole_sequence),
               "verifies_geometry": bool(cls.verifies_geometry),
               "saves_state": True, "adds_tours": adds, "adds_places": adds, "adds_tours_exactly": adds,
               "builds_shards": shards, "scores_top_k": top_k}
    names = {f.name for f in fields(RecognizerTags)}
    for key in cls.tag_overrides:
        if key not in names:
            raise TypeError(f"{cls.__name__}.tag_overrides: unknown tag {key!r} (tags: {', '.join(sorted(names))})")
        if key in _ATTRIBUTE_TAGS:
            raise TypeError(f"{cls.__name__}.tag_overrides: declare {key!r} with the class attribute of that name")
    tags = RecognizerTags(**{**derived, **{k: bool(v) for k, v in cls.tag_overrides.items()}})
    for tag, has_hook in (("adds_tours", adds), ("adds_places", adds), ("adds_tours_exactly", adds),
                          ("builds_shards", shards), ("scores_top_k", top_k)):
        if getattr(tags, tag) and not has_hook:
            raise TypeError(f"{cls.__name__} claims {tag!r} without the hook that provides it")
    return tags


def _same(a: Any, b: Any) -> bool:
    try:
        return bool(a == b) and type(a) is type(b)
    except (TypeError, ValueError):
        return False


def map_place_ids(maps: Sequence[Traverse]) -> np.ndarray:
    """Sorted unique place ids over all map traverses (the rows of ``S``)."""
    if not maps:
        raise TopolocError("at least one map traverse is needed")
    return np.unique(np.concatenate([m.places for m in maps]))


def extend_place_ids(place_ids: np.ndarray, places: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Place ids after a tour visiting ``places`` is added, and the new row of each old row.

    Returns
    -------
    ids : ndarray of int64, shape (n_new,)
        Sorted union of ``place_ids`` and ``places``.
    old_rows : ndarray of int64, shape (len(place_ids),)
        Row of ``ids`` holding each old place (increasing: old rows keep their order).
    """
    ids = np.union1d(place_ids, np.asarray(places, np.int64))
    return ids, np.searchsorted(ids, place_ids)


def parse_param(cls: type[PlaceRecognizer], key: str, value: str) -> Any:
    """Convert a ``--param KEY=VALUE`` string to the type of the parameter's default."""
    return convert_param(cls.name, cls, key, value)
