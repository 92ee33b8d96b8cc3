"""Geometric verification of any method's answers: local matches, epipolar geometry, a verified confidence.

:mod:`~topoloc.verification.pairs` checks one query image against one map
image; :mod:`~topoloc.verification.rerank` turns the inliers of each query's
candidates into verified scores; :class:`~topoloc.verification.verifier.Verifier`
runs both over a block of queries.  Arrays and feature sets in, arrays out
(layer 2 of ``docs/architecture.md``).
"""

from topoloc.verification.consistency import confirmed, demote_unconfirmed
from topoloc.verification.pairs import (
    chance_inliers,
    check_pair,
    fundamental_inliers,
    fundamental_mask,
    inlier_threshold,
    mutual_matches,
    prepare_descriptors,
)
from topoloc.verification.rerank import candidate_rows, squash, verified_scores
from topoloc.verification.verifier import (
    DEFAULT_CANDIDATES,
    DEFAULT_MAX_ITERS,
    SEQUENCE_CANDIDATES,
    VerifiedBlock,
    Verifier,
    default_candidates,
)

__all__ = [
    "DEFAULT_CANDIDATES",
    "DEFAULT_MAX_ITERS",
    "SEQUENCE_CANDIDATES",
    "VerifiedBlock",
    "Verifier",
    "candidate_rows",
    "chance_inliers",
    "check_pair",
    "confirmed",
    "default_candidates",
    "demote_unconfirmed",
    "fundamental_inliers",
    "fundamental_mask",
    "inlier_threshold",
    "mutual_matches",
    "prepare_descriptors",
    "squash",
    "verified_scores",
]
