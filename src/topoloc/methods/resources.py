"""What the recognisers get their per-image inputs from: the :class:`Resources` protocol.

A recogniser never opens a file itself.  It asks its resources for the local
features, the visual words or a per-image transform of a
:class:`~topoloc.datasets.traverse.Traverse`, whatever that traverse holds
(image files, images in memory, already-extracted features, word ids), and
for the vocabulary and the vocabulary's training words.  Two implementations:

* :class:`CachedResources` -- what ``topoloc evaluate`` uses: features of
  image files are cached on disk (keyed by the image bytes and the settings),
  per-image work runs on a thread pool, and the vocabulary may be trained on
  first use;
* :class:`InMemoryResources` -- nothing is read from or written to a cache:
  features of in-memory images (and of files, when given) are computed on the
  spot.  ``fit(maps)`` without resources uses one with default settings.

Both memoise per traverse within one run, so that ``fit``, ``encode`` and
``show-match`` extract and quantise each traverse once, and both record the
milliseconds of per-image work (``ms_features`` of the protocol).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TypeVar, runtime_checkable

import numpy as np

from topoloc._parallel import n_workers
from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.progress import ProgressFactory, no_progress

if TYPE_CHECKING:
    from topoloc.features import FeatureExtractor, FeatureSet
    from topoloc.vocabulary import Vocabulary

log = logging.getLogger(__name__)
T = TypeVar("T")

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
        self.image_ms: dict[tuple[str, str], float] = {}
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
            raise TopolocError("this method needs a visual vocabulary: pass --vocab or --vocab-train")
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
        tkey = memo_key[0]

        def run(k: int) -> T:
            t0 = time.perf_counter()
            out = fn(k)
            if timed and self.memoise:
                ms = getattr(out, "extract_ms", None)
                self.image_ms[(f"{tkey}#{k}", key)] = (
                    float(ms) if ms is not None else 1e3 * (time.perf_counter() - t0))
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
            feats = self._map(traverse, key, lambda k: ex.extract_path(traverse.images[k]),
                              f"features {traverse.name}", timed)
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
        feats = self.features(traverse, timed=timed)
        # Quantised once per traverse and run: fit, encode and show-match may all ask.
        memo_key = (traverse_key(traverse), "words:" + self.extractor.config.key())
        if memo_key in self._memo:
            return self._memo[memo_key]
        voc = self.vocabulary
        words = [voc.quantize(f.descriptors) for f in feats]
        if self.memoise:
            self._memo[memo_key] = words
        return words

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
                raise TopolocError(
                    "this method needs training images: pass --vocab-train (the vocabulary file "
                    "does not record its training folders)"
                )
            images = find_images(folders)
        # A pseudo-traverse over the training files; its root only keys the memo.
        common = Path(os.path.commonpath([str(p.parent.resolve()) for p in images]))
        pseudo = Traverse(root=common, images=tuple(images),
                          places=np.arange(len(images), dtype=np.int64), name="training")
        return self.words(pseudo, timed=False)

    def ms_features_median(self) -> float:
        vals = list(self.image_ms.values())
        return float(np.median(vals)) if vals else 0.0


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
    ) -> None:
        super().__init__(extractor=extractor, vocabulary=vocabulary, progress=progress, n_jobs=n_jobs,
                         training=training, training_images=training_images)

    def _default_extractor(self) -> FeatureExtractor:
        from topoloc.features import FeatureExtractor

        return FeatureExtractor()


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
        elif feature_config is not None:
            from topoloc.features import FeatureExtractor

            extractor = FeatureExtractor(feature_config, use_cache=False)
        super().__init__(extractor=extractor, vocabulary=vocabulary, progress=progress, n_jobs=n_jobs,
                         training=training, training_images=training_images, memoise=memoise)

    def _default_extractor(self) -> FeatureExtractor:
        from topoloc.features import FeatureExtractor

        return FeatureExtractor(use_cache=False)


def traverse_key(traverse: Traverse) -> str:
    """Memo key of a traverse: its folder and file names (an in-memory traverse's root is unique)."""
    return str(traverse.root.resolve()) + "|" + ",".join(p.name for p in traverse.images)


__all__ = ["CachedResources", "InMemoryResources", "ProgressFactory", "Resources", "no_progress", "traverse_key"]
