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
  ``resources`` an :class:`~topoloc.methods.resources.InMemoryResources` with
  default settings is used.
* ``encode(query, resources=None)`` turns a query traverse into one item per
  image (local features, a downsampled image...).  This is the per-image
  "feature extraction" and is timed separately from matching.
* ``score(items)`` returns the similarity block ``S`` of shape
  ``(len(place_ids_), len(items))``, higher = more similar.  The evaluation
  times it query by query; methods that need the whole query sequence at once
  (SeqSLAM) set ``scores_whole_sequence = True`` and are timed as total / n.
* ``similarity(query)`` is ``score(encode(query))``.
* A keyword-only ``confidence`` parameter (``"margin"`` by default, or
  ``"raw"``) says whether ``score`` returns the method's own scores or
  shifts each query's column so that its best score is a confidence
  comparable across queries (:mod:`topoloc.confidence`); a method applies
  it with ``_confident(S)`` at the end of ``score``.

Subclasses implement ``_fit``, ``_encode`` and ``score``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, Self

import numpy as np

from topoloc._params import Constraint, convert_param, keyword_defaults, validate_params
from topoloc.confidence import apply_confidence
from topoloc.datasets.traverse import Traverse
from topoloc.errors import NotFittedError, TopolocError
from topoloc.io.state import object_state, restore_state
from topoloc.methods.resources import InMemoryResources, Resources
from topoloc.methods.shards import ShardPart, check_parts, shard_maps


class PlaceRecognizer(ABC):
    """Base class of all methods; see the module docstring for the contract."""

    name: ClassVar[str] = ""
    uses_vocabulary: ClassVar[bool] = False
    scores_whole_sequence: ClassVar[bool] = False
    #: What each keyword-only parameter accepts (see :mod:`topoloc._params`).
    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {}
    #: Parameters added after maps were first saved, with the value that reproduces
    #: how such a map scored before (a saved map without them loads with these; a key
    #: the method does not have is ignored).  A map saved before ``confidence``
    #: existed scored, and was calibrated, on raw scores.
    legacy_defaults: ClassVar[Mapping[str, Any]] = {"confidence": "raw"}

    place_ids_: np.ndarray
    resources_: Resources

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

    @abstractmethod
    def score(self, items: Sequence[Any]) -> np.ndarray:
        """Similarity block of shape (n_map_places, len(items)), higher = more similar."""

    def similarity(self, query: Traverse, *, resources: Resources | None = None) -> np.ndarray:
        """``S`` of shape (n_map_places, len(query)) for a query traverse: ``score(encode(query))``."""
        return self.score(self.encode(query, resources=resources))

    # -- saved maps and later tours ------------------------------------------------------------
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
        self._add_tour(tour, resources if resources is not None else self.resources_)
        return self

    def get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The learned state as JSON metadata and named arrays (what a map file stores; nothing pickled)."""
        self.check_fitted()
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
        rec._set_state(meta, arrays)
        rec.resources_ = resources if resources is not None else InMemoryResources()
        return rec

    # -- maps built from shards (see topoloc.methods.shards) ---------------------------------
    def fit_shard(self, maps: Sequence[Traverse] | Traverse, *, places: tuple[int, int], index: int = 0,
                  resources: Resources | None = None) -> ShardPart:
        """The partial model of one shard: every map tour cut to the place ids in ``[lo, hi)``.

        An independent task (:func:`topoloc.methods.shards.build_from_shards`
        runs one per shard); :meth:`from_shards` merges the parts.

        Raises
        ------
        TopolocError
            For a bad parameter, no map traverse, or a method that cannot be built from shards.
        """
        maps, res = self._checked_inputs(maps, resources)
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
        ordered = check_parts(parts, cls.name)
        rec._merge_shards(ordered, maps, res)
        rec.resources_ = res
        return rec

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
    def param_names(cls) -> list[str]:
        """Names of the keyword-only constructor parameters."""
        return list(keyword_defaults(cls))

    @classmethod
    def default_params(cls) -> dict[str, Any]:
        """The constructor parameters and their defaults."""
        return keyword_defaults(cls)

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The constructor parameters and their current values."""
        return {k: getattr(self, k) for k in self.param_names()}

    def set_params(self, **params: Any) -> Self:
        """Set constructor parameters (checked at the next ``fit``).

        Raises
        ------
        TopolocError
            For a name that is not a parameter of this method.
        """
        names = set(self.param_names())
        for key, value in params.items():
            if key not in names:
                raise TopolocError(
                    f"method {self.name!r} has no parameter {key!r} (parameters: {', '.join(sorted(names))})")
            setattr(self, key, value)
        return self

    def validate_params(self) -> None:
        """Check every parameter against :attr:`parameter_constraints` (one-line TopolocError)."""
        validate_params(self.name, self.get_params(), self.parameter_constraints)

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
