"""Equal-frame-rate comparison (benchmarks/bench_landmarks_fps.py): selection, ground truth, sweep."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.bench.landmark_density import (
    RATE_KEYS,
    densest_within_budget,
    frame_rate_sweep,
    nearest_node_ground_truth,
    nodes_at_rate,
)
from topoloc.datasets.groundtruth import GroundTruth, ground_truth_from_places
from topoloc.errors import TopolocError


def _row(method: str, stride: int, nodes: int, elements: int, fps: float, label: str | None = None) -> dict[str, Any]:
    return {"label": label or method, "method": method, "stride": stride, "nodes": nodes, "map_elements": elements,
            "fps_total_cpu": fps, "ms_total_cpu": 1e3 / fps}


def test_densest_within_budget_takes_the_most_nodes_that_are_fast_enough() -> None:
    rows = [
        _row("voting", 1, 100, 90_000, 1.7), _row("voting", 2, 50, 45_000, 2.9), _row("voting", 3, 34, 30_000, 3.4),
        _row("voting", 5, 20, 18_000, 4.1),
        _row("landmarks", 1, 100, 7_000, 3.9, "lm"), _row("landmarks", 1, 100, 3_000, 4.5, "lm3"),
        _row("landmarks", 2, 50, 4_000, 4.6, "lm"),
        {"label": "lm", "method": "landmarks", "stride": 10, "nodes": 10, "error": "no feature track"},
    ]
    at3 = densest_within_budget(rows, fps=3.0)
    assert list(at3) == ["voting", "landmarks"]
    assert at3["voting"] is not None and at3["voting"]["stride"] == 3  # 2.9 frames/s at k = 2 misses the budget
    # Same nodes: the configuration with more landmarks per node is the denser map.
    assert at3["landmarks"] is not None and at3["landmarks"]["label"] == "lm"
    at45 = densest_within_budget(rows, fps=4.5)
    assert at45["landmarks"] is not None and at45["landmarks"]["label"] == "lm3"
    assert at45["voting"] is None  # nothing fast enough: None, not the fastest row
    assert densest_within_budget(rows, fps=1.0)["voting"]["stride"] == 1  # type: ignore[index]
    # A budget exactly met counts as met.
    assert densest_within_budget(rows, fps=4.1)["voting"]["stride"] == 5  # type: ignore[index]


def test_densest_within_budget_refuses_bad_input() -> None:
    with pytest.raises(ValueError, match="fps"):
        densest_within_budget([_row("voting", 1, 10, 10, 5.0)], fps=0.0)
    with pytest.raises(ValueError, match="fps_match_cpu"):
        densest_within_budget([_row("voting", 1, 10, 10, 5.0)], fps=3.0, rate="fps_match_cpu")
    assert densest_within_budget([], fps=3.0) == {}


def test_nodes_at_rate_extrapolates_a_straight_line() -> None:
    rows = [{"label": "v", "nodes": n, "ms_total_cpu": 100.0 + 2.0 * n} for n in (10, 20, 50, 100)]
    assert nodes_at_rate(rows, label="v", fps=3.0) == pytest.approx((1e3 / 3 - 100.0) / 2.0)
    assert nodes_at_rate(rows, label="v", fps=20.0) == 0.0  # even an empty map misses 50 ms
    flat = [{"label": "l", "nodes": n, "ms_total_cpu": 5.0} for n in (10, 100)]
    assert nodes_at_rate(flat, label="l", fps=3.0) is None
    assert nodes_at_rate(rows[:1], label="v", fps=3.0) is None


def test_nearest_node_ground_truth() -> None:
    gt = ground_truth_from_places(np.arange(10), np.arange(10), 0, 1)
    same = nearest_node_ground_truth(gt, np.arange(10))
    assert np.array_equal(same.hard, gt.hard) and np.array_equal(same.soft, gt.soft)
    sub = nearest_node_ground_truth(gt, np.array([0, 3, 6, 9]))
    assert sub.shape == (4, 10)
    # Query 1 is nearest node 0 (1 place away, node 3 is 2); query 2 node 3; every query has one right node.
    assert np.flatnonzero(sub.hard[:, 1]).tolist() == [0] and np.flatnonzero(sub.hard[:, 2]).tolist() == [1]
    assert (sub.hard.sum(axis=0) == 1).all()
    assert sub.soft[1, 1] and not sub.hard[1, 1]  # soft reaches one place further, through frame 2
    tie = nearest_node_ground_truth(gt, np.array([0, 2]))
    assert tie.hard[:, 1].tolist() == [True, True]  # frame 1 is as near node 0 as node 2
    assert tie.hard[:, 9].tolist() == [False, True]  # past the last node: the last node
    with pytest.raises(ValueError, match="ascending"):
        nearest_node_ground_truth(gt, np.array([3, 1]))
    with pytest.raises(ValueError, match="ascending"):
        nearest_node_ground_truth(gt, np.array([0, 10]))


def test_frame_rate_sweep_on_a_generated_route(tmp_path: Path) -> None:
    from topoloc.datasets.traverse import load_traverse
    from topoloc.features import FeatureConfig
    from topoloc.spec.setup import make_resources
    from topoloc.synth import RouteConfig, generate_route

    dirs = generate_route(tmp_path / "route", config=RouteConfig(n_places=8, seed=4),
                          tours=(("a", 10.0), ("b", 13.0)))
    m, q = load_traverse(dirs[0]), load_traverse(dirs[1])
    res, _ = make_resources(FeatureConfig(), cache_dir=tmp_path / "cache")
    gt = ground_truth_from_places(m.places, q.places, 0, 1)  # per map image: several images show one place
    configs = [("lm", "landmarks", {}), ("lm-long", "landmarks", {"min_track_length": 50}), ("v", "voting", {})]
    rows = frame_rate_sweep(m, q, gt, resources=res, strides=(1, 2), configs=configs, log_progress=False)
    assert [(r["label"], r["stride"]) for r in rows] == [(c[0], s) for s in (1, 2) for c in configs]
    built = [r for r in rows if "error" not in r]
    assert {r["label"] for r in rows if "error" in r} == {"lm-long"}  # no track of 50 frames on a 9-image map
    for r in built:
        assert r["nodes"] == len(range(0, len(m), r["stride"])) and r["map_elements"] > 0
        assert r["ms_match_cpu"] >= 0 and r["ms_extract_cpu"] > 0 and r["ms_total_cpu"] >= r["ms_extract_cpu"]
        assert all(r[k] > 0 for k in RATE_KEYS) and r["fps_total_cpu_2cores"] == 2 * r["fps_total_cpu"]
        assert 0.0 <= r["auc"] <= 1.0 and r["n_queries"] == len(q) and r["n_queries_with_match"] == len(q)
        assert r["fixed_tolerance"] == 1 and 0.0 <= r["correct_rate"] <= 1.0
    voting_dense = next(r for r in built if r["label"] == "v" and r["stride"] == 1)
    assert voting_dense["recall_at_1"] >= 0.5  # a clean generated route: voting finds most places
    assert voting_dense["correct_rate"] >= voting_dense["recall_at_1"] - 1e-9  # within 1 place vs exact
    with pytest.raises(TopolocError, match="ground truth has shape"):
        frame_rate_sweep(m, q, GroundTruth(np.ones((3, 3), bool), np.ones((3, 3), bool)), resources=res)
    with pytest.raises(TopolocError, match="strides"):
        frame_rate_sweep(m, q, gt, resources=res, strides=(0,))
    with pytest.raises(TopolocError, match="not seqslam"):
        frame_rate_sweep(m, q, gt, resources=res, configs=[("s", "seqslam", {})])
