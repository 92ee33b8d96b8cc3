"""What the recognisers get their per-image inputs from: the :class:`Resources` protocol.

A recogniser never opens a file itself.  It asks its resources for the local
features, the visual words or a per-image transform of a
:class:`~topoloc.datasets.traverse.Traverse`, whatever that traverse holds
(image files, images in memory, already-extracted features, word ids), and
for the vocabulary and the vocabulary's training words.  Two implementations:

* :class:`CachedResources` -- what ``topoloc evaluate`` uses: features of
  a traverse of image files live in its feature store on disk
  (:mod:`topoloc.features.store`: blocks of images, each block checked
  against the SHA-1 of its images), filled block by block through an
  executor (:mod:`topoloc.cluster`: threads of this process, or the workers
  of a Dask cluster, which then also quantise the blocks into words), and
  the vocabulary may be trained on first use;
* :class:`InMemoryResources` -- nothing is read from or written to a cache:
  features of in-memory images (and of files, when given) are computed on the
  spot.  ``fit(maps)`` without resources uses one with default settings.

Both memoise per traverse within one run, so that ``fit``, ``encode`` and
``show-match`` extract and quantise each traverse once, and both record the
milliseconds of per-image work (``ms_features`` of the protocol).
"""

from __future__ import annotations

import copy
import hashlib
import logging
import os
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TypeVar, runtime_checkable

import numpy as np

from topoloc._parallel import n_workers
from topoloc.cluster import Executor, LocalExecutor, flatten
from topoloc.datasets.traverse import Traverse
from topoloc.errors import ParameterError, TopolocError
from topoloc.io.scratch import spill, spilling
from topoloc.progress import ProgressFactory, no_progress

if TYPE_CHECKING:
    from topoloc.features import FeatureExtractor, FeatureSet
    from topoloc.features.store import BlockResult, BlockTask, FeatureStore
    from topoloc.vocabulary import Vocabulary

log = logging.getLogger(__name__)
T = TypeVar("T")

PlacedWords = tuple[np.ndarray, np.ndarray, tuple[int, int]]
"""One image's word ids (n,), its keypoints' (x, y) as float32 (n, 2), and its (height, width)."""

@runtime_checkable
class Resources(Protocol):
    """Per-image inputs of the recognisers (see the module docstring)."""

    progress: ProgressFactory

    @property
    def extractor(self) -> FeatureExtractor:
        """The local-feature extractor (its ``config`` are the run's feature settings)."""
        ...

    @property
    def vocabulary(self) -> Vocabulary:
        """The visual vocabulary; raises :class:`TopolocError` when there is none."""
        ...

    @property
    def has_vocabulary(self) -> bool:
        """Whether a vocabulary was given (without training or loading it)."""
        ...

    def features(self, traverse: Traverse, *, timed: bool = True) -> list[FeatureSet]:
        """Local features of every image of ``traverse``."""
        ...

    def words(self, traverse: Traverse, *, timed: bool = True) -> list[np.ndarray]:
        """Visual-word ids of every image's features, each of shape (n_features,)."""
        ...

    def placed_words(self, traverse: Traverse, *, limit: int | None = None) -> list[PlacedWords]:
        """Word ids of every image's first ``limit`` features, with their keypoints' (x, y) and the image shape."""
        ...

    def per_image(
        self, traverse: Traverse, key: str, fn: Callable[[np.ndarray], T], description: str = "", *,
        timed: bool = True,
    ) -> list[T]:
        """``fn(grey image)`` for every image of ``traverse``, memoised by ``key``."""
        ...

    def training_words(self) -> list[np.ndarray]:
        """Visual-word ids of the vocabulary's training images (FAB-MAP learns from these)."""
        ...

    def ms_features_median(self) -> float:
        """Median milliseconds of per-image work on map and query images so far."""
        ...


