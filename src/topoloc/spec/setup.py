"""From a run's specification to its recogniser and what it reads: the one door to resources.

Every command and every benchmark that extracts features goes through
:func:`make_resources`: the feature extractor of the run's resolved
:class:`~topoloc.features.FeatureConfig`, the vocabulary of its
:class:`~topoloc.spec.parts.VocabularySpec` (loaded and checked now, or trained
lazily on first use and cached), and the executor per-image work runs on.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from topoloc.cluster import Executor
from topoloc.datasets.traverse import find_images
from topoloc.errors import ParameterError
from topoloc.features import FeatureConfig, FeatureExtractor
from topoloc.methods import get_method
from topoloc.methods.base import PlaceRecognizer, parse_param
from topoloc.progress import ProgressFactory
from topoloc.resources import CachedResources
from topoloc.spec.parts import VocabularySpec
from topoloc.vocabulary import Vocabulary


def build_method(name: str, params: Mapping[str, Any]) -> PlaceRecognizer:
    """Instantiate method ``name``; string values (``--param KEY=VALUE``) are converted to the parameters' types.

    Every parameter is validated here, before any image is read.
    """
    cls = get_method(name)
    names = set(cls.param_names())
    # Values already typed (from Python or a configuration file) are taken as they are; an unknown
    # name still gets parse_param's one-line error.
    kwargs = {k: v if k in names and not isinstance(v, str) else parse_param(cls, k, str(v))
              for k, v in params.items()}
    method = cls(**kwargs)
    method.validate_params()
    return method


def make_resources(
    features: FeatureConfig,
    vocabulary: VocabularySpec | Vocabulary | None = None,
    *,
    cache_dir: str | Path | None = None,
    needs_vocabulary: str = "",
    progress: ProgressFactory | None = None,
    executor: Executor | None = None,
) -> tuple[CachedResources, dict[str, Any]]:
    """Feature extractor and vocabulary for a run, and the vocabulary's record for ``metrics.json``.

    Parameters
    ----------
    features : FeatureConfig
        The resolved feature settings (:meth:`FeatureSpec.config`).
    vocabulary : VocabularySpec or Vocabulary, optional
        A file (loaded and checked against the descriptors now), folders to train
        one on (trained on first use, inside ``fit``, and cached under
        ``cache_dir``), or a vocabulary in memory.
    cache_dir : path, optional
        Feature and vocabulary cache.
    needs_vocabulary : str
        The user of the vocabulary (a method); when set, no vocabulary is an error.
    progress, executor
        Progress bars; where per-block work runs (default: this process's threads).

    Returns
    -------
    resources : CachedResources
    vocab_info : dict
        ``{"used": bool, ...}``: the file or training folders, the number of
        words and the vocabulary's provenance; after a training,
        ``seconds_this_run``.
    """
    extractor = FeatureExtractor(features, cache_dir=cache_dir)
    vocab_info: dict[str, Any] = {"used": False}
    voc: Any = None
    training_images: list[Path] = []
    if isinstance(vocabulary, Vocabulary):
        voc = vocabulary
        voc.check_compatible(features.descriptor_kind)
        vocab_info = {"used": True, "file": "in memory", "n_words": int(voc.n_words_), **voc.provenance_}
    elif vocabulary is not None and vocabulary.file is not None:
        voc = Vocabulary.load(vocabulary.file)
        voc.check_compatible(features.descriptor_kind, source=vocabulary.file)
        vocab_info = {"used": True, "file": str(vocabulary.file), "n_words": int(voc.n_words_), **voc.provenance_}
    elif vocabulary is not None and vocabulary.train:
        from topoloc.vocabulary import cached_vocabulary

        spec = vocabulary
        training_images = find_images(list(spec.train))

        def provide() -> Any:
            # Called by the first user of the vocabulary (inside ``fit``): its time is recorded
            # here so that ``evaluate`` can report it apart from the fit time.
            t0 = time.perf_counter()
            trained, path = cached_vocabulary(
                list(spec.train), extractor=extractor, n_words=spec.words, seed=spec.seed, cache_dir=cache_dir,
                progress=progress, executor=executor,
            )
            vocab_info.update({"used": True, "file": str(path), "n_words": int(trained.n_words_),
                               **trained.provenance_, "seconds_this_run": round(time.perf_counter() - t0, 3)})
            return trained

        voc = provide
        vocab_info = {"used": False, "train_folders": [str(f) for f in spec.train]}
    elif needs_vocabulary:
        raise ParameterError("vocabulary", f"is missing: {needs_vocabulary} needs a vocabulary; give a vocabulary "
                                           "file or folders to train one on")
    res = CachedResources(extractor=extractor, vocabulary=voc, progress=progress,
                          training_images=training_images, executor=executor)
    return res, vocab_info


__all__ = ["build_method", "make_resources"]
