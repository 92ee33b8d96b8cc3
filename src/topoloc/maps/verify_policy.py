"""Whether and how answers against a saved map are verified (:mod:`topoloc.verification`).

Verification matches a query's local features against the map images of its
candidate places, which a saved map reaches through its tours' folders or
recordings: only the images it recorded, and only those whose content is
still the one it was built from (:mod:`topoloc.maps.tour_images`; their
features come from the feature cache, extracted once).  This module says
whether a map can verify, what a run does when no one says (the one
precedence is :func:`topoloc.spec.parts.choose_verify`), and builds the
verification stage over its tours.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.datasets.traverse import Traverse
from topoloc.errors import ParameterError, TopolocError
from topoloc.features import FeatureConfig
from topoloc.maps.calibration import calibrated_verify
from topoloc.maps.tour_images import TourImages, read_again
from topoloc.maps.tours import reload_tour
from topoloc.resources import Resources
from topoloc.spec import VerificationSpec
from topoloc.spec.parts import VerifyChoice, choose_verify
from topoloc.spec.setup import build_verifier
from topoloc.verification import ConfidenceModel, Verifier

log = logging.getLogger(__name__)


def _unreadable(rec: dict[str, Any]) -> str:
    """Why a tour's images cannot be read again ("" when its folder or recording is there)."""
    root = str(rec.get("root", ""))
    src = rec.get("source") or {}
    if root.startswith("<"):
        return f"tour {rec.get('name')!r} was built from images in memory, which cannot be read again"
    where = Path(src["file"]) if src else Path(root)
    if not where.exists():
        return f"tour {rec.get('name')!r} is gone: {where}"
    return ""


def verification_blocker(tours: Sequence[dict[str, Any]]) -> str:
    """Why answers against a map of these tour records cannot be verified at all, or "" when some tour can be read.

    A tour that is gone leaves its places without images to verify, the others are still verified
    (:func:`verification_tours` says so in one line).
    """
    reasons = [_unreadable(rec) for rec in tours]
    return reasons[0] if reasons and all(reasons) else ""


def verification_tours(tours: Sequence[dict[str, Any]], *, where: str = "the map") -> list[Traverse]:
    """The map's tours as verification reads them: the recorded images whose content is the recorded one.

    A tour that is gone or changed, and images changed or gone since the build,
    are left out with one warning line (naming ``--no-verify``) for them all.

    Raises
    ------
    TopolocError
        When no image of any tour can be used.
    """
    out: list[Traverse] = []
    left_out: list[str] = []
    for rec in tours:
        why = _unreadable(rec)
        if why:
            left_out.append(why)
            continue
        images = rec.get("images")
        if rec.get("source") or not isinstance(images, TourImages):
            # A recording (its frames' content is in its fingerprint), or a map saved before image digests were
            # recorded: the whole tour, checked against its fingerprint.
            try:
                out.append(reload_tour(rec, purpose="to verify answers"))
            except TopolocError as exc:
                left_out.append(str(exc))
            continue
        again = read_again(rec, images)
        bad = len(again.changed) + len(again.missing)
        if bad:
            first = (again.changed or again.missing)[0]
            left_out.append(f"{bad} of {len(images.names)} images of tour {rec.get('name')!r} "
                            f"{'changed' if again.changed else 'are gone'} since the map was built (first: {first})")
        if again.traverse is not None:
            out.append(again.traverse)
    if not out:
        raise TopolocError(f"{where} cannot verify answers: {'; '.join(left_out) or 'it has no tour'}")
    if left_out:
        log.warning("%s: %s: those images are not used to verify answers (answers at their places are not "
                    "verified; --no-verify to verify none)", where, "; ".join(left_out))
    return out


def _built_verification(spec: dict[str, Any] | None) -> dict[str, Any]:
    """The verification settings a map's build recorded (``map build --verify``, ``--min-support``; {}: none)."""
    return (spec or {}).get("verification") or {}


def recorded_verify(calibration: dict[str, Any] | None, spec: dict[str, Any] | None) -> bool | None:
    """What a map records of verification: as its threshold was calibrated, else as it was built.

    A map calibrated with verification recorded keeps that setting (the
    threshold holds for those scores only); a map built before verification
    existed, or calibrated before it was recorded, scores as it always did
    (False); else the build's ``--verify/--no-verify`` (None: wherever it can).
    """
    calibrated = calibrated_verify(calibration)
    if calibrated is not None:
        return calibrated
    if calibration is not None or not spec or "verification" not in spec:
        return False
    return _built_verification(spec).get("enabled")


