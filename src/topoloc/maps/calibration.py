"""A map's acceptance threshold: chosen on a labelled tour, stored in the map, read by every localiser.

The calibration record (the ``calibration`` of a map file's header,
``docs/protocol.md``) holds the threshold, the precision and recall reached on
the tour it was chosen on, how that tour's frames were matched (sequence,
verification) and whether tours were added since (stale).  The functions here
choose it from scores and read it; :class:`~topoloc.maps.map.Map` keeps it.
"""

from __future__ import annotations

import logging
import math
from datetime import UTC, datetime
from typing import Any

import numpy as np

from topoloc.datasets.groundtruth import GroundTruth
from topoloc.errors import ParameterError, TopolocError
from topoloc.ranking import threshold_sweep
from topoloc.spec import SequenceSpec
from topoloc.verification import DEFAULT_CONFIDENCE, ConfidenceModel, VerifiedBlock

log = logging.getLogger(__name__)


def check_precision(precision: float) -> None:
    """Refuse a precision outside (0, 1] (one line naming the parameter)."""
    if isinstance(precision, bool) or not isinstance(precision, int | float) or not 0 < precision <= 1:
        raise ParameterError("precision", f"must be in (0, 1], got {precision!r}")


def json_calibration(calibration: dict[str, Any] | None) -> dict[str, Any] | None:
    """A stored calibration with a threshold JSON can hold: maps saved before null stood for "none reached"
    wrote ``Infinity``, which Python's reader accepts but strict JSON does not (``map info --json``)."""
    if calibration is None or not isinstance(calibration.get("threshold"), float):
        return calibration
    if math.isfinite(calibration["threshold"]):
        return calibration
    return {**calibration, "threshold": None}


def calibrated_verify(calibration: dict[str, Any] | None) -> bool | None:
    """Whether the calibration's answers were verified (None: not recorded, or no calibration)."""
    cal = calibration or {}
    return bool(cal["verify"]) if "verify" in cal else None


def recorded_min_support(record: dict[str, Any] | None) -> int | None:
    """The support floor a map's record holds under ``min_support``: a calibration's (the floor its answers were
    verified with) or a build's verification settings (``map build --min-support``); None: none recorded."""
    value = (record or {}).get("min_support")
    return int(value) if isinstance(value, int) and not isinstance(value, bool) else None


def is_stale(calibration: dict[str, Any] | None) -> bool:
    """Whether tours were added after the calibration (its threshold was chosen on other scores)."""
    return bool(calibration and calibration.get("stale"))


def tours_added_since(calibration: dict[str, Any] | None) -> list[str]:
    """The tours added after the calibration (:func:`mark_stale`)."""
    return [str(t) for t in (calibration or {}).get("tours_added_since", [])]


def threshold_of(calibration: dict[str, Any] | None) -> float | None:
    """The score above which a localisation is accepted, or None without a calibration (``inf``: none reached)."""
    if calibration is None:
        return None
    value = calibration.get("threshold")
    return math.inf if value is None else float(value)


def calibrated_sequence(calibration: dict[str, Any] | None) -> SequenceSpec:
    """The sequence matching a calibration was chosen with (single images: length 0, also when none is recorded)."""
    seq = (calibration or {}).get("sequence") or {}
    return SequenceSpec(length=int(seq.get("length", 0)), mode=str(seq.get("mode", "constant")))


def mark_stale(calibration: dict[str, Any] | None, tour_name: str) -> dict[str, Any] | None:
    """The calibration kept, marked stale: a tour added since changes the scores it was chosen on.

    ``stale_since`` names the first tour added after it, ``tours_added_since`` all of them;
    calibrating again clears both.
    """
    if calibration is None:
        return None
    added = [*calibration.get("tours_added_since", []), tour_name]
    return {**calibration, "stale": True, "stale_since": calibration.get("stale_since", tour_name),
            "tours_added_since": added}


def _sweep(values: np.ndarray, right: np.ndarray, counted: np.ndarray, n_pos: int, precision: float,
           what: str) -> tuple[float | None, float, float]:
    """(threshold, recall, precision reached): the lowest value at which the answers at least that high reach
    ``precision`` (None: no value does, one warning)."""
    s, tp, fp, last = threshold_sweep(values, right, counted)
    n_counted = tp + fp
    prec = np.where(n_counted > 0, tp / np.maximum(n_counted, 1), 1.0)
    ok = last & (prec >= precision) & (n_counted > 0)
    if ok.any():
        k = int(np.flatnonzero(ok)[-1])
        return float(s[k]), float(tp[k] / n_pos), float(prec[k])
    # JSON has no infinity: null stands for "no threshold reached", which accepts nothing.
    log.warning("calibration on %s: no threshold reaches precision %g, so the map now accepts no "
                "localisation; calibrate on a longer tour or ask for a lower --precision", what, precision)
    return None, 0.0, 1.0


