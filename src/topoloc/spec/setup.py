"""From a run's specification to its recogniser and what it reads: the one door to resources.

Every command and every benchmark that extracts features goes through
:func:`make_resources`: the feature extractor of the run's resolved
:class:`~topoloc.features.FeatureConfig`, the vocabulary of its
:class:`~topoloc.spec.parts.VocabularySpec` (loaded and checked now, or trained
lazily on first use and cached), and the executor per-image work runs on.

With no vocabulary given, a method that needs one gets the **default
vocabulary**: one trained on the map's own tours (as RTAB-Map does), on first
use, from the features the method extracts anyway, and cached by the tours'
fingerprints (:func:`tours_vocabulary`).  ``docs/results/vocabulary.md``
("Default vocabulary", ``benchmarks/bench_default_vocab.py``) measures what it
costs per method against a vocabulary trained on separate images.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.cluster import Executor
from topoloc.datasets.traverse import Traverse, find_images
from topoloc.errors import ParameterError, TopolocError, input_error
from topoloc.features import FeatureConfig, FeatureExtractor
from topoloc.features.cache import cache_root
from topoloc.methods import get_method
from topoloc.methods.base import PlaceRecognizer, parse_param
from topoloc.progress import ProgressFactory
from topoloc.resources import CachedResources, Resources
from topoloc.spec.parts import VerificationSpec, VocabularySpec
from topoloc.verification import DEFAULT_CONFIDENCE, ConfidenceModel, Verifier, default_candidates
from topoloc.vocabulary import Vocabulary
from topoloc.vocabulary.vocab import VOCAB_SCHEMA

log = logging.getLogger(__name__)


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
    tours: Sequence[Traverse] = (),
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
    tours : sequence of Traverse
        The map's tours.  With no vocabulary given and ``needs_vocabulary`` set,
        the default vocabulary is trained on them on first use
        (:func:`tours_vocabulary`) and they are also the training images of
        the methods that learn word statistics (FAB-MAP).

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
    elif needs_vocabulary and tours:
        spec = vocabulary if vocabulary is not None else VocabularySpec()
        res = CachedResources(extractor=extractor, progress=progress, training=list(tours), executor=executor)

        def default() -> Any:
            t0 = time.perf_counter()
            trained, path = tours_vocabulary(tours, res, words=spec.words, seed=spec.seed, cache_dir=cache_dir)
            vocab_info.update({"used": True, "file": str(path), "n_words": int(trained.n_words_),
                               **trained.provenance_, "seconds_this_run": round(time.perf_counter() - t0, 3)})
            return trained

        res._vocabulary = default
        vocab_info = {"used": False, "source": "map tours"}
        return res, vocab_info
    elif needs_vocabulary:
        raise ParameterError("vocabulary", f"is missing: {needs_vocabulary} needs a vocabulary; give a vocabulary "
                                           "file or folders to train one on")
    res = CachedResources(extractor=extractor, vocabulary=voc, progress=progress,
                          training_images=training_images, executor=executor)
    return res, vocab_info


def tours_vocabulary(
    tours: Sequence[Traverse],
    resources: CachedResources,
    *,
    words: int,
    seed: int,
    cache_dir: str | Path | None = None,
) -> tuple[Vocabulary, Path]:
    """The default vocabulary: ``words`` k-means words of the tours' own features, trained once and cached.

    The features are the tours' (``resources.features``: the ones the method
    then uses, extracted once); a uniform sample of at most the default
    ``max_descriptors`` of them, drawn with ``seed`` (random keys per tour from
    the seed ``(seed, tour number)``), is clustered by :meth:`Vocabulary.fit`.
    The file is ``<cache>/vocab/tours-<key>.tlv``, the key hashing the tours'
    fingerprints and every training setting, so a second run on the same
    tours loads it.

    Returns
    -------
    vocabulary : Vocabulary
        ``provenance_["source"] == "map tours"``, with the tours' names and roots.
    path : Path
        The cache file.

    Raises
    ------
    TopolocError
        When the tours have fewer than 2 local features in all.
    """
    extractor = resources.extractor
    proto = Vocabulary(n_words=words, seed=seed)
    key_src = {"schema": VOCAB_SCHEMA, "tours": [t.fingerprint() for t in tours], "features": extractor.config.key(),
               **{k: v for k, v in proto.get_params().items() if k != "ef_search"}, "kmeans": "lloyd-hnsw"}
    key = hashlib.sha1(json.dumps(key_src, sort_keys=True).encode()).hexdigest()[:20]
    root = cache_root(cache_dir) if cache_dir is not None else extractor.cache_dir
    file = root / "vocab" / f"tours-{key}.tlv"
    if file.is_file():
        try:
            return Vocabulary.load(file), file
        except TopolocError as exc:
            log.warning("ignoring unusable cached vocabulary, training again (%s)", exc)
    cap = int(proto.max_descriptors)
    keys = np.empty(0, np.float64)
    kept: list[np.ndarray] = []
    n_total, n_images = 0, 0
    for i, tour in enumerate(tours):
        descs = [f.descriptors for f in resources.features(tour) if len(f)]
        n_images += len(tour)
        if not descs:
            continue
        d = np.concatenate(descs)
        n_total += len(d)
        keys = np.concatenate([keys, np.random.default_rng([int(seed), i]).random(len(d))])
        kept.append(d)
        if len(keys) > cap:  # keep the cap's smallest keys: a uniform sample, memory bounded by one tour
            sel = np.sort(np.argpartition(keys, cap - 1)[:cap])
            allk = np.concatenate(kept)
            keys, kept = keys[sel], [allk[sel]]
    if n_total < 2:
        raise input_error(f"the map's tours have only {n_total} local features: cannot train the default "
                          "vocabulary on them (give --vocab or --vocab-train)", ", ".join(str(t.root) for t in tours))
    sample = np.concatenate(kept)
    provenance = {"source": "map tours", "tours": [t.name for t in tours],
                  "folders_of_tours": [str(t.root) for t in tours if t.kind == "files"],
                  "n_images": n_images, "n_descriptors": n_total, "feature_key": extractor.config.key(),
                  "feature_config": asdict(extractor.config)}
    t0 = time.perf_counter()
    voc = Vocabulary(n_words=words, seed=seed, max_descriptors=cap).fit(
        sample, descriptor_kind=extractor.config.descriptor_kind, provenance=provenance,
        progress=resources.progress)
    voc.provenance_["total_seconds"] = round(time.perf_counter() - t0, 3)
    try:
        voc.save(file)
    except OSError as exc:
        log.warning("cannot write vocabulary cache %s (%s)", file, exc)
    return voc, file



def unverifiable(tours: Sequence[Traverse]) -> str:
    """Why map images of ``tours`` cannot be verified ("" when they can): verification matches their local features."""
    for t in tours:
        if t.kind == "words":
            return f"tour {t.name!r} holds visual words, not images or local features"
    return ""


def build_verifier(spec: VerificationSpec, place_ids: np.ndarray, tours: Sequence[Traverse],
                   resources: Resources, *, what: str = "the map", sequence: int = 0,
                   confidence: ConfidenceModel | None = None) -> Verifier:
    """The verification stage of a run (:mod:`topoloc.verification`) over the map's tours.

    Whether a run verifies is decided before (:func:`topoloc.spec.parts.choose_verify`);
    this builds the stage.

    Parameters
    ----------
    spec : VerificationSpec
        Its settings (candidates, the decision's rule).
    place_ids : ndarray of int64, shape (n_places,)
        The recogniser's place of each row of S (sorted).
    tours : sequence of Traverse
        The map's tours: the images of each place.
    resources : Resources
        Where their local features come from (the run's feature settings and cache).
    what : str
        Named in the error.
    sequence : int
        The run's ``--sequence N`` (0: single images), which sets the default
        number of candidates (:func:`topoloc.verification.default_candidates`).
    confidence : ConfidenceModel, optional
        Default :data:`topoloc.verification.DEFAULT_CONFIDENCE`.

    Raises
    ------
    ParameterError
        Where the tours cannot be verified (visual words, no images).
    """
    why = unverifiable(tours)
    if why:
        raise ParameterError("verification.enabled", f"{what} cannot be verified: {why} (use --no-verify)")
    # Every map image as (row, tour, index in the tour), sorted by row: a place's images are one slice.
    n = len(place_ids)
    row = np.concatenate([np.searchsorted(place_ids, t.places) for t in tours]) if tours else np.zeros(0, np.int64)
    tour = np.concatenate([np.full(len(t), ti) for ti, t in enumerate(tours)]) if tours else row
    index = np.concatenate([np.arange(len(t)) for t in tours]) if tours else row
    places = np.concatenate([t.places for t in tours]) if tours else row
    known = row < n
    known[known] = place_ids[row[known]] == places[known]
    order = np.argsort(row[known], kind="stable")
    row, tour, index = row[known][order], tour[known][order], index[known][order]
    starts = np.searchsorted(row, np.arange(n + 1))
    feats: dict[int, list[Any]] = {}

    def images_of(r: int) -> list[tuple[int, int]]:
        a, b = starts[r], starts[r + 1]
        return list(zip(tour[a:b].tolist(), index[a:b].tolist(), strict=True))

    def place_images(r: int) -> list[Any]:
        out = []
        for ti, k in images_of(r):
            if ti not in feats:  # a tour's features at its first candidate: from the feature store, extracted once
                feats[ti] = resources.features(tours[ti], timed=False)
            out.append(feats[ti][k])
        return out

    def image_names(r: int) -> list[str]:
        return [str(tours[ti].images[k]) for ti, k in images_of(r)]

    candidates = spec.candidates if spec.candidates is not None else default_candidates(sequence)
    return Verifier(place_images, candidates=candidates, rule=spec.rule(),
                    confidence=confidence or DEFAULT_CONFIDENCE, image_names=image_names)


__all__ = ["build_method", "build_verifier", "make_resources", "tours_vocabulary", "unverifiable"]
