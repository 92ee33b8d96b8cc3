"""Batch localisation on a cluster: frames are described and scored by Dask workers, lines written in order.

``topoloc localize MAP FRAMES --scheduler ADDRESS`` sends batches of frames to
the workers; each worker opens the map file once (memory-mapped, so the map
file must be on a file system the workers share, at the same path), extracts
the frames' features and scores them against every place, and sends back one
score column per frame.  The sequence search, the top places and the
threshold then run here, in frame order, through
:meth:`~topoloc.maps.localizer.Localizer.step_scores`, so every output line equals
the line of a local run.  Methods that score whole sequences (SeqSLAM) keep
their last frames in the localiser and run here, one frame at a time.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from itertools import islice
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, cast

import numpy as np

from topoloc.cluster import Executor
from topoloc.datasets.frames import frame_index
from topoloc.errors import TopolocError
from topoloc.maps.frame_resources import FrameResources, describe

if TYPE_CHECKING:
    from topoloc.features import FeatureSet

# What this module needs of a map and its localiser, as protocols: the map module calls this one, so this one
# does not import it, not even for annotations (an import circle, issue #41); the map class travels with each
# batch instead.
class Map(Protocol):
    """A saved map (:class:`topoloc.maps.map.Map`): its file, recogniser and description settings."""

    @property
    def path(self) -> Path | None: ...

    @property
    def recognizer(self) -> Any: ...

    @property
    def features(self) -> Any: ...

    @property
    def vocabulary(self) -> Any: ...


class MapType(Protocol):
    """The class that opens a map file (:class:`topoloc.maps.map.Map`)."""

    def load(self, path: str | Path) -> Map: ...


class Localizer(Protocol):
    """The online localiser of a map (:class:`topoloc.maps.localizer.Localizer`)."""

    @property
    def map(self) -> Map: ...

    @property
    def verifier(self) -> Any: ...

    workers: int
    ms_overlap: float

    def step(self, image: np.ndarray, *, name: str = "", time_s: float | None = None,
             index: int | None = None) -> dict[str, Any]: ...

    def step_scores(self, col: np.ndarray, *, name: str = "", time_s: float | None = None,
                    ms_features: float = 0.0, ms_matching: float = 0.0,
                    features: FeatureSet | None = None, index: int | None = None) -> dict[str, Any]: ...

BATCH_FRAMES = 16
"""Frames per task: SIFT describes 15.5 frames of 640 x 480 per second and thread
(``docs/results/performance.md``, from ``benchmarks/bench_performance.py``), so a task is about a second,
and the frames held in memory at once stay at ``2 x worker threads x 16``."""


@dataclass(frozen=True)
class FrameBatch:
    """Frames to score on a worker: the map file (with its size and mtime, so a rewritten map is refused).

    ``map_type`` is the class whose ``load`` opens the file (:class:`~topoloc.maps.map.Map`);
    ``keep_features``: also send back each frame's local features (the localiser verifies).
    """

    map_file: str
    stamp: tuple[int, int]
    first: int
    frames: tuple[np.ndarray, ...]
    map_type: MapType
    keep_features: bool = False


_maps: dict[tuple[str, tuple[int, int]], Map] = {}
_maps_lock = threading.Lock()


def _stamp(path: str | Path) -> tuple[int, int]:
    st = os.stat(path)
    return int(st.st_size), int(st.st_mtime_ns)


def _worker_map(path: str, stamp: tuple[int, int], map_type: MapType) -> Map:
    """The map of ``path``, opened once per worker process."""
    with _maps_lock:
        m = _maps.get((path, stamp))
        if m is None:
            if _stamp(path) != stamp:
                raise TopolocError(f"map file changed during the run (or is not shared with the workers): {path}")
            m = _maps[(path, stamp)] = map_type.load(path)
    return m


def score_frames(batch: FrameBatch) -> list[tuple[np.ndarray, float, float, FeatureSet | None]]:
    """``(score column of shape (n_places,), ms features, ms matching, features)`` of each frame of a batch.

    The same computation as :meth:`Localizer.step` before its sequence
    search: features of the frame in memory, ``encode``, ``score``.
    """
    m = _worker_map(batch.map_file, batch.stamp, batch.map_type)
    rec = m.recognizer
    res = FrameResources(m.features, m.vocabulary)
    out = []
    for k, image in enumerate(batch.frames):
        t0 = time.perf_counter()
        items, _, _, feats = describe(rec, res, image, f"frame{batch.first + k}", keep_features=batch.keep_features)
        t1 = time.perf_counter()
        col = np.asarray(rec.score(items)[:, 0])
        out.append((col, 1e3 * (t1 - t0), 1e3 * (time.perf_counter() - t1), feats))
    return out


def localize_on(executor: Executor, loc: Localizer,
                frames: Iterator[tuple[Any, ...]], *,
                batch_frames: int = BATCH_FRAMES) -> Iterator[tuple[dict[str, Any], float]]:
    """Result lines of ``frames`` in order, scored on ``executor``'s workers; with each, seconds spent decoding.

    Parameters
    ----------
    executor : Executor
        A Dask executor (a local one works too, on threads).
    loc : Localizer
        The localiser of a map loaded from a file (``Map.load``): the workers open that file.
    frames : iterator of (name, time_s or None, image, index)
        As :meth:`topoloc.spec.InputSpec.frames` yields them (``index``, the frame's number in its
        input, is optional: without it a line's ``frame`` counts the lines).
    batch_frames : int
        Frames per task.

    Raises
    ------
    TopolocError
        If the map was not loaded from a file.
    """
    m = loc.map
    if m.path is None:
        raise TopolocError("batch localisation on a cluster needs a map loaded from a file")
    if m.recognizer.scores_whole_sequence:
        while True:
            t0 = time.perf_counter()
            item = next(frames, None)
            if item is None:
                return
            yield loc.step(item[2], name=item[0], time_s=item[1], index=frame_index(item)), time.perf_counter() - t0
    path = str(Path(m.path).resolve())
    stamp = _stamp(path)
    threads = max(1, executor.n_workers)
    loc.workers = max(loc.workers, threads)
    window = batch_frames * 2 * threads
    first = 0
    while True:
        t0 = time.perf_counter()
        chunk = list(islice(frames, window))
        decode_s = time.perf_counter() - t0
        if not chunk:
            return
        map_type = cast(MapType, type(m))
        batches = [FrameBatch(path, stamp, first + a, tuple(f[2] for f in chunk[a:a + batch_frames]), map_type,
                              keep_features=loc.verifier is not None)
                   for a in range(0, len(chunk), batch_frames)]
        first += len(chunk)
        scored = [c for part in executor.map(score_frames, batches) for c in part]
        # The batches ran side by side: the wall clock saw only 1/parallel of their summed times.
        parallel = min(threads, len(batches))
        loc.ms_overlap += sum(ms_f + ms_m for _, ms_f, ms_m, _ in scored) * (1.0 - 1.0 / parallel)
        for k, (item, (col, ms_f, ms_m, feats)) in enumerate(zip(chunk, scored, strict=True)):
            line = loc.step_scores(col, name=item[0], time_s=item[1], ms_features=ms_f, ms_matching=ms_m,
                                   features=feats, index=frame_index(item))
            yield line, decode_s if k == 0 else 0.0


__all__ = ["BATCH_FRAMES", "FrameBatch", "localize_on", "score_frames"]
