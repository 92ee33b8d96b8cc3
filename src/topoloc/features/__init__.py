"""Local features (SIFT, RootSIFT, ORB, AKAZE) with a parallel, disk-cached extractor."""

from topoloc.features.cache import default_cache_dir, file_sha1
from topoloc.features.local import (
    FEATURES_SCHEMA,
    METHODS,
    FeatureConfig,
    FeatureExtractor,
    FeatureSet,
    check_method_available,
    extract_features,
)

__all__ = [
    "FEATURES_SCHEMA",
    "METHODS",
    "FeatureConfig",
    "FeatureExtractor",
    "FeatureSet",
    "check_method_available",
    "default_cache_dir",
    "extract_features",
    "file_sha1",
]
