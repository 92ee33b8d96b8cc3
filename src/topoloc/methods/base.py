"""The contract every place-recognition method follows.

A method is a class with keyword-only parameters (scikit-learn style):

* ``fit(maps, resources=...)`` learns from one or more map traverses of the same
  places and returns ``self``; learned state lives in attributes ending in
  ``_``, in particular ``place_ids_`` (sorted unique map place ids: the rows of
  ``S``).
* ``encode(query, resources=...)`` turns a query traverse into one item per
  image (local features, a downsampled image...).  This is the per-image
  "feature extraction" and is timed separately from matching.
* ``score(items)`` returns the similarity block ``S`` of shape
  ``(len(place_ids_), len(items))``, higher = more similar.  The evaluation
  times it query by query; methods that need the whole query sequence at once
  (SeqSLAM) set ``scores_whole_sequence = True`` and are timed as total / n.

:class:`Resources` provides what several methods share within one run: local
features (parallel, cached on disk), the visual vocabulary, and timing of
per-image work.
"""

from __future__ import annotations

import inspect
import logging
import os
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Self, TypeVar

import numpy as np

from topoloc._parallel import n_workers
from topoloc.datasets.traverse import Traverse
from topoloc.errors import NotFittedError, TopolocError

if TYPE_CHECKING:
    from topoloc.features import FeatureExtractor, FeatureSet
    from topoloc.vocabulary import Vocabulary

log = logging.getLogger(__name__)
T = TypeVar("T")

ProgressFactory = Callable[[str, int], Callable[[int], None]]
"""``factory(description, total)`` returns ``advance(n)``; the CLI passes rich's."""


def _no_progress(description: str, total: int) -> Callable[[int], None]:
    return lambda n: None


class Resources:
    """Shared, lazily computed inputs of one evaluation run.

    Parameters
    ----------
    extractor : FeatureExtractor, optional
        Local-feature extractor (default: SIFT with the default cache).
    vocabulary : Vocabulary or callable returning one, optional
        The visual vocabulary, or a function that trains/loads it on first use.
    progress : callable, optional
        Progress factory, see :data:`ProgressFactory`.
    n_jobs : int
        Threads for per-image work (OpenCV releases the GIL).
    """

    def __init__(
        self,
        *,
        extractor: FeatureExtractor | None = None,
        vocabulary: Vocabulary | Callable[[], Vocabulary] | None = None,
        progress: ProgressFactory | None = None,
        n_jobs: int = -1,
        training_images: Sequence[Path] = (),
    ) -> None:
        self._extractor = extractor
        self.training_images = [Path(p) for p in training_images]
        self._vocabulary = vocabulary
        self.progress: ProgressFactory = progress or _no_progress
        self.n_jobs = n_jobs
        self.image_ms: dict[tuple[str, str], float] = {}
        self._memo: dict[tuple[str, str], list[Any]] = {}

    @property
    def extractor(self) -> FeatureExtractor:
        if self._extractor is None:
            from topoloc.features import FeatureExtractor

            self._extractor = FeatureExtractor()
        return self._extractor

    @property
    def vocabulary(self) -> Vocabulary:
        """The vocabulary; trained or loaded on first access."""
        if self._vocabulary is None:
            raise TopolocError("this method needs a visual vocabulary: pass --vocab or --vocab-train")
        if callable(self._vocabulary) and not hasattr(self._vocabulary, "quantize"):
            self._vocabulary = self._vocabulary()
        return self._vocabulary  # type: ignore[return-value]

    @property
    def has_vocabulary(self) -> bool:
        return self._vocabulary is not None

    def per_image(
        self, traverse: Traverse, key: str, fn: Callable[[Path], T], description: str = "", *, timed: bool = True
    ) -> list[T]:
        """Apply ``fn`` to every image of ``traverse`` in parallel, memoised by ``key``.

        With ``timed``, the milliseconds each image took are recorded in
        :attr:`image_ms` (an item's own ``extract_ms`` attribute is used when
        present, so that results loaded from the disk cache report their real
        extraction time); training images are not timed, so ``ms_features``
        describes map and query images only.
        """
        memo_key = (_traverse_key(traverse), key)
        if memo_key in self._memo:
            return self._memo[memo_key]
        advance = self.progress(description or f"{key} {traverse.name}", len(traverse))

        def run(path: Path) -> T:
            t0 = time.perf_counter()
            out = fn(path)
            if timed:
                ms = getattr(out, "extract_ms", None)
                self.image_ms[(str(path), key)] = float(ms) if ms is not None else 1e3 * (time.perf_counter() - t0)
            advance(1)
            return out

        workers = n_workers(self.n_jobs)
        if workers == 1:
            result = [run(p) for p in traverse.images]
        else:
            with ThreadPoolExecutor(max_workers=workers) as pool:
                result = list(pool.map(run, traverse.images))
        self._memo[memo_key] = result
        return result

    def features(self, traverse: Traverse, *, timed: bool = True) -> list[FeatureSet]:
        """Local features of every image of ``traverse`` (cached)."""
        ex = self.extractor
        return self.per_image(traverse, "features:" + ex.config.key(), ex.extract_path,
                              f"features {traverse.name}", timed=timed)

    def words(self, traverse: Traverse, *, timed: bool = True) -> list[np.ndarray]:
        """Visual-word ids of every image's features, each of shape (n_features,)."""
        feats = self.features(traverse, timed=timed)
        # Quantised once per traverse and run: fit, encode and show-match may all ask.
        memo_key = (_traverse_key(traverse), "words:" + self.extractor.config.key())
        if memo_key not in self._memo:
            voc = self.vocabulary
            self._memo[memo_key] = [voc.quantize(f.descriptors) for f in feats]
        return self._memo[memo_key]

    def training_words(self) -> list[np.ndarray]:
        """Visual-word ids of every training image (the vocabulary's training set).

        Methods that learn word statistics apart from the map (FAB-MAP) use
        these.  Without explicit ``training_images`` the folders recorded in
        the vocabulary's provenance are used.
        """
        images = self.training_images
        if not images:
            from topoloc.datasets.traverse import find_images

            folders = self.vocabulary.provenance_.get("folders", [])
            if not folders:
                raise TopolocError(
                    "this method needs training images: pass --vocab-train (the vocabulary file "
                    "does not record its training folders)"
                )
            images = find_images(folders)
        common = Path(os.path.commonpath([str(p.parent) for p in images]))
        pseudo = Traverse(root=common, images=tuple(images),
                          places=np.arange(len(images), dtype=np.int64), name="training")
        return self.words(pseudo, timed=False)

    def ms_features_median(self) -> float:
        """Median per-image milliseconds of all per-image work so far."""
        vals = list(self.image_ms.values())
        return float(np.median(vals)) if vals else 0.0




