"""Place-recognition methods and their registry.

Methods are imported lazily so that the CLI starts fast; ``get_method(name)``
returns the class.
"""

from __future__ import annotations

import importlib

from topoloc.errors import TopolocError
from topoloc.methods.base import PlaceRecognizer, map_place_ids
from topoloc.methods.resources import CachedResources, InMemoryResources, Resources

_REGISTRY: dict[str, str] = {
    "bow": "topoloc.methods.bag_of_words:BagOfWords",
    "coocmap": "topoloc.methods.cooc_map:CoocMap",
    "descriptors": "topoloc.methods.global_descriptors:GlobalDescriptors",
    "fabmap": "topoloc.methods.fab_map:FabMap",
    "fabmap2": "topoloc.methods.fab_map:FabMap2",
    "landmarks": "topoloc.methods.landmark_map:LandmarkMap",
    "seqslam": "topoloc.methods.seq_slam:SeqSLAM",
    "seqslam-single": "topoloc.methods.seq_slam:SingleImageSeqSLAM",
    "voting": "topoloc.methods.image_voting:ImageVoting",
}


def available_methods() -> list[str]:
    """Names accepted by ``topoloc evaluate --method``."""
    return sorted(_REGISTRY)


def get_method(name: str) -> type[PlaceRecognizer]:
    """The method class registered under ``name``."""
    try:
        module, cls = _REGISTRY[name].split(":")
    except KeyError:
        raise TopolocError(
            f"unknown method {name!r} (available: {', '.join(available_methods())})"
        ) from None
    return getattr(importlib.import_module(module), cls)


__all__ = [
    "CachedResources", "InMemoryResources", "PlaceRecognizer", "Resources", "available_methods", "get_method",
    "map_place_ids",
]