class _MemoisedResources:
    """The shared implementation; subclasses choose the extractor's caching."""

    def __init__(
        self,
        *,
        extractor: FeatureExtractor | None,
        vocabulary: Vocabulary | Callable[[], Vocabulary] | None,
        progress: ProgressFactory | None,
        n_jobs: int,
        training: Sequence[Traverse] | Traverse | None,
        training_images: Sequence[Path],
        memoise: bool = True,
    ) -> None:
        self.memoise = memoise
        self._extractor = extractor
        self._vocabulary = vocabulary
        self.progress: ProgressFactory = progress or no_progress
        self.n_jobs = n_jobs
        self.training = [training] if isinstance(training, Traverse) else list(training or [])
        self.training_images = [Path(p) for p in training_images]
        # Per (traverse, key): one array of per-image ms (per-image dict entries would cost a
        # Python object each, and a key naming the traverse, on a 100,000-image route).
        self.image_ms: dict[tuple[str, str], np.ndarray] = {}
        self._memo: dict[tuple[str, str], list[Any]] = {}

    def _default_extractor(self) -> FeatureExtractor:
        raise NotImplementedError

    @property
    def extractor(self) -> FeatureExtractor:
        if self._extractor is None:
            self._extractor = self._default_extractor()
        return self._extractor

    @property
    def vocabulary(self) -> Vocabulary:
        if self._vocabulary is None:
            raise ParameterError("vocabulary", "is needed by this method (it needs a visual vocabulary): give a "
                                               "vocabulary file or folders to train one on")
        if callable(self._vocabulary) and not hasattr(self._vocabulary, "quantize"):
            self._vocabulary = self._vocabulary()
        return self._vocabulary  # type: ignore[return-value]

    @property
    def has_vocabulary(self) -> bool:
        return self._vocabulary is not None

    # -- per-image work -------------------------------------------------------------------
    def _map(
        self, traverse: Traverse, key: str, fn: Callable[[int], T], description: str, timed: bool
    ) -> list[T]:
        """``fn(k)`` for every image index ``k``, in parallel, memoised and timed per image.

        An item's own ``extract_ms`` attribute is used as its time when present,
        so that features loaded from the disk cache report their real extraction
        time; training images are not timed, so ``ms_features`` describes map and
        query images only.
        """
        memo_key = (traverse_key(traverse), key)
        if memo_key in self._memo:
            return self._memo[memo_key]
        advance = self.progress(description or f"{key} {traverse.name}", len(traverse))
        times = np.full(len(traverse), np.nan) if timed and self.memoise else None

        def run(k: int) -> T:
            t0 = time.perf_counter()
            out = fn(k)
            if times is not None:
                ms = getattr(out, "extract_ms", None)
                times[k] = float(ms) if ms is not None else 1e3 * (time.perf_counter() - t0)
            advance(1)
            return out

        workers = min(n_workers(self.n_jobs), max(len(traverse), 1))
        if workers == 1:
            result = [run(k) for k in range(len(traverse))]
        else:
            with ThreadPoolExecutor(max_workers=workers) as pool:
                result = list(pool.map(run, range(len(traverse))))
        if self.memoise:
            self._memo[memo_key] = result
        if times is not None:
            self.image_ms[memo_key] = times
        return result

    def per_image(
        self, traverse: Traverse, key: str, fn: Callable[[np.ndarray], T], description: str = "", *,
        timed: bool = True,
    ) -> list[T]:
        return self._map(traverse, key, lambda k: fn(traverse.read(k, gray=True)), description, timed)

    def features(self, traverse: Traverse, *, timed: bool = True) -> list[FeatureSet]:
        if traverse.kind == "features":
            return list(traverse.frames or ())
        if traverse.kind == "words":
            raise TopolocError(f"traverse {traverse.name!r} holds visual words, not local features "
                               "(this method needs features or images)")
        ex = self.extractor
        key = "features:" + ex.config.key()
        fresh = (traverse_key(traverse), key) not in self._memo
        if traverse.kind == "images":
            frames = traverse.frames or ()
            feats = self._map(traverse, key, lambda k: ex.extract_image(frames[k]), f"features {traverse.name}",
                              timed)
        else:
            feats = self._file_features(traverse, key, timed)
        empty = [k for k, f in enumerate(feats) if len(f) == 0]
        if empty and fresh and self.memoise:
            # One line per traverse: such images match nothing, and every method scores them as it can.
            log.warning("%d of %d images of %s have no local features (blank, tiny or dark?), e.g. %s",
                        len(empty), len(feats), traverse.name, traverse.images[empty[0]].name)
        return feats

    def words(self, traverse: Traverse, *, timed: bool = True) -> list[np.ndarray]:
        if traverse.kind == "words":
            words = list(traverse.frames or ())
            if self.has_vocabulary:
                n_words = int(self.vocabulary.n_words_)
                if any(len(w) and int(w.max()) >= n_words for w in words):
                    raise TopolocError(f"traverse {traverse.name!r} has word ids >= the vocabulary's "
                                       f"{n_words} words")
            return words
        # Quantised once per traverse and run: fit, encode and show-match may all ask.
        memo_key = (traverse_key(traverse), "words:" + self.extractor.config.key())
        if memo_key in self._memo:
            return self._memo[memo_key]
        words = self._quantize(traverse, timed)
        if self.memoise:
            self._memo[memo_key] = words
        return words

    def placed_words(self, traverse: Traverse, *, limit: int | None = None) -> list[PlacedWords]:
        """Word ids of every image's first ``limit`` features (all: None), their (x, y) and the image shape.

        What a method that places words in the image (Cooc-Map) needs, without
        the descriptors: on a cluster the workers read and quantise their
        blocks and send back only this (12 bytes a feature instead of the
        descriptor's 128 and more), so the client never holds a tour's features.
        """
        feats = self.features(traverse)
        words = self.words(traverse)
        return [(w[:limit], np.asarray(f.keypoints[:limit, :2], np.float32), f.image_shape)
                for f, w in zip(feats, words, strict=True)]

    def _file_features(self, traverse: Traverse, key: str, timed: bool) -> list[FeatureSet]:
        """Features of a traverse of image files (here: per image, through the extractor's own cache)."""
        ex = self.extractor
        return self._map(traverse, key, lambda k: ex.extract_path(traverse.images[k]), f"features {traverse.name}",
                         timed)

    def _quantize(self, traverse: Traverse, timed: bool) -> list[np.ndarray]:
        """Word ids of every image of a traverse of files or images (not memoised here)."""
        feats = self.features(traverse, timed=timed)
        voc = self.vocabulary
        return [voc.quantize(f.descriptors) for f in feats]

    def training_words(self) -> list[np.ndarray]:
        """Visual-word ids of every training image (the vocabulary's training set).

        Methods that learn word statistics apart from the map (FAB-MAP) use
        these: the ``training`` traverses when given, else ``training_images``,
        else the folders recorded in the vocabulary's provenance.
        """
        if self.training:
            return [w for t in self.training for w in self.words(t, timed=False)]
        images = self.training_images
        if not images:
            from topoloc.datasets.traverse import find_images

            folders = self.vocabulary.provenance_.get("folders", []) if self.has_vocabulary else []
            if not folders:
                raise ParameterError("vocabulary.train", "is needed: this method needs training images and the "
                                                         "vocabulary file does not record its training folders")
            images = find_images(folders)
        # A pseudo-traverse over the training files; its root only keys the memo.
        common = Path(os.path.commonpath([str(p.parent.resolve()) for p in images]))
        pseudo = Traverse(root=common, images=tuple(images),
                          places=np.arange(len(images), dtype=np.int64), name="training")
        return self.words(pseudo, timed=False)

    def ms_features_median(self) -> float:
        vals = np.concatenate([np.empty(0), *self.image_ms.values()])
        return float(np.median(vals)) if vals.size else 0.0

    def for_task(self, *, remote: bool = False) -> _MemoisedResources:
        """A shallow copy for one task of an executor: no progress display.

        With ``remote`` (the task is pickled to a worker process) the copy runs
        its per-image work on the worker's own thread, not through a cluster
        client (which cannot be pickled), and starts with empty memos: a
        worker computes what its task needs, nothing memoised here is shipped.
        """
        out = copy.copy(self)
        out.progress = no_progress
        if remote:
            out._memo = {}
            out.image_ms = {}
        return out


