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


def choose_threshold(S: np.ndarray, gt: GroundTruth, *, precision: float = 0.99, query: str = "",
                     ground_truth: str = "", tolerance: str = "",
                     sequence: SequenceSpec | None = None) -> dict[str, Any]:
    """The calibration record of a labelled tour's scores (:meth:`topoloc.maps.Map.calibrate` documents it)."""
    check_precision(precision)
    if S.shape != gt.shape:
        raise TopolocError(f"scores of shape {S.shape} do not match the ground truth {gt.shape}")
    has_pos = gt.hard.any(axis=0)
    if not has_pos.any():
        raise TopolocError("calibration needs a tour with ground truth: no query has a correct map place")
    best = np.argmax(S, axis=0)
    cols = np.arange(S.shape[1])
    score = S[best, cols].astype(np.float64)
    right = gt.hard[best, cols]
    counted = right | ~gt.soft[best, cols]
    s, tp, fp, last = threshold_sweep(score, right, counted)
    n_counted = tp + fp
    prec = np.where(n_counted > 0, tp / np.maximum(n_counted, 1), 1.0)
    ok = last & (prec >= precision) & (n_counted > 0)
    n_pos = int(has_pos.sum())
    threshold: float | None
    if ok.any():
        k = int(np.flatnonzero(ok)[-1])
        threshold, rec = float(s[k]), float(tp[k] / n_pos)
        reached = float(prec[k])
    else:
        # JSON has no infinity: null stands for "no threshold reached", which accepts nothing.
        threshold, rec, reached = None, 0.0, 1.0
        log.warning("calibration on %s: no score threshold reaches precision %g, so the map now accepts no "
                    "localisation; calibrate on a longer tour or ask for a lower --precision",
                    query or gt.description, precision)
    seq = sequence or SequenceSpec()
    return {
        "threshold": threshold, "precision_asked": precision, "precision": reached, "recall": rec,
        "query": query, "ground_truth": ground_truth or gt.description,
        "tolerance": tolerance or gt.description, "n_queries": int(S.shape[1]),
        "n_with_right_place": n_pos,
        "sequence": {"length": seq.length, "mode": seq.mode},
        "recall_of": "queries with a right place in the map (n_with_right_place)",
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
    }


__all__ = ["calibrated_sequence", "check_precision", "choose_threshold", "json_calibration", "mark_stale",
           "threshold_of"]
