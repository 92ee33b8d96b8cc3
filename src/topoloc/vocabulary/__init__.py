"""Visual vocabularies: k-means words over local descriptors and fast quantisation."""

from topoloc.vocabulary.vocab import (
    DEFAULT_EF_SEARCH,
    DEFAULT_N_ITER,
    VOCAB_SCHEMA,
    Vocabulary,
    cached_vocabulary,
    parse_descriptor_kind,
    train_vocabulary,
    vocabulary_cache_key,
)

__all__ = [
    "DEFAULT_EF_SEARCH",
    "DEFAULT_N_ITER",
    "VOCAB_SCHEMA",
    "Vocabulary",
    "cached_vocabulary",
    "parse_descriptor_kind",
    "train_vocabulary",
    "vocabulary_cache_key",
]