class CachedResources(_MemoisedResources):
    """Resources of an evaluation run: features of image files cached on disk.

    Parameters
    ----------
    extractor : FeatureExtractor, optional
        Local-feature extractor (default: SIFT with the default on-disk cache).
    vocabulary : Vocabulary or callable returning one, optional
        The visual vocabulary, or a function that trains/loads it on first use.
    progress : callable, optional
        Progress factory, see :data:`ProgressFactory`.
    n_jobs : int
        Threads for per-image work (OpenCV releases the GIL); -1 = all cores.
    training : Traverse or sequence of Traverse, optional
        Images the vocabulary-dependent models learn word statistics from.
    training_images : sequence of path
        The same as image files (used when ``training`` is empty).
    executor : Executor, optional
        Where block tasks run (:func:`topoloc.cluster.connect`; default: ``n_jobs``
        threads of this process).  On a Dask cluster the workers extract the
        blocks of image-file traverses into the feature store and quantise
        them; the cache folder must then be shared with the workers.
    block_size : int, optional
        Images per feature-store block (default
        :data:`topoloc.features.store.BLOCK_IMAGES`).

    Notes
    -----
    With an extractor whose cache is off (``use_cache=False``) nothing is
    written: features of files are extracted per image on the threads.
    """

    def __init__(
        self,
        *,
        extractor: FeatureExtractor | None = None,
        vocabulary: Vocabulary | Callable[[], Vocabulary] | None = None,
        progress: ProgressFactory | None = None,
        n_jobs: int = -1,
        training: Sequence[Traverse] | Traverse | None = None,
        training_images: Sequence[Path] = (),
        executor: Executor | None = None,
        block_size: int | None = None,
    ) -> None:
        super().__init__(extractor=extractor, vocabulary=vocabulary, progress=progress, n_jobs=n_jobs,
                         training=training, training_images=training_images)
        self.executor: Executor = executor if executor is not None else LocalExecutor(n_jobs)
        self.block_size = block_size
        self._fills: dict[tuple[str, str], _Filled] = {}
        self._shared_checked = False

    def _default_extractor(self) -> FeatureExtractor:
        from topoloc.features import FeatureExtractor

        return FeatureExtractor()

    @property
    def distributed(self) -> bool:
        """Whether block tasks run on a cluster (not on this process's threads)."""
        return not isinstance(self.executor, LocalExecutor)

    def for_task(self, *, remote: bool = False) -> CachedResources:
        out = super().for_task(remote=remote)
        assert isinstance(out, CachedResources)
        if remote:
            out.executor = LocalExecutor(1)
            out._fills = {}
        return out

    def _fill(self, traverse: Traverse, key: str, timed: bool) -> _Filled:
        """Complete the feature store of a file traverse through the executor (memoised per run).

        A traverse cut from a whole tour (:meth:`Traverse.take`, a map shard) is read from
        the blocks of the whole tour's store when those are all complete, so no image is
        stored twice; otherwise it gets a store of its own.
        """
        from topoloc.features.store import BLOCK_IMAGES, FeatureStore, check_shared_cache, fill_block

        memo_key = (traverse_key(traverse), key)
        if memo_key in self._fills:
            return self._fills[memo_key]
        ex = self.extractor
        size = self.block_size or BLOCK_IMAGES
        local = not self.distributed
        if not local and not self._shared_checked:
            check_shared_cache(self.executor, ex.cache_dir)
            self._shared_checked = True
        # Locally one block at a time on all the executor's threads: balanced to the last image of each
        # block, as the per-image pool was (blocks on one thread each would leave threads idle while the
        # last blocks finish).  On a cluster every worker thread takes a block.
        runner: Executor = LocalExecutor(1) if local else self.executor
        threads = self.executor.n_workers if local else 1
        advance = self.progress(f"features {traverse.name}", len(traverse))
        whole = _whole_tour_blocks(traverse, ex.config, ex.cache_dir, size)
        if whole is not None:
            store, blocks, select = whole
            results = runner.map(fill_block, [store.task(b, threads=threads, keep=local) for b in blocks])
            advance(len(traverse))
        else:
            store = FeatureStore(ex.config, traverse.images, root=traverse.root, cache_dir=ex.cache_dir,
                                 block_size=size)
            results, select = store.fill(runner, advance=advance, keep=local, threads=threads), None
        filled = _Filled(store, results, select)
        if timed and self.memoise:
            self.image_ms[memo_key] = filled.pick(np.concatenate([r.extract_ms for r in results])
                                                  if results else np.empty(0))
        if self.memoise:
            self._fills[memo_key] = filled
        return filled

    def _file_features(self, traverse: Traverse, key: str, timed: bool) -> list[FeatureSet]:
        if not self.extractor.use_cache:
            return super()._file_features(traverse, key, timed)
        memo_key = (traverse_key(traverse), key)
        if memo_key in self._memo:
            return self._memo[memo_key]
        filled = self._fill(traverse, key, timed)
        feats = filled.pick(filled.store.read(filled.results))
        for r in filled.results:
            r.features = None  # held once, in the memo below
        if self.memoise:
            self._memo[memo_key] = feats
        return feats

    def _on_workers(self, traverse: Traverse) -> bool:
        """Whether the traverse's blocks are read and quantised by cluster workers (not gathered here)."""
        return traverse.kind == "files" and self.distributed and self.extractor.use_cache

    def _block_tasks(self, traverse: Traverse, timed: bool, limit: int | None = None
                     ) -> tuple[list[QuantizeTask], _Filled]:
        filled = self._fill(traverse, "features:" + self.extractor.config.key(), timed)
        ref = vocabulary_file(self.vocabulary, self.extractor.cache_dir)
        return [QuantizeTask(block=filled.store.task(r.block), sha1=tuple(r.sha1), vocabulary=ref[0],
                             fingerprint=ref[1], limit=limit) for r in filled.results], filled

    def placed_words(self, traverse: Traverse, *, limit: int | None = None) -> list[PlacedWords]:
        if not self._on_workers(traverse):
            return super().placed_words(traverse, limit=limit)
        tasks, filled = self._block_tasks(traverse, True, limit)
        return filled.pick(flatten([split_placed(b) for b in self._run_blocks(placed_block, tasks, traverse)]))

    def _run_blocks(self, fn: Any, tasks: list[QuantizeTask], traverse: Traverse) -> list[Any]:
        """``fn`` of every block task on the executor, progress advancing by each block's images."""
        advance = self.progress(f"words {traverse.name}", len(traverse))
        sizes = iter([len(t.block.images) for t in tasks])
        # Within io.scratch.spill_to (map build, map add) each block's result goes to a scratch file as it
        # arrives: the results of a whole tour are as large as the map's table.
        return list(self.executor.map(fn, tasks, advance=lambda _: advance(next(sizes)),
                                      keep=spill if spilling() else None))

    def _quantize(self, traverse: Traverse, timed: bool) -> list[np.ndarray]:
        if self._on_workers(traverse):
            # The workers read their blocks from the store and quantise them: no descriptor crosses the network.
            tasks, filled = self._block_tasks(traverse, timed)
            return filled.pick(flatten(self._run_blocks(quantize_block, tasks, traverse)))
        feats = self.features(traverse, timed=timed)
        voc = self.vocabulary
        local = self.executor if not self.distributed else LocalExecutor(self.n_jobs)
        from topoloc.cluster import chunks
        from topoloc.features.store import BLOCK_IMAGES

        parts = local.map(lambda r: [voc.quantize(feats[k].descriptors) for k in r],
                          chunks(len(feats), self.block_size or BLOCK_IMAGES))
        return flatten(parts)


