"""benchmarks.bench_verification's evidence part: what it measures of a pair's supporting matches, and its table."""

from __future__ import annotations

import numpy as np
from benchmarks import bench_verification as bv

SHAPES = np.array([480, 640, 480, 640])


def _two_views(X: np.ndarray) -> np.ndarray:
    """Supporting matches (query x, y, map x, y) of 3-D points seen from two poses."""
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    a = 0.05
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    x1 = (K @ X.T).T
    x2 = (K @ (R @ X.T + np.array([[0.8], [0.05], [0.2]]))).T
    return np.c_[x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:]].astype(np.float32)


def test_a_plane_is_all_one_homography_and_depth_is_not() -> None:
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-4, 4, 60), rng.uniform(-3, 3, 60), np.full(60, 8.0)]
    deep = np.c_[rng.uniform(-4, 4, 60), rng.uniform(-3, 3, 60), rng.uniform(4, 40, 60)]
    flat, solid = bv.pair_evidence(_two_views(plane), SHAPES), bv.pair_evidence(_two_views(deep), SHAPES)
    assert flat["homography"] == 1.0 and solid["homography"] < 0.8
    assert flat["cells"] > 0.5 and solid["cells"] > 0.3


def test_matches_in_one_corner_cover_one_cell() -> None:
    pairs = np.tile(np.array([[10.0, 12.0, 11.0, 13.0]], np.float32), (30, 1))
    pairs[:, :2] += np.random.default_rng(1).uniform(0, 20, (30, 2)).astype(np.float32)
    assert bv.pair_evidence(pairs, SHAPES)["cells"] == round(1 / bv.GRID ** 2, 4)
    assert bv.pair_evidence(pairs[:3], SHAPES)["homography"] == 1.0  # too few to fit: nothing to refuse


def test_the_table_says_what_each_evidence_adds_per_set() -> None:
    items = [{"set": "gp_day", "kind": "answer", "right": True, "support": 20, "confirmed": 1.0, "cells": 0.5,
              "homography": 0.3},
             {"set": "gp_day", "kind": "hard", "right": False, "support": 18, "confirmed": 1.0, "cells": 0.2,
              "homography": 0.6}]
    rules = bv.evidence_rules(items)
    assert {k: (v["bar"], v["gained"]["gp_day"]) for k, v in rules.items()} == {
        "cells": (0.2, 1), "homography": (0.6, 1), "confirmed": (1.0, 0)}  # a wrong one confirmed: none past it
    items_more = [*items, {**items[0], "cells": 0.2, "homography": 0.6, "confirmed": 0.0}]
    assert bv.evidence_rules(items_more)["cells"]["gained"]["gp_day"] == 1  # at the bar is not past it
    page = bv.render({"date": "d", "machine": "m", "evidence": {"floor": 12, "items": items, "rules": rules}})
    assert "1 right answers, and 0 wrong answers, 1 hard negatives and 0 frames" in page
    assert "| 0.20 / 0.20 / 0.20 | 0.50 / 0.50 / 0.50 | > 0.2 | 1 of 1 |" in page
    assert "| < 0.6 | 1 of 1 |" in page and "| > 1 | 0 of 1 |" in page
