"""Per-query confidence: similarity matrices whose best scores threshold across queries.

A method's raw similarity ``S`` (map places x queries) ranks the places of one
query well, but its scale often changes from query to query (a dark query has
few features and so small scores even where it is right), so thresholding the
best score of each query gives a PR curve without a clean top.
:func:`peak_margin` shifts each column by the best score outside the best
place's own peak, so that a column's best score is its margin over the best
*other* stretch of the map.  See :mod:`topoloc.confidence.margin`.
"""

from __future__ import annotations

from topoloc.confidence.margin import (
    CONFIDENCE_MODES,
    apply_confidence,
    check_confidence,
    peak_extent,
    peak_margin,
    peak_reference,
)

__all__ = [
    "CONFIDENCE_MODES",
    "apply_confidence",
    "check_confidence",
    "peak_extent",
    "peak_margin",
    "peak_reference",
]