class InMemoryResources(_MemoisedResources):
    """Resources that never touch a cache: every feature is computed in memory.

    Parameters are those of :class:`CachedResources`; ``feature_config`` may be
    given instead of an ``extractor`` (the extractor is then created without a
    cache).  An ``extractor`` given with its cache on is used with the cache off.
    ``memoise=False`` keeps nothing between calls (a localiser fed one camera
    frame after another: memory must not grow with the frames).
    """

    def __init__(
        self,
        *,
        extractor: FeatureExtractor | None = None,
        feature_config: Any = None,
        vocabulary: Vocabulary | Callable[[], Vocabulary] | None = None,
        progress: ProgressFactory | None = None,
        n_jobs: int = -1,
        training: Sequence[Traverse] | Traverse | None = None,
        training_images: Sequence[Path] = (),
        memoise: bool = True,
    ) -> None:
        if extractor is not None and feature_config is not None:
            raise TopolocError("pass either extractor or feature_config, not both")
        if extractor is not None and extractor.use_cache:
            from topoloc.features import FeatureExtractor

            extractor = FeatureExtractor(extractor.config, use_cache=False, n_jobs=extractor.n_jobs)
        # A feature_config's extractor is made when features are first needed: a saved map opens (map info) where
        # its features cannot be computed (XFeat's runtime missing), and says so when they are.
        self._feature_config = feature_config
        super().__init__(extractor=extractor, vocabulary=vocabulary, progress=progress, n_jobs=n_jobs,
                         training=training, training_images=training_images, memoise=memoise)

    def _default_extractor(self) -> FeatureExtractor:
        from topoloc.features import FeatureExtractor

        return FeatureExtractor(self._feature_config, use_cache=False)