def choice_for(asked: bool | None, *, calibration: dict[str, Any] | None, spec: dict[str, Any] | None,
               verifies_geometry: bool) -> VerifyChoice:
    """The choice to verify against a map (:func:`topoloc.spec.parts.choose_verify` with the map's record).

    The calibration's record (``verify``, with the threshold it holds for), then
    the build's (``verification.enabled``); a map with neither (built before
    verification existed, or calibrated before it was recorded) is ``legacy``.
    """
    calibrated = calibrated_verify(calibration)
    recorded = bool(spec) and "verification" in (spec or {})
    built = _built_verification(spec).get("enabled")
    legacy = calibrated is None and (calibration is not None or not recorded)
    return choose_verify(asked, calibrated=calibrated, built=built, legacy=legacy, checks_geometry=verifies_geometry)


def with_map_floor(spec: VerificationSpec, *, calibration: dict[str, Any] | None,
                   built: dict[str, Any] | None, where: str = "the map") -> VerificationSpec:
    """``spec`` with the map's support floor where the run gives none: the one precedence of the floor.

    In order: the run's (``--min-support``, the ROS node's ``min_support``, a
    configuration file's ``[verification] min_support``); the floor the
    calibration's answers were verified with (its threshold holds for that
    floor only: the confidence follows it); the build's (``map build
    --min-support``); else :data:`topoloc.verification.MIN_SUPPORT`
    (:meth:`VerificationSpec.rule`).

    Raises
    ------
    TopolocError
        One line naming ``where`` when the floor it records is not one :class:`VerificationSpec` takes.
    """
    if spec.min_support is not None:
        return spec
    cal = calibration or {}
    floor = cal["min_support"] if "min_support" in cal else _built_verification(built).get("min_support")
    if floor is None:
        return spec
    try:
        return dataclasses.replace(spec, min_support=floor)
    except ParameterError as exc:  # written by other code: the header's CRC says it is intact, not that it is sensible
        raise TopolocError(f"{where} records a support floor it cannot verify with: {exc}; build or calibrate it "
                           "again") from None


def settle(choice: VerifyChoice, why_not: str, *, where: str) -> bool:
    """Whether a run verifies, given the choice and why the map cannot (""): one rule for every caller.

    Asked explicitly (an option, a ROS parameter, ``$TOPOLOC_VERIFY=1``) where the
    map cannot verify: a one-line error naming why and ``--no-verify``.  Otherwise
    a map that cannot verify localises unverified, with one warning line.

    Raises
    ------
    TopolocError
        Verification asked for explicitly where the map cannot verify.
    """
    if choice.enabled is False:
        return False
    if not why_not:
        return True
    if choice.enabled and choice.explicit:
        raise TopolocError(f"{where} cannot verify answers: {why_not} (use --no-verify)")
    log.warning("%s cannot verify answers (%s): they are not verified%s (--no-verify: not verified, without this "
                "line)", where, why_not, ", although its threshold was calibrated on verified answers"
                if choice.source == "the map's calibration" else "")
    return False


def map_verifier(tours: Sequence[dict[str, Any]], place_ids: np.ndarray, resources: Resources, *,
                 where: str, spec: VerificationSpec | None = None, sequence: int = 0,
                 confidence: ConfidenceModel | None = None) -> Verifier:
    """The verification stage against a map of these tour records (:func:`verification_tours`).

    Raises
    ------
    TopolocError
        One line when no image of the map can be used.
    """
    return build_verifier(spec or VerificationSpec(), place_ids, verification_tours(tours, where=where), resources,
                          what=where, sequence=sequence, confidence=confidence)


def verification_info(tours: Sequence[dict[str, Any]], features: FeatureConfig,
                      default: bool | None) -> dict[str, Any]:
    """Whether a map can verify answers, and the memory its map images' features then take."""
    why = verification_blocker(tours)
    n_images = sum(int(t.get("n_images", 0) or 0) for t in tours)
    # keypoints: 5 float32 columns; descriptors: descriptor_dim columns of descriptor_dtype
    per_image = int(features.max_features) * (
        20 + features.descriptor_dim * np.dtype(features.descriptor_dtype).itemsize)
    gone = [r for r in (_unreadable(rec) for rec in tours) if r]
    return {"can_verify": not why, **({"why_not": why} if why else {}), **({"tours_gone": gone} if gone else {}),
            "default": default, "map_images": n_images,
            "content_recorded": all(isinstance(t.get("images"), TourImages) or t.get("source") for t in tours),
            "features_bytes_at_most": n_images * per_image}


__all__ = [
    "choice_for",
    "map_verifier",
    "recorded_verify",
    "settle",
    "verification_blocker",
    "verification_info",
    "verification_tours",
    "with_map_floor",
]
