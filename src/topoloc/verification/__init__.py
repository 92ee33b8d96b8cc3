"""Geometric verification of any method's answers: local matches, epipolar geometry, a decision and a confidence.

:mod:`~topoloc.verification.pairs` checks one query image against one map
image; :mod:`~topoloc.verification.rerank` chooses each query's answer among
its candidates and ranks the answers; :mod:`~topoloc.verification.decision` is
the one home of what verifies an answer and of its confidence;
:class:`~topoloc.verification.verifier.Verifier` runs them over a block of
queries.  Arrays and feature sets in, arrays out (layer 2 of ``docs/architecture.md``).
"""

from topoloc.verification.consistency import confirmed, demote_unconfirmed
from topoloc.verification.decision import (
    CLIMB,
    DEFAULT_CONFIDENCE,
    DEFAULT_MAX_ITERS,
    MIN_SUPPORT,
    ConfidenceModel,
    LookAlikes,
    VerificationRule,
    query_confusion,
    strength,
    tells_apart,
    verified,
)
from topoloc.verification.pairs import (
    PairCheck,
    check_pair,
    distinctive_matches,
    fundamental_inliers,
    fundamental_mask,
    inlier_threshold,
    mutual_matches,
    prepare_descriptors,
)
from topoloc.verification.rerank import candidate_rows, choose_winner, squash, verified_scores
from topoloc.verification.verifier import (
    DEFAULT_CANDIDATES,
    SEQUENCE_CANDIDATES,
    VerifiedBlock,
    Verifier,
    default_candidates,
)

__all__ = [
    "CLIMB",
    "DEFAULT_CANDIDATES",
    "DEFAULT_CONFIDENCE",
    "DEFAULT_MAX_ITERS",
    "MIN_SUPPORT",
    "SEQUENCE_CANDIDATES",
    "ConfidenceModel",
    "LookAlikes",
    "PairCheck",
    "VerificationRule",
    "VerifiedBlock",
    "Verifier",
    "candidate_rows",
    "check_pair",
    "choose_winner",
    "confirmed",
    "default_candidates",
    "demote_unconfirmed",
    "distinctive_matches",
    "fundamental_inliers",
    "fundamental_mask",
    "inlier_threshold",
    "mutual_matches",
    "prepare_descriptors",
    "query_confusion",
    "squash",
    "strength",
    "tells_apart",
    "verified",
    "verified_scores",
]