def choose_threshold(S: np.ndarray, gt: GroundTruth, *, precision: float = 0.99, query: str = "",
                     ground_truth: str = "", tolerance: str = "", sequence: SequenceSpec | None = None,
                     verified: VerifiedBlock | None = None, confidence: ConfidenceModel | None = None,
                     verify: bool | None = None, min_support: int | None = None) -> dict[str, Any]:
    """The calibration record of a labelled tour's scores (:meth:`topoloc.maps.Map.calibrate` documents it).

    Without ``verified``, each query's answer is the best place of ``S`` and the
    threshold is on its score (``threshold_on: "score"``), and a confidence
    model of the score is fitted.  With it (the verification of ``S``), the
    answers are the verified block's, their confidence model is fitted on the
    tour (:meth:`~topoloc.verification.ConfidenceModel.fit`, from ``confidence``'s
    slope where the tour has too few wrong answers to fit one) and the
    threshold is on that confidence (``threshold_on: "confidence"``).
    ``verify`` records whether the tour's answers were verified (None: not recorded), ``min_support`` the support
    floor they were verified with (recorded with ``verified`` only: the confidence, and so the threshold, follow it).

    The record's keys (the ``calibration`` of a map file's header): ``threshold`` (null: none reached),
    ``threshold_on``, ``precision_asked``, ``precision``, ``recall``, ``query``, ``ground_truth``,
    ``tolerance``, ``n_queries``, ``n_with_right_place``, ``sequence`` (``length``, ``mode``),
    ``confidence_model``, ``recall_of``, ``date``, ``verify``, ``min_support``; :func:`mark_stale` adds ``stale``,
    ``stale_since`` and ``tours_added_since``.  Every reader goes through this module.
    """
    check_precision(precision)
    if S.shape != gt.shape:
        raise TopolocError(f"scores of shape {S.shape} do not match the ground truth {gt.shape}")
    has_pos = gt.hard.any(axis=0)
    if not has_pos.any():
        raise TopolocError("calibration needs a tour with ground truth: no query has a correct map place")
    cols = np.arange(S.shape[1])
    best = np.argmax(S, axis=0) if verified is None else np.asarray(verified.answer)
    right = gt.hard[best, cols]
    counted = right | ~gt.soft[best, cols]
    what = query or gt.description
    if verified is None:
        score = S[best, cols].astype(np.float64)
        model = ConfidenceModel.fit(score[counted], np.zeros(int(counted.sum()), bool), right[counted], on="score",
                                    source=f"calibration on {what}")
        threshold, rec, reached = _sweep(score, right, counted, int(has_pos.sum()), precision, what)
        on = "score"
    else:
        prior = confidence or DEFAULT_CONFIDENCE
        u = prior.inputs(strength=verified.strength)
        model = ConfidenceModel.fit(u[counted], verified.verified[counted], right[counted], on="strength",
                                    source=f"calibration on {what}", prior=prior)
        # Only verified answers can be accepted (:func:`accepts`): the threshold is chosen among them, recall
        # still over every query with a right place. On a tour whose answers are all right, the lowest
        # confidence of every answer would accept unverified ones, and with them frames of no mapped place
        # (bench_verification, part offmap: 82 of 111 corridor frames accepted by a gardens_point map so).
        ok = np.asarray(verified.verified, bool)
        threshold, rec, reached = _sweep(model(u, verified.verified)[ok], right[ok], counted[ok], int(has_pos.sum()),
                                         precision, what)
        on = "confidence"
    seq = sequence or SequenceSpec()
    return {
        "threshold": threshold, "threshold_on": on, "precision_asked": precision, "precision": reached, "recall": rec,
        "query": query, "ground_truth": ground_truth or gt.description,
        "tolerance": tolerance or gt.description, "n_queries": int(S.shape[1]),
        "n_with_right_place": int(has_pos.sum()),
        "sequence": {"length": seq.length, "mode": seq.mode},
        "confidence_model": model.to_dict(),
        "recall_of": "queries with a right place in the map (n_with_right_place)",
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        **({} if verify is None else {"verify": bool(verify)}),
        **({} if verified is None or min_support is None else {"min_support": int(min_support)}),
    }


def confidence_model(calibration: dict[str, Any] | None, *, on: str = "strength") -> ConfidenceModel | None:
    """The confidence model a calibration fitted for answers read ``on`` their strength or score (None: none)."""
    d = (calibration or {}).get("confidence_model")
    if not isinstance(d, dict) or str(d.get("on", "strength")) != on:
        return None
    return ConfidenceModel.from_dict(d)


def threshold_kind(calibration: dict[str, Any] | None) -> str:
    """What a calibration's threshold applies to: ``"confidence"``, ``"score"`` (the method's own score), or
    ``"stale"``: one chosen on verified scores before answers had a confidence (no longer comparable)."""
    cal = calibration or {}
    if "threshold_on" in cal:
        return str(cal["threshold_on"])
    return "stale" if calibrated_verify(cal) else "score"


def accepts(calibration: dict[str, Any] | None, *, score: float, confidence: float | None,
            is_verified: bool | None) -> bool:
    """Whether an answer is accepted: the one rule ``localize``, the ROS node and reports follow.

    Not calibrated: a verified answer where answers are verified, every
    answer where they are not.  Calibrated with verification: a verified
    answer whose confidence is at least the threshold (calibration can only
    raise the bar verification sets, never accept what it refused); without
    verification, the method's score at least the threshold; a null
    threshold accepts nothing.  A threshold chosen on
    verified scores before answers had a confidence no longer applies: the
    answer is accepted when verified (``localize`` says so before the first frame).
    """
    if calibration is None:
        return True if is_verified is None else bool(is_verified)
    kind = threshold_kind(calibration)
    if kind == "stale":
        return bool(is_verified)
    if kind == "confidence" and not is_verified:
        return False
    t = threshold_of(calibration)
    value = confidence if kind == "confidence" else score
    return value is not None and t is not None and value >= t


__all__ = [
    "accepts",
    "calibrated_sequence",
    "calibrated_verify",
    "check_precision",
    "choose_threshold",
    "confidence_model",
    "is_stale",
    "json_calibration",
    "mark_stale",
    "recorded_min_support",
    "threshold_kind",
    "threshold_of",
    "tours_added_since",
]
