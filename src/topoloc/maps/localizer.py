"""Online localisation against a saved map, one frame at a time, with bounded memory.

:class:`Localizer` takes camera frames (or the lines of a recording) in order
and gives one result line per frame: the recogniser's scores, the sequence
search over the last frames, the verification of the candidates, the top
places and whether the map's calibrated threshold accepts the answer.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from topoloc._parallel import n_workers
from topoloc.cluster import Executor
from topoloc.datasets.frames import frame_index
from topoloc.errors import ParameterError
from topoloc.features import FeatureConfig, FeatureSet
from topoloc.maps.frame_resources import Described, FrameResources, describe
from topoloc.maps.prefetch import ahead, prefetch_depth, single_threaded_libraries
from topoloc.methods.base import PlaceRecognizer
from topoloc.ranking import top_rows
from topoloc.spec import SequenceSpec
from topoloc.spec.runs import check_prefetch
from topoloc.verification import ConfidenceModel, VerifiedBlock, Verifier, confirmed, demote_unconfirmed
from topoloc.vocabulary import Vocabulary


# What the localiser reads of its map, as a protocol: the map module builds localisers, so this module does
# not import it, not even for annotations (an import circle, docs/architecture.md).
class LocalizedMap(Protocol):
    """A saved map (:class:`topoloc.maps.map.Map`) as the localiser uses it."""

    @property
    def path(self) -> Path | None: ...
    @property
    def recognizer(self) -> PlaceRecognizer: ...
    @property
    def features(self) -> FeatureConfig: ...
    @property
    def vocabulary(self) -> Vocabulary | None: ...
    @property
    def place_ids(self) -> np.ndarray: ...
    @property
    def place_xy(self) -> np.ndarray: ...
    @property
    def threshold(self) -> float | None: ...
    @property
    def score_confidence(self) -> ConfidenceModel | None: ...

    def accepts(self, *, score: float, confidence: float | None, is_verified: bool | None) -> bool: ...



class Localizer:
    """Online localisation against a saved map (:class:`topoloc.maps.Map`), one frame at a time, with bounded memory.

    With ``sequence = N > 0`` each frame is matched together with the ``N``
    frames before it (causal: frame ``i`` uses only frames ``<= i``), by the
    same search as ``evaluate --sequence`` on the last ``N + 1`` score
    columns, so its result equals the batch result for that frame; its
    ``score`` is then the sequence confidence (the best path's margin over
    the best path elsewhere on the route, :mod:`topoloc.sequence.confidence`),
    which :meth:`topoloc.maps.Map.calibrate_on` with the same ``sequence`` calibrates.  Methods
    that score whole sequences (SeqSLAM) keep their own last ``ds + 1`` frames.

    Parameters
    ----------
    m : LocalizedMap
    top_k : int
        Places listed per frame.
    sequence, sequence_mode
        Online sequence matching (off with 0).
    verify : bool
        Verify each frame's candidates against the map images (:mod:`topoloc.verification`):
        its line then says ``verified`` and ``inliers``, and its score is the
        verified confidence.
    confirm : bool
        Temporal consistency (:mod:`topoloc.verification.consistency`): a
        frame's answer not confirmed by the previous frame's ranks below every
        confirmed one; its line says ``confirmed``.
    candidates : int, optional
        Distinct peaks verified per frame (default: 3 for single images, the
        best place with ``sequence``: :func:`topoloc.verification.default_candidates`).
    prefetch : int
        Frames :meth:`stream` reads and describes ahead of the one being
        matched, on a pool of one thread per core (at most ``prefetch``): the
        next frames' decoding, features and quantisation run while this frame
        is matched, and the lines come out in the same order with the same
        content.  -1 (default): two per core; 0: every frame read, described
        and matched in turn on this thread.  Memory holds at most this many
        frames beyond the one being matched.
    """

    def __init__(self, m: LocalizedMap, *, top_k: int = 5, sequence: int = 0, sequence_mode: str = "constant",
                 prefetch: int = -1, verifier: Verifier | None = None, confirm: bool = False) -> None:
        if isinstance(top_k, bool) or not isinstance(top_k, int) or top_k < 1:
            raise ParameterError("top_k", f"must be a whole number >= 1, got {top_k!r}")
        check_prefetch(prefetch)
        # One-line errors naming the parameter; the last N + 1 columns it keeps are bounded too.
        SequenceSpec(length=sequence, mode=sequence_mode).check_memory(len(m.place_ids), online=True)
        self.map = m
        self.top_k = top_k
        self.sequence = sequence
        self.sequence_mode = sequence_mode
        self.prefetch = prefetch
        self.frames = 0
        self.verifier = verifier
        self.ms_verify = 0.0
        self.n_verified = 0
        self.confirm = confirm
        self._previous_best: int | None = None
        rec = m.recognizer
        self._items: deque[Any] = deque(maxlen=int(rec.get_params().get("ds", 0)) + 1)
        self._columns: deque[np.ndarray] = deque(maxlen=sequence + 1)
        # Running sums (ms over all frames so far), not lists: memory must not grow with a long recording.
        self.ms_decode = 0.0
        self.ms_features = 0.0
        self.ms_quantise = 0.0
        self.ms_matching = 0.0
        self.ms_wait = 0.0
        self.wall_s = 0.0
        self.start_s = 0.0
        self.cpu_s = 0.0
        self.workers = 1
        self.threads = 1
        self.ms_overlap = 0.0
        self._tls = threading.local()

    def describe(self, image: np.ndarray, *, name: str = "") -> Described:
        """``(items, ms features, ms quantisation, features)`` of one frame: the recogniser's ``encode``.

        ``features`` (the frame's local features, for verification) is None when
        the localiser does not verify.  Safe on any thread.
        """
        res: FrameResources | None = getattr(self._tls, "res", None)
        if res is None:  # one per thread: a feature detector is not shared between threads
            res = self._tls.res = FrameResources(self.map.features, self.map.vocabulary)
        return describe(self.map.recognizer, res, image, name, keep_features=self.verifier is not None)

    def warm_up(self, image: np.ndarray) -> float:
        """Pay a frame's first-use costs on ``image`` without answering it; the seconds it took.

        Extraction, quantisation, matching and verification run once (loading
        compiled code, creating detectors, reading what the verifier reads), so
        that the first frame of a live source is not late by them; nothing of the
        localiser's state changes (frames, sequence, timings).
        """
        t0 = time.perf_counter()
        items, _, _, features = self.describe(image)
        rec = self.map.recognizer
        col = rec.score(items[:1])[:, -1]
        if self.verifier is not None and features is not None:
            self.verifier.verify(np.asarray(col)[:, None], [features])
        return time.perf_counter() - t0

    def stream(self, frames: Iterable[tuple[Any, ...]], *,
               executor: Executor | None = None) -> Iterator[dict[str, Any]]:
        """Result lines of ``frames`` (``(name, time_s or None, image[, index])``, as :meth:`InputSpec.frames` gives).

        A frame's ``index`` (its number in its input, frames not answered leaving
        gaps) is its line's ``frame``; without one, ``frame`` counts the lines.

        On this process (``executor`` None or local) frames are read and
        described ``prefetch`` ahead on a thread pool while this thread matches
        them in order (:func:`topoloc.maps.prefetch.ahead`), so a recording is
        never held in memory; with ``prefetch=0`` one at a time.  On a Dask
        executor they are described and scored in batches by the workers
        (:func:`topoloc.maps.batch.localize_on`), with the same lines.  The
        stage times and the wall time accumulate for :meth:`summary`.
        """
        it = iter(frames)
        voc = self.map.vocabulary
        if voc is not None and self.map.recognizer.uses_vocabulary:
            # The word index (HNSW) is built on its first use, once per process like opening the map: built
            # and timed here (``s_start``), it no longer inflates the first frame's quantisation and ``fps``.
            t0 = time.perf_counter()
            voc.quantize(voc.words_[:1])
            self.start_s += time.perf_counter() - t0
        t_start, cpu_start = time.perf_counter(), time.process_time()
        try:
            if executor is not None and executor.name != "local":
                from topoloc.maps.batch import localize_on

                for line, seconds in localize_on(executor, self, it):
                    self.ms_decode += 1e3 * seconds
                    yield line
                return
            depth = prefetch_depth(self.prefetch)
            if depth == 0:
                yield from self._one_at_a_time(it)
                return
            first = self.frames

            def work(k: int, item: tuple[Any, ...]) -> Described:
                return self.describe(item[2], name=item[0] or f"frame{first + k}")

            done = ahead(it, work, depth=depth)
            self.threads = max(self.threads, min(n_workers(-1), depth))
            with single_threaded_libraries():
                try:
                    for a in done:
                        items, ms_f, ms_q, feats = a.result
                        self.ms_wait += a.wait_ms
                        yield self._match(items, name=a.item[0], time_s=a.item[1], ms_decode=a.decode_ms,
                                          ms_features=ms_f, ms_quantise=ms_q, features=feats,
                                          index=frame_index(a.item))
                finally:
                    done.close()  # stops the reader and the pool before OpenCV's threads come back
        finally:
            self.wall_s += time.perf_counter() - t_start
            self.cpu_s += time.process_time() - cpu_start

    def _one_at_a_time(self, it: Iterator[tuple[Any, ...]]) -> Iterator[dict[str, Any]]:
        while True:
            t0 = time.perf_counter()
            item = next(it, None)
            decode_ms = 1e3 * (time.perf_counter() - t0)
            if item is None:
                return
            name, time_s, frame = item[:3]
            items, ms_f, ms_q, feats = self.describe(frame, name=name or f"frame{self.frames}")
            self.ms_wait += 1e3 * (time.perf_counter() - t0)
            yield self._match(items, name=name, time_s=time_s, ms_decode=decode_ms, ms_features=ms_f,
                              ms_quantise=ms_q, features=feats, index=frame_index(item))

    def summary(self) -> dict[str, Any]:
        """Frames, frames per second and mean milliseconds per frame of each stage.

        ``ms_decode_mean`` (reading and decoding the frame), ``ms_extract_mean``
        (local features or the method's own per-image transform),
        ``ms_quantise_mean`` (visual words) and ``ms_matching_mean`` (scoring the
        frame against the map, the sequence search, the top places) are each
        frame's own time on the thread that did it; ``ms_features_mean`` is the
        first three together, as ``evaluate``'s ``ms_features`` counts decoding.
        ``fps`` is counted on the wall clock.  With prefetch (``threads``: the
        describing threads) frames are described while others are matched, so
        the stages add up to more than the wall time; ``ms_wait_mean`` is how
        long matching waited for the next frame to be described (near 0: the
        matching is the bottleneck), and the overhead is the wall time per frame
        beyond that wait and the matching (building and writing the lines).
        ``s_start`` is the time spent before the first frame, outside ``fps``:
        building the vocabulary's word index, once per process.
        ``ms_cpu_mean`` is the processor time of the whole process per frame, every
        thread together: unlike the wall clock it hardly grows when other
        processes share the cores, so ``cores * 1000 / ms_cpu_mean`` bounds the
        frames/s the same run reaches on idle cores.  On
        a cluster (``workers``: the worker threads) features and matching are
        each frame's own time on a worker, and frames run side by side, so the
        overhead is the wall time per frame less the part of that work the wall
        clock saw (``ms_overlap``, the work done alongside other frames, is
        given back); never negative.
        """
        n = max(self.frames, 1)
        match_ms = self.ms_matching / n
        decode_ms, extract_ms, quantise_ms = self.ms_decode / n, self.ms_features / n, self.ms_quantise / n
        features_ms = decode_ms + extract_ms + quantise_ms
        wall = self.wall_s
        if self.workers > 1:
            overhead = 1e3 * wall / n - features_ms - match_ms + self.ms_overlap / n
        else:
            overhead = 1e3 * wall / n - self.ms_wait / n - match_ms
        out = {"frames": self.frames, "fps": round(self.frames / wall, 2) if wall else None,
               "fps_without_features": round(1e3 / match_ms, 2) if match_ms else None,
               "ms_features_mean": round(features_ms, 2), "ms_decode_mean": round(decode_ms, 2),
               "ms_extract_mean": round(extract_ms, 2), "ms_quantise_mean": round(quantise_ms, 2),
               "ms_matching_mean": round(match_ms, 2),
               # Clock readings of different threads and machines: a few hundredths below zero is noise.
               "ms_overhead_mean": round(max(overhead, 0.0), 2),
               "calibrated": self.map.threshold is not None, "s_start": round(self.start_s, 3)}
        if self.verifier is not None:
            out["ms_verify_mean"] = round(self.ms_verify / n, 2)
            out["verified"] = self.n_verified
        if self.workers > 1:
            out["workers"] = self.workers
        else:
            out["ms_wait_mean"] = round(self.ms_wait / n, 2)
            out["threads"] = self.threads
            out["ms_cpu_mean"] = round(1e3 * self.cpu_s / n, 2)
        return out

    def step(self, image: np.ndarray, *, name: str = "", time_s: float | None = None,
             index: int | None = None) -> dict[str, Any]:
        """Localise the next frame (a NumPy image) and return its result line (:meth:`topoloc.maps.Map.localize`)."""
        items, ms_f, ms_q, feats = self.describe(image, name=name or f"frame{self.frames}")
        return self._match(items, name=name, time_s=time_s, ms_decode=0.0, ms_features=ms_f, ms_quantise=ms_q,
                           features=feats, index=index)

    def _match(self, items: list[Any], *, name: str, time_s: float | None, ms_decode: float, ms_features: float,
               ms_quantise: float, features: FeatureSet | None = None, index: int | None = None) -> dict[str, Any]:
        """The result line of the next frame from its described ``items``, in frame order."""
        rec = self.map.recognizer
        t1 = time.perf_counter()
        if rec.scores_whole_sequence:
            self._items.append(items[0])
            col = rec.score(list(self._items))[:, -1]
        else:
            col = rec.score(items)[:, 0]
        self.ms_decode += ms_decode
        self.ms_quantise += ms_quantise
        return self.step_scores(col, name=name, time_s=time_s, ms_features=ms_features,
                                ms_matching=1e3 * (time.perf_counter() - t1), features=features, index=index)

    def step_scores(self, col: np.ndarray, *, name: str = "", time_s: float | None = None,
                    ms_features: float = 0.0, ms_matching: float = 0.0,
                    features: FeatureSet | None = None, index: int | None = None) -> dict[str, Any]:
        """The result line of the next frame from its score column, shape (n_places,), computed elsewhere.

        What :meth:`step` does after scoring (the sequence search over the last
        columns, the top places, the threshold); a batch localisation scores
        frames on a cluster (:mod:`topoloc.maps.batch`) and feeds the columns
        here in frame order, so the lines are the same.
        """
        t2 = time.perf_counter()
        if self.sequence:
            from topoloc.sequence import sequence_similarity

            self._columns.append(np.asarray(col, np.float32))
            window = np.stack(self._columns, axis=1)
            col = sequence_similarity(window, ds=self.sequence, mode=self.sequence_mode)[:, -1]  # type: ignore[arg-type]
        self.ms_features += ms_features
        self.ms_matching += ms_matching + 1e3 * (time.perf_counter() - t2)
        block = None
        own = np.asarray(col, np.float64)  # the method's own scores (after the sequence search)
        if self.verifier is not None:
            if features is None:
                raise ValueError("this localiser verifies: give the frame's local features")
            block = self.verifier.verify(np.asarray(col)[:, None], [features])
            col = block.S[:, 0]
            self.ms_verify += float(block.ms[0])
            self.n_verified += int(block.verified[0])
        ok = None
        if self.confirm:
            col2 = np.asarray(col, np.float32)[:, None]
            ok = bool(confirmed(col2, self._previous_best)[0])
            self._previous_best = int(np.argmax(col2[:, 0]))
            col = demote_unconfirmed(col2, np.array([ok]))[:, 0]
        out = self._result(np.asarray(col, np.float64), own, name, time_s, block, index)
        if ok is not None:
            out["confirmed"] = ok
        self.frames += 1
        return out

    def _result(self, col: np.ndarray, own: np.ndarray, name: str, time_s: float | None,
                block: VerifiedBlock | None, index: int | None = None) -> dict[str, Any]:
        """The line: the places in ``col``'s order (the verified ranking), each with the method's own score."""
        m = self.map
        top = top_rows(col[:, None], self.top_k)[0][0]  # best first, ties by row as argmax
        best = int(top[0])
        score = float(own[best])
        if block is None:
            confidence = self._score_confidence(score)
            verified = None
        else:
            confidence, verified = float(block.confidence[0]), bool(block.verified[0])
        out: dict[str, Any] = {
            "frame": self.frames if index is None else int(index), "image": name, "place": int(m.place_ids[best]),
            "score": score,
            "accepted": m.accepts(score=score, confidence=confidence, is_verified=verified),
            "top": [[int(m.place_ids[i]), float(own[i])] for i in top],
        }
        if block is not None:
            out["verified"] = verified
            out["inliers"] = int(block.support[0])
        if confidence is not None:
            out["confidence"] = round(confidence, 4)
        if time_s is not None:
            out["time"] = time_s
        x, y = m.place_xy[best] if len(m.place_xy) else (np.nan, np.nan)
        if np.isfinite(x) and np.isfinite(y):
            out["x"], out["y"] = float(x), float(y)
        return out

    def _score_confidence(self, score: float) -> float | None:
        """An unverified run's confidence: the calibration's model of the method's score (None before one)."""
        model = self.map.score_confidence
        return None if model is None else float(model(model.inputs(score=np.array([score])), np.zeros(1, bool))[0])


__all__ = ["LocalizedMap", "Localizer"]
