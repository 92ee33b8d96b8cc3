"""Sequence matching: SeqSLAM's trajectory search and Cooc-Map's acceleration-tolerant paths.

See :mod:`topoloc.sequence.search` for the conventions (causal window over the
current query and the ``ds`` before it, shorter windows at the start of a
traverse, costs as mean differences, similarities as negated costs).
"""

from __future__ import annotations

from topoloc.sequence.confidence import SEQUENCE_CONFIDENCES, sequence_stretch, stretch_margin
from topoloc.sequence.search import (
    SEQUENCE_MEMORY_BUDGET,
    acceleration_search,
    constant_velocity_search,
    contrast_enhance,
    search_memory_bytes,
    sequence_search,
    sequence_similarity,
    similarity_to_difference,
    uniqueness_margin,
    velocity_offsets,
)

__all__ = [
    "SEQUENCE_CONFIDENCES",
    "SEQUENCE_MEMORY_BUDGET",
    "acceleration_search",
    "constant_velocity_search",
    "contrast_enhance",
    "search_memory_bytes",
    "sequence_search",
    "sequence_similarity",
    "sequence_stretch",
    "similarity_to_difference",
    "stretch_margin",
    "uniqueness_margin",
    "velocity_offsets",
]
