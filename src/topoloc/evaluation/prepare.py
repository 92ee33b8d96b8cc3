"""From ``evaluate``'s options to what a run needs: the method, the feature scale, the resources.

Shared by ``evaluate``, ``show-match`` and ``slam``: every cheap check happens
here, before any feature is extracted.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from topoloc.cluster import Executor
from topoloc.datasets.traverse import Traverse, find_images, probe_image_sides, read_image
from topoloc.errors import TopolocError
from topoloc.methods import get_method
from topoloc.methods.base import PlaceRecognizer, parse_param
from topoloc.methods.resources import CachedResources
from topoloc.progress import ProgressFactory


def build_method(name: str, params: dict[str, str]) -> PlaceRecognizer:
    """Instantiate method ``name`` with ``--param`` strings converted to their types."""
    cls = get_method(name)
    kwargs = {k: parse_param(cls, k, v) for k, v in params.items()}
    method = cls(**kwargs)
    method.validate_params()  # a bad value stops the run before any image is read
    return method


def resolve_max_side(
    spec: str | int, traverses: Sequence[Traverse], *, images: Sequence[Path] = ()
) -> int:
    """The ``max_side`` to extract features at: ``spec`` itself, or for ``"auto"`` a common scale.

    SIFT and its kin are scale-invariant only up to their sampling of scale space:
    the same scene imaged at 960 and at 640 pixels yields different keypoints, which
    costs matches between traverses taken with different cameras or settings (on
    gardens_point the night traverse is 640 x 360, the day traverses 960 x 540).
    ``"auto"`` therefore returns the smallest longer image side found in
    ``traverses`` when they differ (every traverse is then extracted at that size),
    and 0 (no resizing) when all sizes agree.  The first, middle and last image
    of each traverse, and every file in ``images``, are read to find the sizes.

    Raises
    ------
    TopolocError
        If ``spec`` is neither ``"auto"`` nor a non-negative integer, or a sampled
        image cannot be read.
    """
    text = str(spec).strip().lower()
    if text != "auto":
        try:
            value = int(text)
        except ValueError:
            raise TopolocError(f"--max-side must be 'auto' or a number of pixels, got {spec!r}") from None
        if value < 0:
            raise TopolocError(f"--max-side must be >= 0 (0 = no resizing), got {value}")
        return value
    sides = {max(read_image(path).shape[:2]) for path in images} | probe_image_sides(traverses)
    return min(sides) if len(sides) > 1 else 0


def make_resources(
    *,
    vocab: Path | None = None,
    vocab_train: list[Path] | None = None,
    vocab_words: int = 10000,
    features: str = "sift",
    max_features: int = 1000,
    max_side: int = 0,
    preprocess: str = "auto",
    cache_dir: Path | None = None,
    seed: int = 0,
    needs_vocabulary: str = "",
    progress: ProgressFactory | None = None,
    executor: Executor | None = None,
) -> tuple[CachedResources, dict[str, Any]]:
    """Feature extractor and vocabulary for a run, with the vocabulary's provenance.

    ``needs_vocabulary`` names the user of the vocabulary (a method, a command);
    when set, a missing ``vocab``/``vocab_train`` is an error.  ``executor``
    runs the per-block work (default: this process's threads).
    """
    from topoloc.features import FeatureConfig, FeatureExtractor

    if vocab is not None and vocab_train:
        raise TopolocError("pass either --vocab FILE or --vocab-train DIR, not both")
    config = FeatureConfig(method=features, max_features=max_features, max_side=max_side, preprocess=preprocess)
    extractor = FeatureExtractor(config, cache_dir=cache_dir)
    vocab_info: dict[str, Any] = {"used": False}
    vocabulary: Any = None
    training_images: list[Path] = []
    if vocab is not None:
        from topoloc.vocabulary import Vocabulary

        vocabulary = Vocabulary.load(vocab)
        vocabulary.check_compatible(extractor.config.descriptor_kind, source=vocab)
        vocab_info = {"used": True, "file": str(vocab), "n_words": int(vocabulary.n_words_), **vocabulary.provenance_}
    elif vocab_train:
        from topoloc.vocabulary import cached_vocabulary

        training_images = find_images(vocab_train)
        folders = list(vocab_train)

        def provide() -> Any:
            # Called lazily by the first user of the vocabulary (inside ``fit``): its time is
            # recorded here so that ``evaluate`` can report it apart from the fit time.
            t0 = time.perf_counter()
            voc, path = cached_vocabulary(
                folders, extractor=extractor, n_words=vocab_words, seed=seed, cache_dir=cache_dir,
                progress=progress, executor=executor,
            )
            vocab_info.update({"used": True, "file": str(path), "n_words": int(voc.n_words_), **voc.provenance_,
                               "seconds_this_run": round(time.perf_counter() - t0, 3)})
            return voc

        vocabulary = provide
        vocab_info = {"used": False, "train_folders": [str(f) for f in folders]}
    elif needs_vocabulary:
        raise TopolocError(f"{needs_vocabulary} needs a vocabulary: pass --vocab FILE or --vocab-train DIR")
    res = CachedResources(extractor=extractor, vocabulary=vocabulary, progress=progress,
                          training_images=training_images, executor=executor)
    return res, vocab_info


