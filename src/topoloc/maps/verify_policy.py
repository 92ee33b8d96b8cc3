"""Whether and how answers against a saved map are verified (:mod:`topoloc.verification`).

Verification matches a query's local features against the map images of its
candidate places, which a saved map reaches through its tours' folders or
recordings (their features come from the feature cache, extracted once).
This module says whether a map can verify, what it does when no one says,
and builds the verification stage over its tours.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.errors import TopolocError
from topoloc.features import FeatureConfig
from topoloc.maps.tours import reload_tour
from topoloc.resources import Resources
from topoloc.spec import VerificationSpec
from topoloc.spec.parts import verify_from_env
from topoloc.spec.setup import build_verifier
from topoloc.verification import Verifier

log = logging.getLogger(__name__)


def verification_blocker(tours: Sequence[dict[str, Any]]) -> str:
    """Why answers against a map of these tour records cannot be verified, or "" when they can."""
    for rec in tours:
        root = str(rec.get("root", ""))
        src = rec.get("source") or {}
        if root.startswith("<"):
            return f"tour {rec.get('name')!r} was built from images in memory, which cannot be read again"
        where = Path(src["file"]) if src else Path(root)
        if not where.exists():
            return f"tour {rec.get('name')!r} is gone: {where}"
    return ""


def default_verify(calibration: dict[str, Any] | None, spec: dict[str, Any] | None) -> bool | None:
    """Whether answers are verified when no one says: as the threshold was calibrated, else as the map was built.

    A map calibrated with verification recorded keeps that setting (the
    threshold holds for those scores only); a map built before verification
    existed, or calibrated before it was recorded, scores as it always did
    (False); else None: wherever it can.
    """
    cal = calibration or {}
    if "verify" in cal:
        return bool(cal["verify"])
    if calibration is not None or not spec or "verification" not in spec:
        return False
    return (spec.get("verification") or {}).get("enabled")


def resolve_verify(verify: bool | None, *, calibration: dict[str, Any] | None, spec: dict[str, Any] | None,
                   verifies_geometry: bool, blocker: Callable[[], str], where: object) -> bool:
    """Whether to verify: as asked; else as the threshold was calibrated; else ``$TOPOLOC_VERIFY``; else
    :func:`default_verify`; else whether the map can verify.  A calibration's record comes before the
    environment: its threshold holds for the scores it was chosen on only."""
    if verify is None and "verify" in (calibration or {}):
        verify = bool((calibration or {})["verify"])
    if verify is None:
        verify = verify_from_env()
    if verify is not None:
        return verify
    default = default_verify(calibration, spec)
    if default is not None:
        return default
    if verifies_geometry:
        return False
    why = blocker()
    if why:
        log.info("%s cannot verify answers (%s): they are not verified", where, why)
    return not why


def map_verifier(tours: Sequence[dict[str, Any]], place_ids: np.ndarray, resources: Resources, *,
                 where: str, candidates: int | None = None, sequence: int = 0) -> Verifier:
    """The verification stage against a map of these tour records (their images read again, fingerprints checked).

    Raises
    ------
    TopolocError
        One line naming the tour that cannot be read again.
    """
    why = verification_blocker(tours)
    if why:
        raise TopolocError(f"{where} cannot verify answers: {why} (use --no-verify)")
    traverses = [reload_tour(rec, purpose="to verify answers") for rec in tours]
    v = build_verifier(VerificationSpec(enabled=True, candidates=candidates), place_ids, traverses, resources,
                       what=where, sequence=sequence)
    assert v is not None
    return v


def verification_info(tours: Sequence[dict[str, Any]], features: FeatureConfig,
                      default: bool | None) -> dict[str, Any]:
    """Whether a map can verify answers, and the memory its map images' features then take."""
    why = verification_blocker(tours)
    n_images = sum(int(t.get("n_images", 0) or 0) for t in tours)
    # keypoints: 5 float32 columns; descriptors: descriptor_dim columns of descriptor_dtype
    per_image = int(features.max_features) * (
        20 + features.descriptor_dim * np.dtype(features.descriptor_dtype).itemsize)
    return {"can_verify": not why, **({"why_not": why} if why else {}),
            "default": default, "map_images": n_images,
            "features_bytes_at_most": n_images * per_image}


__all__ = ["default_verify", "map_verifier", "resolve_verify", "verification_blocker", "verification_info"]
