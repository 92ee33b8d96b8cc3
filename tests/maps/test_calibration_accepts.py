"""A map calibrated with verification accepts only verified answers: calibration raises the bar, never lowers it."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.datasets.groundtruth import GroundTruth
from topoloc.maps.calibration import accepts, choose_threshold
from topoloc.verification.verifier import VerifiedBlock


def _block(answer: np.ndarray, verified: np.ndarray, strength: np.ndarray, n_places: int) -> VerifiedBlock:
    n = len(answer)
    z = np.zeros(n)
    return VerifiedBlock(S=np.zeros((n_places, n), np.float32), answer=answer, verified=verified,
                         support=(strength * 25).astype(np.int64), strength=strength, confidence=z,
                         candidates=answer[:, None], candidate_support=(strength * 25)[:, None], ms=z,
                         matches=[np.zeros((0, 4), np.float32)] * n, match_images=[None] * n,
                         match_shapes=np.zeros((n, 4), np.int64))


@pytest.mark.parametrize("seed", range(5))
def test_a_tour_whose_answers_are_all_right_does_not_make_unverified_answers_accepted(seed: int) -> None:
    """Calibrated on a day tour where every answer was right, a map accepted 82 of 111 frames of a corridor it
    does not hold: the lowest confidence of every answer, unverified ones included, was the threshold."""
    rng = np.random.default_rng(seed)
    n = 60
    answer = np.arange(n)
    verified = rng.random(n) < 0.7
    verified[:2] = True, False
    strength = np.where(verified, 1 + 3 * rng.random(n), 0.2 + 0.7 * rng.random(n))
    eye = np.eye(n, dtype=bool)
    cal = choose_threshold(np.zeros((n, n), np.float32), GroundTruth(eye, eye), precision=0.99,
                           verified=_block(answer, verified, strength, n), verify=True)
    assert cal["threshold_on"] == "confidence" and cal["threshold"] is not None
    # Every verified answer of the tour is accepted (all were right), and recall counts only those.
    assert cal["recall"] == pytest.approx(verified.mean())
    from topoloc.maps.calibration import confidence_model

    model = confidence_model(cal)
    assert model is not None
    conf = model(model.inputs(strength=strength), verified)
    got = [accepts(cal, score=0.0, confidence=float(c), is_verified=bool(v)) for c, v in zip(conf, verified,
                                                                                             strict=True)]
    assert got == verified.tolist()
    # An unverified answer is refused however confident the model is of it.
    assert not accepts(cal, score=1.0, confidence=1.0, is_verified=False)
    assert not accepts(cal, score=1.0, confidence=1.0, is_verified=None)


def test_a_map_calibrated_without_verification_still_accepts_by_score() -> None:
    cal = {"threshold": 0.5, "threshold_on": "score", "verify": False}
    assert accepts(cal, score=0.6, confidence=None, is_verified=None)
    assert not accepts(cal, score=0.4, confidence=None, is_verified=None)
