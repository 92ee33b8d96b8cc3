"""Maps built from shards: partial models of place ranges, built apart and merged into one.

A route's places (the sorted unique place ids of every map tour) are cut into
``S`` contiguous ranges (:func:`split_places`).  Shard ``k`` sees, of every
map tour, the images whose place lies in its range (:func:`shard_traverse`),
and builds a partial model from them with
:meth:`~topoloc.methods.base.PlaceRecognizer.fit_shard`; each shard is one
independent task for :meth:`topoloc.cluster.Executor.map`, so the shards run
on local threads or on a Dask cluster alike.  The partials come back as
:class:`ShardPart` (JSON metadata and named arrays, nothing pickled that a
worker could not rebuild) and
:meth:`~topoloc.methods.base.PlaceRecognizer.from_shards` merges them into one
recogniser whose saved state and scores equal those of the recogniser fitted
in one piece on the same tours (``tests/methods/test_shards.py``).

Every image keeps its *position*: its index in the concatenation of the map
tours in the order given (tour 0's images, then tour 1's...).  The methods
whose state is a list of per-image observations (bow documents, FAB-MAP
observations, voting's indexed images, SeqSLAM's vectors, global descriptors)
merge by sorting the shards' images back into that order, which is why the
merge is exact rather than "equal up to a permutation".
"""

from __future__ import annotations

import copy
import itertools
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.progress import no_progress

if TYPE_CHECKING:
    from topoloc.resources import Resources

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ShardPart:
    """The partial model of one shard, as JSON metadata and named arrays.

    Attributes
    ----------
    index : int
        Shard number ``k`` in ``0..S-1`` (shards are in place-id order).
    places : tuple of int
        The shard's place-id range ``[lo, hi)``.
    positions : ndarray of int64, shape (n_images,)
        Position of every image the shard saw in the concatenation of the map
        tours (increasing).
    meta : dict
        JSON-able metadata of the partial model (method specific).
    arrays : dict of str to ndarray
        Its arrays (method specific).
    """

    index: int
    places: tuple[int, int]
    positions: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)


def split_places(place_ids: np.ndarray, n_shards: int) -> list[tuple[int, int]]:
    """Contiguous place-id ranges ``[lo, hi)`` holding about equal numbers of places.

    Parameters
    ----------
    place_ids : ndarray of int64, shape (n_places,)
        Sorted unique place ids of the map.
    n_shards : int
        Wanted shards; at most one per place.

    Returns
    -------
    list of (lo, hi)
        ``min(n_shards, n_places)`` ranges covering every place id once, in order;
        the first starts at ``place_ids[0]``, the last ends after ``place_ids[-1]``.

    Raises
    ------
    TopolocError
        For ``n_shards < 1`` or a map without places.
    """
    if n_shards < 1:
        raise TopolocError(f"the number of shards must be at least 1, got {n_shards}")
    ids = np.asarray(place_ids, np.int64)
    if ids.size == 0:
        raise TopolocError("a map without places cannot be split into shards")
    s = min(int(n_shards), ids.size)
    cuts = [ids.size * k // s for k in range(s + 1)]
    bounds = [int(ids[c]) for c in cuts[:-1]] + [int(ids[-1]) + 1]
    return [(bounds[k], bounds[k + 1]) for k in range(s)]


def shard_traverse(traverse: Traverse, places: tuple[int, int]) -> tuple[Traverse, np.ndarray]:
    """The images of ``traverse`` whose place lies in ``[lo, hi)``, in traverse order.

    The sub-traverse keeps the tour's root and name (saved models name tours by
    it), so only its images differ.

    Returns
    -------
    sub : Traverse
    index : ndarray of int64, shape (n_kept,)
        Index in ``traverse`` of each kept image.
    """
    lo, hi = places
    index = np.flatnonzero((traverse.places >= lo) & (traverse.places < hi)).astype(np.int64)
    return traverse.take(index), index


def shard_maps(maps: Sequence[Traverse], places: tuple[int, int]) -> tuple[list[Traverse], np.ndarray]:
    """Every map tour cut to a place range, and the positions of the kept images (see the module docstring)."""
    subs, positions = [], []
    offset = 0
    for t in maps:
        sub, index = shard_traverse(t, places)
        subs.append(sub)
        positions.append(index + offset)
        offset += len(t)
    return subs, (np.concatenate(positions) if positions else np.zeros(0, np.int64)).astype(np.int64)


def merge_order(parts: Sequence[ShardPart], n_images: int) -> np.ndarray:
    """Order that sorts the shards' concatenated images back into map order.

    Raises
    ------
    TopolocError
        If the shards do not hold every map image exactly once.
    """
    pos = np.concatenate([p.positions for p in parts]) if parts else np.zeros(0, np.int64)
    order = np.argsort(pos, kind="stable")
    if len(pos) != n_images or not np.array_equal(pos[order], np.arange(n_images)):
        raise TopolocError(f"the shards hold {len(pos)} images but not each of the map's {n_images} once: "
                           "were they built from the same tours?")
    return order


def check_parts(parts: Sequence[ShardPart], name: str) -> list[ShardPart]:
    """The parts in shard order, refusing none, repeated or overlapping shards (one-line error)."""
    parts = sorted(parts, key=lambda p: p.index)
    if not parts:
        raise TopolocError(f"{name}: no shard to merge")
    if [p.index for p in parts] != list(range(len(parts))):
        raise TopolocError(f"{name}: shards {[p.index for p in parts]} are not 0..{len(parts) - 1}")
    for a, b in itertools.pairwise(parts):
        if a.places[1] > b.places[0]:
            raise TopolocError(f"{name}: shard {a.index} {a.places} overlaps shard {b.index} {b.places}")
    return parts


def portable(resources: Resources, *, remote: bool = False) -> Resources:
    """A copy of ``resources`` for the shard tasks (``Resources.for_task`` when it has one)."""
    for_task = getattr(resources, "for_task", None)
    if for_task is not None:
        return for_task(remote=remote)
    out = copy.copy(resources)
    out.progress = no_progress
    return out


__all__ = ["ShardPart", "check_parts", "merge_order", "portable", "shard_maps",
           "shard_traverse", "split_places"]
