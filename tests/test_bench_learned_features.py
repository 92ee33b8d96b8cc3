"""The learned-features page (benchmarks/bench_learned_features.py): brute force, a page written from the numbers."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType

import numpy as np
import pytest


@pytest.fixture(scope="module")
def bench(benchmark_module: Callable[[str], ModuleType]) -> ModuleType:
    return benchmark_module("bench_learned_features")


def _v(auc: float, r100p: float, r1: float) -> dict[str, float]:
    return {"auc": auc, "recall_at_100_precision": r100p, "recall_at_1": r1}


def test_vectorised_brute_force_counts_the_mutual_nearest_neighbours(bench: ModuleType) -> None:
    rng = np.random.default_rng(0)
    tour = [rng.standard_normal((n, 8)).astype(np.float32) for n in (50, 0, 40, 7)]
    queries = [rng.standard_normal((n, 8)).astype(np.float32) for n in (30, 45, 10)]
    queries.append(tour[0][:20] + 0.01)  # a query that shares 20 features with map image 0
    S = bench.brute_S([tour], [np.array([0, 1, 2, 3])], queries, np.array([0, 1, 2, 3]))
    expected = np.array([[bench.mnn_count(a, b) for b in queries] for a in tour])
    np.testing.assert_array_equal(S, expected)
    assert S[0, 3] >= 20 and S[1].sum() == 0
    # Two tours: a place scores its best image.
    S2 = bench.brute_S([tour[:2], tour[2:]], [np.array([0, 1]), np.array([0, 1])], queries, np.array([0, 1]))
    np.testing.assert_array_equal(S2, np.maximum(expected[:2], expected[2:]))


def test_the_page_reports_the_targets_and_the_worse_cells(bench: ModuleType) -> None:
    quality = []
    for f, day, night in (("sift", _v(0.80, 0.3, 0.83), _v(0.23, 0.04, 0.38)),
                          ("xfeat", _v(0.98, 0.9, 0.98), _v(0.94, 0.76, 0.95))):
        for row, v in (("gp_day", day), ("gp_night_2tours", night)):
            for method in ("coocmap", "bow"):
                quality.append({"row": row, "method": method, "features": f, "single": v, "sequence": v,
                                "ms_per_query": 1.0, "ms_features": 30.0})
    quality[-1] = {**quality[-1], "sequence": _v(0.10, 0.0, 0.2)}  # xfeat bow night, sequence: worse than SIFT
    page = bench.render({"date": "today", "machine": "m", "quality": quality})
    assert "| gardens_point day_left -> day_right | `coocmap` | 0.800 / 0.30 / 0.83 | **0.980 / 0.90 / 0.98** |" in page
    assert "XFeat is worse than SIFT by more than 0.02 AUC in 1: `bow` on gardens_point day_left + day_right" in page
    assert "two day tours, single images, XFeat R@1: 0.950 (>= 0.75: met)" in page
    assert "bag of words by day, XFeat R@1: 0.980 (>= 0.95: met)" in page


def test_runtimes_are_compared_at_the_same_positions(bench: ModuleType) -> None:
    from topoloc.features import FeatureSet

    rng = np.random.default_rng(1)
    kp = np.zeros((4, 5), np.float32)
    kp[:, :2] = [[1, 2], [3, 4], [5, 6], [7, 8]]
    d = rng.standard_normal((4, 64)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a = FeatureSet(kp, d, (10, 10))
    other = kp.copy()
    other[3, :2] = [9, 9]  # one keypoint moved: 3 of 4 at the same position
    b = FeatureSet(other[[2, 0, 1, 3]], d[[2, 0, 1, 3]], (10, 10))  # another order
    c = bench.compare_features(a, b)
    assert c["same"] == 3 and c["n_a"] == c["n_b"] == 4
    np.testing.assert_allclose(c["cos"], 1.0, rtol=1e-6)
    page = bench.render({"date": "today", "machine": "m", "runtimes": {
        "images": 2, "folders": [{"folder": "x", "images": 2, "keypoints_onnx": 8, "keypoints_torch": 8,
                                  "same_positions": 0.75, "cos_min": 0.9999, "share_cos_ok": 1.0}],
        "keypoints_onnx": 8, "keypoints_torch": 8, "same_positions": 0.75, "cos_min": 0.9999, "cos_p001": 0.9999,
        "share_cos_ok": 1.0, "worst_image": {"share": 0.75, "image": "x/1.jpg", "n_a": 4, "n_b": 4},
        "onnxruntime": "1", "torch": "2"}})
    assert "PyTorch's positions, every development image (share): 0.750 (>= 0.99: NOT met)" in page
    assert "smallest descriptor cosine at the same positions: 1.000 (>= 0.999: met)" in page