@dataclass(frozen=True)
class QuantizeTask:
    """Quantise one feature-store block on a worker: the block, its images' SHA-1s, the vocabulary file.

    ``limit``: only each image's first ``limit`` features (:func:`placed_block`; None: all).
    """

    block: BlockTask
    sha1: tuple[str, ...]
    vocabulary: str
    fingerprint: str
    limit: int | None = None


_worker_vocabularies: dict[str, Vocabulary] = {}
_worker_lock = threading.Lock()


def vocabulary_file(vocabulary: Vocabulary, cache_dir: Path) -> tuple[str, str]:
    """``(path, sha1)`` of the vocabulary saved under the cache for workers to load (written once).

    Workers get the file's path, not the vocabulary: a faiss index does not
    pickle, and one file read per worker process beats one copy per task.
    """
    from topoloc.vocabulary.vocab import vocabulary_fingerprint

    sha1 = vocabulary_fingerprint(vocabulary)["sha1"]
    path = Path(cache_dir).absolute() / "vocab" / f"words-{sha1[:20]}-{vocabulary.index}-{vocabulary.ef_search}.tlv"
    if not path.is_file():
        vocabulary.save(path)
    with _worker_lock:  # this process already has it: a local worker need not read it back
        _worker_vocabularies.setdefault(f"{path}|{sha1}", vocabulary)
    return str(path), sha1


