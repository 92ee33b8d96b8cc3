"""``evaluate --top-k K``: the sparse S of the K best places per query, and metrics computed from it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.datasets.groundtruth import GroundTruth, ground_truth_from_places, ground_truth_from_xy
from topoloc.evaluation.metrics import compute_metrics
from topoloc.evaluation.topk import TopK, compute_metrics_top_k, score_top_k, top_k_of
from topoloc.methods import get_method
from topoloc.progress import no_progress


def _metrics(scores: Any) -> dict[str, float]:
    return {k: round(v, 12) for k, v in scores.as_dict().items()}


def _boosted(n_places: int, n_queries: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random S (no ties) whose correct row (query j shows place j mod n_places) is near the top."""
    rng = np.random.default_rng(seed)
    S = rng.random((n_places, n_queries))
    truth = np.arange(n_queries) % n_places
    S[truth, np.arange(n_queries)] += 0.6 + rng.random(n_queries) * 0.6  # sometimes best, sometimes a few rows down
    return S.astype(np.float32), truth


def test_top_k_of_keeps_the_best_rows_best_first() -> None:
    S = np.array([[0.1, 5.0], [0.9, 1.0], [0.5, 3.0], [0.7, 3.0]], np.float32)
    rows, scores = top_k_of(S, 3)
    np.testing.assert_array_equal(rows, [[1, 3, 2], [0, 2, 3]])
    np.testing.assert_array_equal(scores, np.float32([[0.9, 0.7, 0.5], [5.0, 3.0, 3.0]]))
    rows, _ = top_k_of(S, 10)  # K above the places: every place, sorted
    assert rows.shape == (2, 4)


@pytest.mark.parametrize("tolerance", [(0, 0), (0, 2), (1, 3)])
def test_metrics_from_the_top_k_equal_the_dense_ones_when_the_correct_place_is_kept(tolerance: tuple) -> None:
    S, truth = _boosted(60, 200, seed=1)
    gt = ground_truth_from_places(np.arange(60), truth, *tolerance)
    k = 35
    top = TopK(*top_k_of(S, k), n_places=60)
    kept = (top.rows == truth[:, None]).any(axis=1)
    assert kept.all()  # the premise: every correct place is within the top K
    dense = compute_metrics(S, gt, (1, 5, 10, 20))
    sparse_ = compute_metrics_top_k(top, gt, (1, 5, 10, 20))
    assert _metrics(sparse_) == _metrics(dense)
    np.testing.assert_allclose(sparse_.precision, dense.precision)
    np.testing.assert_allclose(sparse_.recall, dense.recall)


def test_sparse_ground_truth_in_metres_gives_the_same_metrics() -> None:
    S, truth = _boosted(40, 120, seed=2)
    map_xy = np.c_[np.arange(40) * 10.0, np.zeros(40)]
    q_xy = map_xy[truth] + np.c_[np.random.default_rng(0).normal(0, 2, 120), np.zeros(120)]
    gt = ground_truth_from_xy(map_xy, q_xy, 6, 15)
    assert gt.is_sparse
    top = TopK(*top_k_of(S, 40), n_places=40)  # all places kept: identical to dense
    assert _metrics(compute_metrics_top_k(top, gt)) == _metrics(compute_metrics(S, GroundTruth(gt.hard, gt.soft)))


def test_a_correct_place_outside_the_top_k_counts_as_not_found() -> None:
    S = np.array([[0.9, 0.1], [0.5, 0.2], [0.1, 0.8], [0.3, 0.7]], np.float32)
    hard = np.zeros((4, 2), bool)
    hard[3, 0] = True  # query 0's correct place is third
    hard[0, 1] = True  # query 1's correct place is last
    gt = GroundTruth(hard, hard)
    top = TopK(*top_k_of(S, 2), n_places=4)
    m = compute_metrics_top_k(top, gt, (1, 2, 3, 4))
    dense = compute_metrics(S, gt, (1, 2, 3, 4))
    assert m.recall_at_k[3] == 0.0 and dense.recall_at_k[3] == 0.5  # beyond K: not found
    assert m.recall_at_k[4] == 0.0 and dense.recall_at_k[4] == 1.0
    assert m.recall_at_1 == dense.recall_at_1 == 0.0
    assert m.auc == dense.auc  # no best match is right either way


