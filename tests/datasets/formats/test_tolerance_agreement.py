"""On a converted dataset, ``--tolerance-m`` scores as the place-id tolerance where the two agree.

A synthetic street (12 of its places, noon and dusk) is described by a Pittsburgh-style
``dbStruct``: database image ``k`` at 10 k m, query ``k`` within a metre of it.  After
``topoloc convert dbstruct``, query ``k`` shows place ``k``, and map places ``i`` at
distance ``|i - k|`` places are ``10 |i - k| +- 1`` m away, so ``--tolerance 1:3`` and
``--tolerance-m 15:35`` mark the same cells and must give the same metrics.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.io import savemat
from typer.testing import CliRunner

from topoloc.cli.main import app
from topoloc.datasets.traverse import load_traverse
from topoloc.spec import GroundTruthSpec

runner = CliRunner()
N = 12


@pytest.fixture(scope="module")
def converted(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from topoloc.synth import RouteConfig, generate_route

    root = tmp_path_factory.mktemp("street")
    noon, dusk = generate_route(root / "route", config=RouteConfig(n_places=2 * N, width=160, height=120, seed=5),
                                tours=[("noon", 12.0), ("dusk", 18.0)])
    db, q = _one_image_per_place(noon, dusk)
    assert len(db) == N and len(q) == N
    rng = np.random.default_rng(1)
    utm_db = np.column_stack([400000 + 10.0 * np.arange(N), np.full(N, 5000000.0)])
    utm_q = utm_db + rng.uniform(-0.7, 0.7, size=(N, 2))
    mat = root / "street.mat"
    savemat(str(mat), {"dbStruct": {
        "whichSet": "test", "dbImage": np.array([str(p.relative_to(root)) for p in db], dtype=object),
        "utmDb": utm_db.T, "qImage": np.array([str(p.relative_to(root)) for p in q], dtype=object),
        "utmQ": utm_q.T, "numImages": N, "numQueries": N, "posDistThr": 25}})
    r = runner.invoke(app, ["convert", "dbstruct", str(mat), "--out", str(root / "conv")])
    assert r.exit_code == 0, r.output
    return root / "conv"


def _one_image_per_place(*folders: Path) -> list[list[Path]]:
    """The first image of each of the first N places that every tour shows."""
    ts = [load_traverse(f) for f in folders]
    common = sorted(set.intersection(*(set(t.places.tolist()) for t in ts)))[:N]
    return [[t.images[int(np.flatnonzero(t.places == p)[0])] for p in common] for t in ts]


def _evaluate(conv: Path, out: Path, *tolerance: str) -> dict:  # type: ignore[type-arg]
    r = runner.invoke(app, ["evaluate", "--method", "seqslam-single", "--map", str(conv / "map"),
                            "--query", str(conv / "query"), "--out", str(out), "--quiet", *tolerance])
    assert r.exit_code == 0, r.output + str(r.exception)
    return json.loads((out / "metrics.json").read_text())


def test_ground_truth_agrees(converted: Path) -> None:
    maps, query = [load_traverse(converted / "map")], load_traverse(converted / "query")
    assert query.places.tolist() == list(range(N))
    ids = np.unique(maps[0].places)
    by_id = GroundTruthSpec(tolerance="1:3").make(ids, query, maps=maps)
    by_m = GroundTruthSpec(tolerance_m="15:35").make(ids, query, maps=maps)
    assert by_m.is_sparse
    assert np.array_equal(by_id.hard, by_m.hard) and np.array_equal(by_id.soft, by_m.soft)


def test_metrics_agree(converted: Path, tmp_path: Path) -> None:
    a = _evaluate(converted, tmp_path / "ids", "--tolerance", "1:3", "--recall-at", "1,2,5,10,20")
    b = _evaluate(converted, tmp_path / "metres", "--tolerance-m", "15:35", "--recall-at", "1,2,5,10,20")
    assert "m" in b["run"]["ground_truth"] and "m" not in a["run"]["ground_truth"].split("tolerance")[-1]
    for key in ["auc", "recall_at_100_precision", "recall_at_1", "recall_at_2", "recall_at_5", "recall_at_10",
                "recall_at_20"]:
        assert a[key] == pytest.approx(b[key]), key
    assert a["recall_at_1"] > 0   # the street is recognised at all
    assert a["recall_at_20"] == 1.0   # 20 >= the 12 places


def test_bad_recall_at(converted: Path, tmp_path: Path) -> None:
    r = runner.invoke(app, ["evaluate", "--method", "seqslam-single", "--map", str(converted / "map"),
                            "--query", str(converted / "query"), "--out", str(tmp_path / "o"), "--recall-at", "x"])
    assert r.exit_code == 2 and "--recall-at 'x'" in r.stderr and "\n" not in r.stderr.strip()