def _load_worker_vocabulary(path: str, sha1: str) -> Vocabulary:
    """The vocabulary of ``path``, loaded once per worker process (its index is then built once too)."""
    from topoloc.vocabulary import Vocabulary
    from topoloc.vocabulary.vocab import vocabulary_fingerprint

    key = f"{path}|{sha1}"
    with _worker_lock:
        voc = _worker_vocabularies.get(key)
        if voc is None:
            voc = Vocabulary.load(path)
            if vocabulary_fingerprint(voc)["sha1"] != sha1:
                raise TopolocError(f"vocabulary file changed while the run used it: {path}")
            _worker_vocabularies[key] = voc
    return voc


def quantize_block(task: QuantizeTask) -> list[np.ndarray]:
    """Word ids of every image of one feature-store block (the unit of distributed quantisation).

    The block is read and checked against its images' SHA-1s; one that fails
    (changed since it was filled) is extracted again first.
    """
    voc = _load_worker_vocabulary(task.vocabulary, task.fingerprint)
    return [voc.quantize(fs.descriptors) for fs in _block_sets(task)]


def _block_sets(task: QuantizeTask) -> list[FeatureSet]:
    """The block's features, read and checked; extracted again when the file fails its checks."""
    from dataclasses import replace

    from topoloc.features.store import fill_block, read_block

    try:
        return read_block(task.block.path, task.block.config, task.sha1)
    except TopolocError as exc:
        log.warning("feature block is unusable, extracting it again (%s)", exc)
        return fill_block(replace(task.block, keep=True, force=True)).features or []


