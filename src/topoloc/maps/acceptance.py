"""Warnings before localising with a map whose acceptance threshold will not hold as calibrated.

Shared by ``topoloc localize`` and the ROS node (:mod:`topoloc.ros.node`), which sit side by side
on the top layer: here, below both, neither imports the other (issue #41).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING

from topoloc.errors import TopolocError
from topoloc.maps.verify_policy import with_map_floor
from topoloc.spec import VerificationSpec
from topoloc.verification import MIN_SUPPORT
from topoloc.verification.pairs import MIN_SAMPLE

if TYPE_CHECKING:
    from topoloc.maps.map import Map
    from topoloc.spec import SequenceSpec

log = logging.getLogger(__name__)


def warn_before_localizing(m: Map, map_file: str | Path | None, sequence: SequenceSpec,
                           verify: bool | None = None, min_support: int | None = None) -> None:
    """The warnings of a map whose acceptance will not hold: not calibrated, stale, another sequence, verification
    or support floor.

    For loop closure an accepted false match breaks the map: ``localize`` and
    the ROS node say so before the first frame.  ``verify`` is the run's option
    (None: not given; the map's record and ``$TOPOLOC_VERIFY`` decide), ``min_support``
    the floor it verifies with (None: not known).
    """
    from topoloc.maps.calibration import calibrated_verify, recorded_min_support, threshold_kind, tours_added_since

    choice = m.verify_choice(verify)
    verifies = choice.enabled is not False and not m.verification_blocker()
    if m.threshold is None:
        if verifies:
            log.warning("%s is not calibrated: a frame is accepted when its answer is verified; run `topoloc map "
                        "calibrate %s --query FOLDER` on a tour with ground truth to set a threshold on the "
                        "confidence", map_file, map_file)
        else:
            log.warning("%s is not calibrated and answers are not verified: every frame is marked accepted; run "
                        "`topoloc map calibrate %s --query FOLDER` on a tour with ground truth to set the acceptance "
                        "threshold", map_file, map_file)
        return
    if m.calibration_stale:
        log.warning("%s: the calibration predates tours added since (%s), which change the scores; run "
                    "`topoloc map calibrate %s --query FOLDER` again", map_file,
                    ", ".join(tours_added_since(m.calibration)), map_file)
    if threshold_kind(m.calibration) == "stale":
        log.warning("%s: the threshold was calibrated on verified scores before answers had a confidence, and no "
                    "longer applies: a frame is accepted when its answer is verified; run `topoloc map calibrate` "
                    "again", map_file)
    if sequence != m.calibrated_sequence:
        cal = m.calibrated_sequence
        log.warning("%s: the threshold was calibrated on %s, not on %s as this run matches: its precision does not "
                    "hold; run `topoloc map calibrate` with the same --sequence", map_file,
                    _sequence_words(cal.length, cal.mode), _sequence_words(sequence.length, sequence.mode))
    recorded = calibrated_verify(m.calibration)
    if recorded is not None and choice.enabled is not None and choice.enabled != recorded:
        log.warning("%s: the threshold was calibrated %s verification, and this run matches %s (%s): its precision "
                    "does not hold; run `topoloc map calibrate` with the same --verify/--no-verify", map_file,
                    "with" if recorded else "without", "with" if choice.enabled else "without", choice.source)
    floor = recorded_min_support(m.calibration)
    if verifies and floor is not None and min_support is not None and min_support != floor:
        # The confidence, and so the threshold on it, follows the floor (docs/protocol.md, Verification, step 6).
        log.warning("%s: the threshold was calibrated on answers verified with --min-support %d, and this run "
                    "verifies with %d: its precision does not hold; run `topoloc map calibrate` again or localise "
                    "with --min-support %d", map_file, floor, min_support, floor)
    elif verifies and recorded and "min_support" not in (m.calibration or {}):
        # Calibrated with verification before calibrations recorded their floor, when it followed the feature cap.
        # (A floor recorded but unusable is the localiser's one line to say: verify_policy.with_map_floor.)
        cap = int(m.features.max_features)
        then = floor_before_it_was_recorded(cap)
        try:
            now = with_map_floor(VerificationSpec(min_support=min_support), calibration=None, built=m.spec,
                                 where=str(map_file)).rule().min_support
        except TopolocError:
            return
        if then != now:
            log.warning("%s: the threshold was calibrated before maps recorded their support floor, on answers "
                        "verified with the floor of that time (%d at %d features), and this run verifies with %d: its "
                        "precision does not hold; run `topoloc map calibrate` again", map_file, then, cap, now)


#: Features per image at which the floor was :data:`topoloc.verification.MIN_SUPPORT` when it followed the cap
#: (before commit 10409dd; verification.md, part ``caps``, measured why it no longer does).
_FLOOR_FEATURES_BEFORE = 1000


def floor_before_it_was_recorded(max_features: int) -> int:
    """The support floor a calibration verified its answers with before calibrations recorded it: the default
    floor in proportion to the feature cap, as verification then chose it."""
    return max(MIN_SAMPLE + 1, math.ceil(MIN_SUPPORT * max_features / _FLOOR_FEATURES_BEFORE))


def _sequence_words(length: int, mode: str) -> str:
    return f"sequences of {length + 1} frames ({mode})" if length else "single images"


__all__ = ["floor_before_it_was_recorded", "warn_before_localizing"]