def _traverse_key(traverse: Traverse) -> str:
    return str(traverse.root.resolve()) + "|" + ",".join(p.name for p in traverse.images)


class PlaceRecognizer(ABC):
    """Base class of all methods; see the module docstring for the contract."""

    name: ClassVar[str] = ""
    uses_vocabulary: ClassVar[bool] = False
    scores_whole_sequence: ClassVar[bool] = False

    place_ids_: np.ndarray

    @abstractmethod
    def fit(self, maps: Sequence[Traverse], *, resources: Resources) -> Self:
        """Learn the map from one or more traverses of the same places."""

    @abstractmethod
    def encode(self, query: Traverse, *, resources: Resources) -> list[Any]:
        """Per-image query representation (timed as feature extraction)."""

    @abstractmethod
    def score(self, items: Sequence[Any]) -> np.ndarray:
        """Similarity block of shape (n_map_places, len(items)), higher = more similar."""

    # -- scikit-learn-like parameter handling -------------------------------------------
    @classmethod
    def param_names(cls) -> list[str]:
        sig = inspect.signature(cls.__init__)
        return [p.name for p in sig.parameters.values() if p.kind is p.KEYWORD_ONLY]

    def get_params(self) -> dict[str, Any]:
        """The constructor parameters and their current values."""
        return {k: getattr(self, k) for k in self.param_names()}

    def check_fitted(self) -> None:
        """Raise :class:`NotFittedError` unless ``fit`` has been called."""
        if not hasattr(self, "place_ids_"):
            raise NotFittedError(f"{type(self).__name__} is not fitted yet: call fit() first")

    def _check_block(self, S: np.ndarray, n_items: int) -> np.ndarray:
        expected = (len(self.place_ids_), n_items)
        if S.shape != expected:
            raise AssertionError(f"{self.name}: S has shape {S.shape}, expected {expected}")
        return S


def map_place_ids(maps: Sequence[Traverse]) -> np.ndarray:
    """Sorted unique place ids over all map traverses (the rows of ``S``)."""
    if not maps:
        raise TopolocError("at least one map traverse is needed")
    return np.unique(np.concatenate([m.places for m in maps]))


def parse_param(cls: type[PlaceRecognizer], key: str, value: str) -> Any:
    """Convert a ``--param KEY=VALUE`` string to the type of the parameter's default."""
    sig = inspect.signature(cls.__init__)
    if key not in sig.parameters or sig.parameters[key].kind is not inspect.Parameter.KEYWORD_ONLY:
        raise TopolocError(
            f"method {cls.name!r} has no parameter {key!r} (parameters: {', '.join(cls.param_names())})"
        )
    default = sig.parameters[key].default
    try:
        if isinstance(default, bool):
            if value.lower() in {"1", "true", "yes", "on"}:
                return True
            if value.lower() in {"0", "false", "no", "off"}:
                return False
            raise ValueError(value)
        if isinstance(default, int):
            return int(value)
        if isinstance(default, float):
            return float(value)
        if default is None:
            for conv in (int, float):
                try:
                    return conv(value)
                except ValueError:
                    pass
            return None if value.lower() == "none" else value
    except ValueError:
        raise TopolocError(
            f"parameter {key}={value!r} of method {cls.name!r} should be {type(default).__name__}"
        ) from None
    return value
