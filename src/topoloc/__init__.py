"""topoloc: appearance-based localisation and loop closure.

Everything a user needs is importable from here (loaded on first use, so that
``import topoloc`` and the command line start fast)::

    import topoloc
    day = topoloc.load_traverse("route/day")                  # a folder of images
    cam = topoloc.Traverse.from_images(frames)                # or images in memory
    rec = topoloc.SeqSLAM().fit(day)                          # any recogniser
    S = rec.similarity(cam)                                   # (n_map_places, n_frames)

Conventions used everywhere in the package
------------------------------------------
Every recogniser produces a similarity matrix ``S`` of shape
``(n_map_places, n_queries)``: row ``i`` is the map's ``i``-th place id in
ascending order, column ``j`` is the ``j``-th query image in traverse order, and
higher values mean "more similar".  Ground truth comes as two boolean matrices
``GThard`` and ``GTsoft`` of the same shape (see :mod:`topoloc.datasets.groundtruth`).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from topoloc._version import __version__
from topoloc.errors import NotFittedError, TopolocError

# Public name -> module that defines it.  The recognisers' classes are not listed: a public
# name (in __all__) that is not here is looked up among the registered methods by class name.
_LAZY: dict[str, str] = {
    # the recognisers' contract
    "PlaceRecognizer": "topoloc.methods.base",
    "available_methods": "topoloc.methods",
    "get_method": "topoloc.methods",
    "Resources": "topoloc.resources",
    "CachedResources": "topoloc.resources",
    "InMemoryResources": "topoloc.resources",
    # inputs
    "Traverse": "topoloc.datasets.traverse",
    "load_traverse": "topoloc.datasets.traverse",
    "read_image": "topoloc.datasets.traverse",
    "GroundTruth": "topoloc.datasets.groundtruth",
    "ground_truth_from_places": "topoloc.datasets.groundtruth",
    "ground_truth_from_xy": "topoloc.datasets.groundtruth",
    "ground_truth_from_file": "topoloc.datasets.groundtruth",
    "FeatureConfig": "topoloc.features.local",
    "FeatureExtractor": "topoloc.features.local",
    "FeatureSet": "topoloc.features.local",
    "extract_features": "topoloc.features.local",
    "Vocabulary": "topoloc.vocabulary.vocab",
    "train_vocabulary": "topoloc.vocabulary.vocab",
    # saved maps and localisation
    "Map": "topoloc.maps.map",
    "Localizer": "topoloc.maps.localizer",
    # a long route's map built or updated through scratch files beside it (what `map build` does)
    "spill_to": "topoloc.io.scratch",
    # evaluation
    "evaluate": "topoloc.evaluation.pipeline",
    # run specifications (topoloc.spec): what a command runs, validated once
    "EvaluateSpec": "topoloc.spec",
    "MapBuildSpec": "topoloc.spec",
    "LocalizeSpec": "topoloc.spec",
    "FeatureSpec": "topoloc.spec",
    "VocabularySpec": "topoloc.spec",
    "GroundTruthSpec": "topoloc.spec",
    "InputSpec": "topoloc.spec",
    "SequenceSpec": "topoloc.spec",
    "ExecutionSpec": "topoloc.spec",
    "load_config": "topoloc.spec",
    "compute_metrics": "topoloc.evaluation.metrics",
    "Scores": "topoloc.evaluation.metrics",
    "sequence_similarity": "topoloc.sequence.search",
}

__all__ = [
    "BagOfWords",
    "CachedResources",
    "CoocMap",
    "EvaluateSpec",
    "ExecutionSpec",
    "FabMap",
    "FabMap2",
    "FeatureConfig",
    "FeatureExtractor",
    "FeatureSet",
    "FeatureSpec",
    "GlobalDescriptors",
    "GroundTruth",
    "GroundTruthSpec",
    "ImageVoting",
    "InMemoryResources",
    "InputSpec",
    "LandmarkMap",
    "LocalizeSpec",
    "Localizer",
    "Map",
    "MapBuildSpec",
    "NotFittedError",
    "PlaceRecognizer",
    "Resources",
    "Scores",
    "SeqSLAM",
    "SequenceSpec",
    "SingleImageSeqSLAM",
    "TopolocError",
    "Traverse",
    "Vocabulary",
    "VocabularySpec",
    "__version__",
    "available_methods",
    "compute_metrics",
    "evaluate",
    "extract_features",
    "get_method",
    "ground_truth_from_file",
    "ground_truth_from_places",
    "ground_truth_from_xy",
    "load_config",
    "load_traverse",
    "read_image",
    "sequence_similarity",
    "spill_to",
    "train_vocabulary",
]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is not None:
        value = getattr(importlib.import_module(module), name)
    elif name in __all__:
        value = _recognizer_class(name)
    else:
        raise AttributeError(f"module 'topoloc' has no attribute {name!r}")
    globals()[name] = value  # later look-ups skip this function
    return value


def _recognizer_class(class_name: str) -> Any:
    from topoloc.methods import available_methods, get_method

    for method in available_methods():
        cls = get_method(method)
        if cls.__name__ == class_name:
            return cls
    raise AttributeError(f"module 'topoloc' has no attribute {class_name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY) | set(__all__))


if TYPE_CHECKING:  # static checkers and IDEs see the real names
    from topoloc.datasets.groundtruth import (
        GroundTruth,
        ground_truth_from_file,
        ground_truth_from_places,
        ground_truth_from_xy,
    )
    from topoloc.datasets.traverse import Traverse, load_traverse, read_image
    from topoloc.evaluation.metrics import Scores, compute_metrics
    from topoloc.evaluation.pipeline import evaluate
    from topoloc.features.local import FeatureConfig, FeatureExtractor, FeatureSet, extract_features
    from topoloc.maps.localizer import Localizer
    from topoloc.maps.map import Map
    from topoloc.methods import available_methods, get_method
    from topoloc.methods.bag_of_words import BagOfWords
    from topoloc.methods.base import PlaceRecognizer
    from topoloc.methods.cooc_map import CoocMap
    from topoloc.methods.fab_map import FabMap, FabMap2
    from topoloc.methods.global_descriptors import GlobalDescriptors
    from topoloc.methods.image_voting import ImageVoting
    from topoloc.methods.landmark_map import LandmarkMap
    from topoloc.methods.seq_slam import SeqSLAM, SingleImageSeqSLAM
    from topoloc.resources import CachedResources, InMemoryResources, Resources
    from topoloc.sequence.search import sequence_similarity
    from topoloc.spec import (
        EvaluateSpec,
        ExecutionSpec,
        FeatureSpec,
        GroundTruthSpec,
        InputSpec,
        LocalizeSpec,
        MapBuildSpec,
        SequenceSpec,
        VocabularySpec,
        load_config,
    )
    from topoloc.vocabulary.vocab import Vocabulary, train_vocabulary
