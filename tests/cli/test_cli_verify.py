"""``--verify/--no-verify`` on the commands that score: what they write, the default, and maps that cannot verify."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from tests.cli.conftest import Cli


def _evaluate(cli: Cli, rf: dict[str, Path], out: Path, *extra: str) -> dict:
    cli.ok(["evaluate", "--method", "bow", "--map", str(rf["map"]), "--query", str(rf["query"]), "--vocab",
            str(rf["vocab"]), "--cache-dir", str(rf["cache"]), "--out", str(out), "-q", *extra])
    return json.loads((out / "metrics.json").read_text())


def test_evaluate_verify_writes_the_stage_and_ranks_verified_answers_first(cli: Cli, rf: dict[str, Path],
                                                                           tmp_path: Path) -> None:
    m = _evaluate(cli, rf, tmp_path / "v", "--verify")
    assert m["params"]["verify"] is True and m["run"]["spec"]["verification"] == {"enabled": True, "candidates": None}
    v = m["verification"]
    assert v["candidates"] == 3 and 0.5 <= v["verified_fraction"] <= 1 and v["ms_per_query"] > 0
    z = np.load(tmp_path / "v" / "verification.npz")
    S = np.load(tmp_path / "v" / "S.npy")
    assert z["verified"].shape == (S.shape[1],) and z["candidates"].shape == (S.shape[1], 3)
    best = S.max(axis=0)
    assert (best[z["verified"]] > 1).all() and (best[~z["verified"]] < 1).all()
    report = (tmp_path / "v" / "report.md").read_text()
    assert "# bow (verified):" in report and "of the answers verified" in report
    # --no-verify: the method's own scores, no stage file.
    m0 = _evaluate(cli, rf, tmp_path / "n", "--no-verify")
    assert m0["params"]["verify"] is False and "verification" not in m0
    assert not (tmp_path / "n" / "verification.npz").exists()
    # The run is made again from its record, verification included.
    again = tmp_path / "again"
    cli.ok(["evaluate", "--config", str(tmp_path / "v" / "metrics.json"), "--out", str(again), "-q"])
    np.testing.assert_array_equal(np.load(again / "S.npy"), S)


def test_verification_is_the_default_where_it_can_run(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TOPOLOC_VERIFY")
    assert _evaluate(cli, rf, tmp_path / "d")["params"]["verify"] is True
    # top_k keeps no whole column: not verified unless asked.
    m = _evaluate(cli, rf, tmp_path / "k", "--top-k", "3")
    assert m["params"]["verify"] is False
    assert _evaluate(cli, rf, tmp_path / "k2", "--top-k", "3", "--verify")["params"]["verify"] is True


def test_a_map_whose_tour_is_gone_refuses_verify_in_one_line(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    tour = tmp_path / "tour"
    shutil.copytree(rf["map"], tour)
    tlm = tmp_path / "m.tlm"
    cli.ok(["map", "build", "--method", "bow", "--map", str(tour), "--vocab", str(rf["vocab"]), "--cache-dir",
            str(rf["cache"]), "--out", str(tlm), "-q"])
    info = cli.ok(["map", "info", str(tlm)])
    assert '"can_verify": true' in info
    shutil.rmtree(tour)
    assert '"can_verify": false' in cli.ok(["map", "info", str(tlm)])
    cli.error(["localize", str(tlm), str(rf["query"]), "--out", str(tmp_path / "l.jsonl"), "--verify"],
              "cannot verify answers: tour 'tour' is gone")
    assert not (tmp_path / "l.jsonl").exists()
    cli.error(["evaluate", "--map-file", str(tlm), "--query", str(rf["query"]), "--out", str(tmp_path / "e"),
               "--verify", "--cache-dir", str(rf["cache"])], "is gone")
    cli.error(["map", "calibrate", str(tlm), "--query", str(rf["query"]), "--verify"], "is gone")
    # --no-verify (and the default, here TOPOLOC_VERIFY=0) still localise.
    cli.ok(["localize", str(tlm), str(rf["query"]), "--out", str(tmp_path / "l.jsonl"), "--no-verify", "-q"])
    assert "verified" not in (tmp_path / "l.jsonl").read_text()


def test_localize_says_per_frame_whether_it_verified(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    tlm = tmp_path / "m.tlm"
    cli.ok(["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]), "--cache-dir",
            str(rf["cache"]), "--out", str(tlm), "-q"])
    summary = json.loads(cli.ok(["localize", str(tlm), str(rf["query"]), "--out", str(tmp_path / "l.jsonl"),
                                 "--verify", "-q"]).strip().splitlines()[-1])
    lines = [json.loads(x) for x in (tmp_path / "l.jsonl").read_text().splitlines()]
    assert all(isinstance(r["verified"], bool) and isinstance(r["inliers"], int) for r in lines)
    assert summary["verified"] == sum(r["verified"] for r in lines) and summary["ms_verify_mean"] > 0


def test_slam_records_whether_it_verified_loop_closures(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TOPOLOC_VERIFY")
    for flag, want in (([], True), (["--no-verify"], False)):
        out = tmp_path / f"slam{len(flag)}"
        said = cli.ok(["slam", str(rf["map"]), "--out", str(out), "--vocab", str(rf["vocab"]), "--cache-dir",
                       str(rf["cache"]), "--min-gap", "2", "-q", *flag])
        params = json.loads((out / "slam.json").read_text())["params"]
        assert params["verify"] is want and ("rejected_by_verification" in params) is want
        assert ("rejected by verification" in said) is want


def test_a_sequence_verifies_its_best_place_only(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    m = _evaluate(cli, rf, tmp_path / "s", "--verify", "--sequence", "2")
    assert m["verification"]["candidates"] == 1
    z = np.load(tmp_path / "s" / "verification.npz")
    S = np.load(tmp_path / "s" / "S.npy")
    # No reranking: each query's best place is the sequence's, verified or not.
    base = _evaluate(cli, rf, tmp_path / "b", "--no-verify", "--sequence", "2")
    assert np.array_equal(np.load(tmp_path / "b" / "S.npy").argmax(axis=0), S.argmax(axis=0))
    assert z["candidates"].shape == (S.shape[1], 1) and base["params"]["verify"] is False
