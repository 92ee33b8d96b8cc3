"""Building a recogniser from shards: one task per shard (:mod:`topoloc.methods.shards`), then one merge.

Apart from :mod:`topoloc.methods.shards` because it needs the recogniser's class
(:mod:`topoloc.methods.base`), which imports that module: kept there, the two
imported each other (issue #41).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.io.scratch import spill
from topoloc.methods.base import PlaceRecognizer, map_place_ids
from topoloc.methods.shards import ShardPart, portable, split_places

if TYPE_CHECKING:
    from topoloc.cluster import Executor
    from topoloc.resources import Resources

log = logging.getLogger(__name__)


def _shard_task(k: int, *, cls: type[PlaceRecognizer], params: Mapping[str, Any], maps: Sequence[Traverse],
                resources: Resources, ranges: Sequence[tuple[int, int]]) -> ShardPart:
    # Module level, so that Dask can pickle it by reference; the keyword arguments are the
    # executor's `common` ones, which a cluster sends to each worker once.
    rec = cls(**params)
    # Memos of this task's own: a Dask worker keeps the task's deserialised arguments and runs
    # every shard it gets with the same resources, whose memos would otherwise hold the features
    # of all of them (a worker's memory then grew with the route: 1.2 GB at 20,000 places).
    return rec.fit_shard(maps, places=ranges[k], index=k, resources=portable(resources, remote=True))



def _spilled(part: ShardPart) -> ShardPart:
    """``part`` with its arrays moved to scratch files (within ``io.scratch.spill_to``; else as it is).

    Applied to each shard as it arrives, so that the process merging them holds
    one shard's arrays in memory at a time, not the whole map's.
    """
    return dataclasses.replace(part, arrays=spill(part.arrays))


def build_from_shards(
    cls: type[PlaceRecognizer], maps: Sequence[Traverse], *, params: Mapping[str, Any] | None = None,
    resources: Resources, n_shards: int, executor: Executor | None = None,
    advance: Callable[[int], None] | None = None,
) -> PlaceRecognizer:
    """Fit ``cls`` on ``maps`` as ``n_shards`` partial models, one task each, then merge them.

    Parameters
    ----------
    cls : type of PlaceRecognizer
        The method.
    maps : sequence of Traverse
        The map tours (every shard sees every tour, cut to its places).
    params : dict, optional
        The method's parameters.
    resources : Resources
        Features, words and vocabulary; each task gets a copy without progress display.
    n_shards : int
        Number of shards ``S`` (at most one per place).
    executor : Executor, optional
        Where the shard tasks run (default: local threads, :func:`topoloc.cluster.connect`).
    advance : callable, optional
        Called with 1 as each shard finishes.

    Returns
    -------
    PlaceRecognizer
        Fitted; its state equals that of ``cls(**params).fit(maps)`` (see ``docs/map_shards.md``).
    """
    from topoloc.cluster import LocalExecutor

    params = dict(params or {})
    maps = list(maps)
    cls(**params).validate_params()  # one-line error before any task is sent
    if not maps:
        raise TopolocError("at least one map traverse is needed")
    ranges = split_places(map_place_ids(maps), n_shards)
    ex = executor if executor is not None else LocalExecutor()
    # The tours (every image of the route) are shared, so that a worker holds them once and not
    # once per queued shard (800 MB at 100,000 places).  The resources stay bound to the task:
    # Dask refuses a scattered resources object in the graph (an empty error from update_graph).
    task = functools.partial(_shard_task, cls=cls, params=params, ranges=ranges,
                             resources=portable(resources, remote=not isinstance(ex, LocalExecutor)))
    common = {"maps": maps}
    log.info("building %s from %d shards on %s", cls.name, len(ranges), ex.name)
    parts = ex.map(task, list(range(len(ranges))), advance=advance, common=common, keep=_spilled)
    return cls.from_shards(parts, maps, params=params, resources=resources)


__all__ = ["build_from_shards"]
