"""The map-density experiment (paper Fig. 5-6) on a tiny generated route."""

from __future__ import annotations

from pathlib import Path

from topoloc.bench.landmark_density import density_experiment
from topoloc.synth import RouteConfig, generate_route


def test_density_rows(tmp_path: Path) -> None:
    generate_route(tmp_path / "route", config=RouteConfig(n_places=10, seed=4),
                   tours=(("tour_1000", 10.0), ("tour_1300", 13.0)))
    rows = density_experiment(tmp_path / "route", strides=(1, 2), methods=("landmarks",), max_queries=6)
    assert [r["stride"] for r in rows] == [1, 2]
    dense, sparse = rows
    assert dense["nodes"] > sparse["nodes"] > 0
    # x,y in places.csv give the density in nodes per metre; halving the nodes halves it.
    assert abs(dense["nodes_per_m"] / sparse["nodes_per_m"] - dense["nodes"] / sparse["nodes"]) < 1e-9
    for r in rows:
        assert r["fps"] > 0 and 0.0 <= r["correct_rate"] <= 1.0 and r["n_queries"] == 6