def test_soft_only_cells_are_dropped_and_all_soft_kept_rows_count_as_wrong() -> None:
    S = np.array([[0.9, 0.9], [0.8, 0.8], [0.1, 0.7]], np.float32)
    hard = np.array([[0, 0], [1, 0], [0, 1]], bool)
    soft = np.array([[1, 1], [1, 1], [0, 1]], bool)
    gt = GroundTruth(hard, soft)
    full = compute_metrics_top_k(TopK(*top_k_of(S, 3), n_places=3), gt)
    assert _metrics(full) == _metrics(compute_metrics(S, gt))
    assert full.recall_at_1 == 1.0
    # K = 1 keeps only the soft-only row 0: the best match is unknown, so not found.
    one = compute_metrics_top_k(TopK(*top_k_of(S, 1), n_places=3), gt)
    assert one.recall_at_1 == 0.0 and one.auc == 0.0


def test_blocks_of_queries_give_the_top_k_of_the_whole_s(tiny_route: dict[str, Any]) -> None:
    rec = get_method("descriptors")().fit(tiny_route["map"])
    items = rec.encode(tiny_route["query"])
    S = rec.score(items)

    class Plain:  # the same scores without the method's own top_k: scored in blocks
        name = "plain"
        place_ids_ = rec.place_ids_
        scores_whole_sequence = False

        def score(self, its: list) -> np.ndarray:
            return rec.score(its)

    top, ms = score_top_k(Plain(), items, 4, no_progress, block=3)  # type: ignore[arg-type]
    rows, scores = top_k_of(S, 4)
    np.testing.assert_array_equal(top.rows, rows)
    np.testing.assert_array_equal(top.scores, scores)
    assert ms.shape == (len(items),)


def test_s_topk_file_round_trips(tmp_path: Path) -> None:
    S, _ = _boosted(10, 7, seed=3)
    top = TopK(*top_k_of(S, 3), n_places=10)
    top.save(tmp_path / "S_topk.npz")
    back = TopK.load(tmp_path / "S_topk.npz")
    np.testing.assert_array_equal(back.rows, top.rows)
    np.testing.assert_array_equal(back.scores, top.scores)
    dense = back.to_sparse().toarray()
    assert dense.shape == (10, 7)
    np.testing.assert_array_equal(dense[top.rows[0], 0], top.scores[0])


def test_evaluate_top_k_of_an_image_method_and_bad_options(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from topoloc.cli.main import app
    from topoloc.errors import TopolocError
    from topoloc.evaluation.pipeline import evaluate

    common = {"method": "seqslam-single", "maps": [tiny_route["map"].root], "query": tiny_route["query"].root,
              "tolerance": "0:1", "cache_dir": tmp_path / "cache"}
    dense = evaluate(out=tmp_path / "dense", **common)
    every = evaluate(out=tmp_path / "every", top_k=1000, **common)  # K above the places: all kept
    for key in ("auc", "recall_at_100_precision", "recall_at_1", "recall_at_5", "recall_at_10"):
        assert every[key] == pytest.approx(dense[key], abs=1e-12), key
    # With K = 1 a soft-only best row leaves no kept row: not found (the dense S looks further down).
    one = evaluate(out=tmp_path / "one", top_k=1, **common)
    assert one["recall_at_1"] < dense["recall_at_1"]
    exact = {**common, "tolerance": "0:0"}
    one = evaluate(out=tmp_path / "one", top_k=1, **exact)
    assert one["recall_at_1"] == pytest.approx(evaluate(out=tmp_path / "d0", **exact)["recall_at_1"], abs=1e-12)
    assert one["recall_at_5"] == one["recall_at_1"]  # a correct place outside the top 1 is not found
    assert TopK.load(tmp_path / "one" / "S_topk.npz").rows.shape == (len(tiny_route["query"]), 1)
    # The other commands read a top-K run folder like any other.
    r = CliRunner().invoke(app, ["report", str(tmp_path / "one"), str(tmp_path / "dense"), "--out",
                                 str(tmp_path / "cmp")])
    assert r.exit_code == 0, r.output
    with pytest.raises(TopolocError, match="top_k must be a whole number >= 0"):
        evaluate(out=tmp_path / "bad", top_k=-1, **common)
    with pytest.raises(TopolocError, match="html draws the whole S"):
        evaluate(out=tmp_path / "bad", top_k=5, html=tmp_path / "x.html", **common)