def placed_block(task: QuantizeTask) -> dict[str, np.ndarray]:
    """Word ids, keypoint (x, y) and image shape of every image of one block, as four flat arrays.

    ``words`` (int32) and ``xy`` (float32, (n, 2)) hold the images' first
    ``task.limit`` features concatenated; image ``i`` owns rows
    ``offsets[i]:offsets[i + 1]``; ``shapes`` is (n_images, 2).  Flat arrays
    pickle as a few buffers, not one object per image.
    """
    voc = _load_worker_vocabulary(task.vocabulary, task.fingerprint)
    sets = _block_sets(task)
    lim = task.limit
    words = [voc.quantize(fs.descriptors[:lim]).astype(np.int32) for fs in sets]
    counts = np.array([len(w) for w in words], np.int64)
    return {"words": np.concatenate(words) if words else np.empty(0, np.int32),
            "xy": (np.concatenate([fs.keypoints[:lim, :2] for fs in sets]).astype(np.float32)
                   if sets else np.empty((0, 2), np.float32)),
            "offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
            "shapes": np.array([fs.image_shape for fs in sets], np.int64).reshape(len(sets), 2)}


def split_placed(block: dict[str, np.ndarray]) -> list[PlacedWords]:
    """The per-image views of one :func:`placed_block` result."""
    off, shapes = np.asarray(block["offsets"]), np.asarray(block["shapes"])
    # Plain views even of a block moved to a scratch file (io.scratch.spill): a memmap view per image
    # costs several times a plain one, and a tour has one per image.
    words, xy = np.asarray(block["words"]), np.asarray(block["xy"])
    return [(words[off[i]:off[i + 1]], xy[off[i]:off[i + 1]],
             (int(shapes[i, 0]), int(shapes[i, 1]))) for i in range(len(shapes))]


@dataclass
class _Filled:
    """A file traverse's features in a store: its blocks' results, and which of their images are the traverse's.

    ``select`` is None when the blocks hold exactly the traverse's images; else the row, among the
    images of the listed blocks in order, of each of the traverse's images (a cut of a whole tour).
    """

    store: FeatureStore
    results: list[BlockResult]
    select: np.ndarray | None

    def pick(self, per_image: Sequence[T] | np.ndarray) -> Any:
        """The traverse's entries of a per-image sequence over the blocks' images."""
        if self.select is None:
            return per_image
        if isinstance(per_image, np.ndarray):
            return per_image[self.select]
        return [per_image[int(k)] for k in self.select]


def _whole_tour_blocks(traverse: Traverse, config: Any, cache_dir: Path | None, block_size: int
                       ) -> tuple[FeatureStore, list[int], np.ndarray] | None:
    """The whole tour's store, the blocks holding the images of a cut of it, and their rows; None if any is missing.

    Only complete blocks are used: a sparse cut (every tenth frame) of a tour never described
    would otherwise extract ten times the images it needs.
    """
    from topoloc.features.store import FeatureStore

    if traverse.origin is None or traverse.kind != "files":
        return None
    parent, index = traverse.origin
    store = FeatureStore(config, parent.images, root=parent.root, cache_dir=cache_dir, block_size=block_size)
    blocks = np.unique(index // block_size)
    if not all(store.block_path(int(b)).is_file() for b in blocks):
        return None
    sizes = np.array([len(store.block_range(int(b))) for b in blocks], np.int64)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    select = starts[np.searchsorted(blocks, index // block_size)] + index % block_size
    return store, [int(b) for b in blocks], select


def traverse_key(traverse: Traverse) -> str:
    """Memo key of a traverse: its folder and a digest of its file names (an in-memory traverse's root is unique).

    Of fixed size whatever the tour's length: the names themselves would make a key of
    megabytes on a 100,000-image route.
    """
    names = hashlib.sha1("\0".join(p.name for p in traverse.images).encode("utf-8", "surrogateescape"),
                         usedforsecurity=False)
    return f"{traverse.root.resolve()}|{len(traverse.images)}|{names.hexdigest()}"


__all__ = ["CachedResources", "InMemoryResources", "PlacedWords", "ProgressFactory", "Resources", "no_progress",
           "traverse_key"]
