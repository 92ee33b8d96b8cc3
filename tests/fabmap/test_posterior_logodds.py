"""``location_log_odds``: the logit of ``location_posterior``, exact where the probability rounds to 1."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import expit, logsumexp

from topoloc.fabmap.posterior import location_log_odds, location_posterior


@pytest.mark.parametrize("smoothing", [1.0, 0.9])
def test_logodds_match_the_posterior_per_model(smoothing: float) -> None:
    ll = np.array([-10.0, -11.5, -9.0, -14.0])
    p = location_posterior(ll, None, -12.0, p_new=0.3, smoothing=smoothing)[:-1]
    z = location_log_odds(ll, None, -12.0, p_new=0.3, smoothing=smoothing)
    np.testing.assert_allclose(expit(z), p, rtol=1e-12)


def test_logodds_of_grouped_models_are_those_of_the_summed_posterior() -> None:
    ll = np.array([-10.0, -11.0, -9.5, -13.0, -12.0])
    starts = np.array([0, 2, 3])  # places {0, 1}, {2}, {3, 4}
    p = location_posterior(ll, None, -11.0, p_new=0.5)[:-1]
    z = location_log_odds(ll, None, -11.0, p_new=0.5, starts=starts)
    np.testing.assert_allclose(expit(z), np.add.reduceat(p, starts), rtol=1e-12)


def test_logodds_keep_apart_what_the_posterior_rounds_to_one() -> None:
    # Leads of 100 and 200 nats: both posteriors are exactly 1.0, the log-odds are the leads.
    for lead in (100.0, 200.0):
        ll = np.array([0.0, -lead, -lead - 5])
        assert location_posterior(ll, None, -lead, p_new=0.5)[0] == 1.0
        z = location_log_odds(ll, None, -lead, p_new=0.5)
        others = logsumexp([-lead + np.log(0.5 / 3), -lead - 5 + np.log(0.5 / 3), -lead + np.log(0.5)])
        np.testing.assert_allclose(z[0], np.log(0.5 / 3) - others, rtol=1e-12)
    assert location_log_odds(np.array([0.0, -200.0]), None, -200.0, p_new=0.5)[0] > \
        location_log_odds(np.array([0.0, -100.0]), None, -100.0, p_new=0.5)[0]
