"""R@N for any list of N (``--recall-at 1,5,10,20``)."""

from __future__ import annotations

import numpy as np
import pytest

from topoloc.datasets.groundtruth import ground_truth_from_places
from topoloc.errors import TopolocError
from topoloc.evaluation.metrics import compute_metrics
from topoloc.spec import parse_recall_at


def test_parse() -> None:
    assert parse_recall_at("1,5,10,20") == (1, 5, 10, 20)
    assert parse_recall_at("20, 1,1") == (1, 20)
    assert parse_recall_at([3, 2]) == (2, 3)
    for bad in ["a", "0", "", "1,-2", "1.5"]:
        with pytest.raises(TopolocError, match="recall_at"):
            parse_recall_at(bad)


def test_any_n_matches_a_naive_count() -> None:
    rng = np.random.default_rng(0)
    n_places, n_queries = 40, 30
    truth = rng.integers(0, n_places, n_queries)
    gt = ground_truth_from_places(np.arange(n_places), truth, 0, 0)
    S = rng.standard_normal((n_places, n_queries))
    m = compute_metrics(S, gt, (1, 3, 20, 40))
    d = m.as_dict()
    assert set(m.recall_at_k) == {1, 3, 20, 40}
    for k in (1, 3, 20, 40):
        rank = np.array([(S[:, q] > S[truth[q], q]).sum() for q in range(n_queries)])   # no ties here
        assert d[f"recall_at_{k}"] == pytest.approx(np.mean(rank < k))
    assert d["recall_at_40"] == 1.0 and d["recall_at_1"] == m.recall_at_1
    # The default output is unchanged: R@1, R@5, R@10 only.
    assert sorted(k for k in compute_metrics(S, gt).as_dict() if k.startswith("recall_at_")) == [
        "recall_at_1", "recall_at_10", "recall_at_100_precision", "recall_at_5"]
