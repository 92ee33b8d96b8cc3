"""A calibration records its tolerance in words; adding a tour marks it stale, calibrating again clears it (#27)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.maps import Map
from topoloc.spec import GroundTruthSpec


def _map(route: dict[str, Any]) -> Map:
    return Map.build(method="bow", tours=[route["map"]], vocabulary=route["vocabulary"], vocab_train=(),
                     cache_dir=route["map"].root.parent / "cache")


def test_localize_many_reaches_the_reported_precision_and_recall(tiny_route: dict[str, Any]) -> None:
    m = _map(tiny_route)
    cal = m.calibrate_on(tiny_route["query"], ground_truth=GroundTruthSpec.for_calibration("1"), precision=0.8)
    assert cal["tolerance"] == "within 1 place"
    lines = m.localize_many(tiny_route["query_frames"])
    q = tiny_route["query"].places
    accepted = np.array([r["accepted"] for r in lines])
    right = np.abs(np.array([r["place"] for r in lines]) - q) <= 1
    has_right = (np.abs(m.place_ids[:, None] - q[None, :]) <= 1).any(axis=0)  # recall's denominator
    assert accepted.any() and int(has_right.sum()) == cal["n_with_right_place"]
    assert (accepted & right).sum() / accepted.sum() == pytest.approx(cal["precision"])
    assert (accepted & right).sum() / has_right.sum() == pytest.approx(cal["recall"])


def test_add_tour_marks_the_calibration_stale_and_it_survives_saving(tiny_route: dict[str, Any],
                                                                      tmp_path: Path) -> None:
    m = _map(tiny_route)
    cal = dict(m.calibrate_on(tiny_route["query"], precision=0.8))
    assert cal["tolerance"] == "within 8 places" and not m.calibration_stale
    m.add_tour(tiny_route["training"])
    assert m.calibration is not None and m.calibration_stale
    assert m.calibration["stale_since"] == "morning" and m.calibration["tours_added_since"] == ["morning"]
    assert {k: v for k, v in m.calibration.items() if k not in ("stale", "stale_since", "tours_added_since")} == cal
    back = Map.load(m.save(tmp_path / "m.tlm"))
    assert back.calibration == m.calibration and back.threshold == m.threshold and back.calibration_stale
    assert back.info()["calibration"]["stale"] is True
    back.calibrate_on(tiny_route["query"], precision=0.8)
    assert not back.calibration_stale and "stale_since" not in (back.calibration or {})


def test_a_map_calibrated_before_loads_unchanged(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    m = _map(tiny_route)
    old = {"threshold": 0.1, "precision_asked": 0.9, "precision": 0.95, "recall": 0.5, "query": "dusk",
           "ground_truth": "place ids, tolerance 0:8", "n_queries": 12, "date": "2024-01-01T00:00:00+00:00"}
    m.calibration = dict(old)
    back = Map.load(m.save(tmp_path / "old.tlm"))
    assert back.calibration == old and back.threshold == 0.1 and not back.calibration_stale
    un = _map(tiny_route)
    un.add_tour(tiny_route["training"])  # nothing to mark on an uncalibrated map
    assert un.calibration is None and not un.calibration_stale
