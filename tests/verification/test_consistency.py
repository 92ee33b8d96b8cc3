"""Temporal consistency: an answer the previous frame does not confirm ranks below every confirmed one."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.verification import confirmed, demote_unconfirmed


def _stream(best: list[int], n: int = 40) -> np.ndarray:
    """Scores of a few frames: a peak at each frame's best place over noise (a peak ends where the noise rises)."""
    x = np.arange(n)[:, None]
    noise = np.random.default_rng(0).uniform(0.0, 0.05, (n, len(best)))
    return (np.exp(-0.5 * ((x - np.array(best)[None, :]) / 1.5) ** 2) + noise).astype(np.float32)


def test_a_jump_is_not_confirmed_and_drops_below_every_confirmed_answer() -> None:
    S = _stream([5, 6, 7, 30, 31, 9])
    ok = confirmed(S)
    assert ok.tolist() == [False, True, True, False, True, False]
    out = demote_unconfirmed(S, ok)
    assert out[:, ~ok].max() < out[:, ok].min()
    assert np.array_equal(out.argmax(axis=0), S.argmax(axis=0))  # the order within a column is kept
    # Online: the frame before the first given.
    assert confirmed(S[:, :1], previous_best=4).tolist() == [True]
    assert confirmed(S[:, 3:4], previous_best=7).tolist() == [False]
    with pytest.raises(ValueError):
        demote_unconfirmed(S, ok[:2])
