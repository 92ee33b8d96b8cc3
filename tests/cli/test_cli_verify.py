"""``--verify/--no-verify`` on the commands that score: what they write, the default, and maps that cannot verify."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from tests.cli.conftest import Cli
from typer.testing import CliRunner

from topoloc.cli.main import app
from topoloc.cli.options import DEFAULT_MIN_SUPPORT
from topoloc.verification import MIN_SUPPORT


def _evaluate(cli: Cli, rf: dict[str, Path], out: Path, *extra: str) -> dict:
    cli.ok(["evaluate", "--method", "bow", "--map", str(rf["map"]), "--query", str(rf["query"]), "--vocab",
            str(rf["vocab"]), "--cache-dir", str(rf["cache"]), "--out", str(out), "-q", *extra])
    return json.loads((out / "metrics.json").read_text())


def test_the_command_lines_floor_is_the_libraries() -> None:
    assert DEFAULT_MIN_SUPPORT == MIN_SUPPORT


def test_the_floor_is_the_same_at_any_feature_cap(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    # The support chance reaches does not follow --max-features (verification.md, part caps): a floor in proportion
    # to the cap would be 8 here at 200 features and 200 at 2000.
    for cap in (200, 2000):
        m = _evaluate(cli, rf, tmp_path / f"cap{cap}", "--verify", "--max-features", str(cap), "--min-support", "100")
        assert m["verification"]["min_support"] == 100, cap


def test_evaluate_verify_writes_the_stage_and_ranks_verified_answers_first(cli: Cli, rf: dict[str, Path],
                                                                           tmp_path: Path) -> None:
    m = _evaluate(cli, rf, tmp_path / "v", "--verify")
    assert m["params"]["verify"] is True
    assert m["run"]["spec"]["verification"] == {"enabled": True, "candidates": None, "confirm": False,
                                                "min_support": None}
    v = m["verification"]
    assert v["candidates"] == 3 and 0.5 <= v["verified_fraction"] <= 1 and v["ms_per_query"] > 0
    assert v["min_support"] == MIN_SUPPORT and v["confusion"] is True and v["confidence_model"]["on"] == "strength"
    assert v["look_alikes"] is True  # learned from the tours with the confusion (Confusion.install)
    z = np.load(tmp_path / "v" / "verification.npz")
    S = np.load(tmp_path / "v" / "S.npy")
    assert z["verified"].shape == (S.shape[1],) and z["candidates"].shape == (S.shape[1], 3)
    assert np.array_equal(z["answer"], S.argmax(axis=0)) and ((z["confidence"] > 0) & (z["confidence"] < 1)).all()
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
    dense = _evaluate(cli, rf, tmp_path / "d")
    assert dense["params"]["verify"] is True
    # --top-k verifies its K places as the dense run does (each block of whole columns verified): the same answers.
    m = _evaluate(cli, rf, tmp_path / "k", "--top-k", "3")
    assert m["params"]["verify"] is True and m["verification"]["verified_fraction"] == \
        dense["verification"]["verified_fraction"]
    top = np.load(tmp_path / "k" / "S_topk.npz")
    S = np.load(tmp_path / "d" / "S.npy")
    assert np.array_equal(top["rows"][:, 0], S.argmax(axis=0))
    np.testing.assert_allclose(top["scores"][:, 0], S.max(axis=0), rtol=0, atol=1e-6)
    assert m["recall_at_1"] == pytest.approx(dense["recall_at_1"], abs=1e-9)
    np.testing.assert_array_equal(np.load(tmp_path / "k" / "verification.npz")["verified"],
                                  np.load(tmp_path / "d" / "verification.npz")["verified"])


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


def _map(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> tuple[Path, Path]:
    """A map of a copy of the route's map tour (which the tests then change), and that copy."""
    tour = tmp_path / "tour"
    shutil.copytree(rf["map"], tour)
    tlm = tmp_path / "m.tlm"
    cli.ok(["map", "build", "--method", "bow", "--map", str(tour), "--vocab", str(rf["vocab"]), "--cache-dir",
            str(rf["cache"]), "--out", str(tlm), "-q"])
    return tlm, tour


def _localize(rf: dict[str, Path], tlm: Path, out: Path, *extra: str) -> tuple[int, str, list[dict]]:
    r = CliRunner().invoke(app, ["localize", str(tlm), str(rf["query"]), "--out", str(out), "-q", *extra])
    lines = [json.loads(x) for x in out.read_text().splitlines()] if out.is_file() else []
    return r.exit_code, r.stderr, lines


@pytest.mark.parametrize("change", ["moved", "deleted image", "replaced images", "all replaced"])
def test_map_images_that_changed_are_not_used_to_verify_and_it_is_said(change: str, cli: Cli, rf: dict[str, Path],
                                                                       tmp_path: Path, caplog: pytest.LogCaptureFixture,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TOPOLOC_VERIFY")
    tlm, tour = _map(cli, rf, tmp_path)
    rows = [line.split(",")[:2] for line in (tour / "places.csv").read_text().splitlines()[1:]]
    images = [tour / name for name, _ in rows]
    place_of = {name: int(place) for name, place in rows}
    before = _localize(rf, tlm, tmp_path / "before.jsonl")[2]
    assert sum(x["verified"] for x in before) >= len(before) // 2
    if change == "moved":
        tour.rename(tmp_path / "elsewhere")
    elif change == "deleted image":
        images[0].unlink()
    else:
        # Other images of the same names and sizes: the content tells them apart, not the name or the size.
        victims = images[:3] if change == "replaced images" else images
        for k, p in enumerate(victims):
            p.write_bytes(images[(k + 7) % len(images)].read_bytes())
    caplog.clear()
    code, err, lines = _localize(rf, tlm, tmp_path / "after.jsonl")
    assert code == 0 and len(lines) == len(before), err  # it localises
    said = [r.getMessage() for r in caplog.records if "--no-verify" in r.getMessage()]
    err = "\n".join(r.getMessage() for r in caplog.records)
    assert len(said) == 1, err  # one line, naming the way out
    if change in ("moved", "all replaced"):
        assert not any(x.get("verified") for x in lines) and "cannot verify" in said[0]
    else:
        assert "not used to verify" in said[0] and sum(x["verified"] for x in lines) >= 1
        # No answer is verified at a place all of whose images changed: none is left to verify with.
        changed = {p.name for p in images[:3 if change == "replaced images" else 1]}
        kept = {place_of[n] for n in place_of if n not in changed}
        assert not any(x["verified"] and x["place"] not in kept for x in lines)
    # --verify where nothing can be verified is the one-line error; --no-verify is silent.
    if change in ("moved", "all replaced"):
        cli.error(["localize", str(tlm), str(rf["query"]), "--out", str(tmp_path / "x.jsonl"), "--verify"],
                  "cannot verify answers")
    caplog.clear()
    code, err, _ = _localize(rf, tlm, tmp_path / "quiet.jsonl", "--no-verify")
    assert code == 0 and not any("--no-verify" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("value,verifies", [("1", True), ("0", False), ("auto", True), ("on", True)])
def test_topoloc_verify_comes_before_the_maps_record_and_after_the_option(value: str, verifies: bool, cli: Cli,
                                                                          rf: dict[str, Path], tmp_path: Path,
                                                                          caplog: pytest.LogCaptureFixture,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TOPOLOC_VERIFY")
    tlm, _ = _map(cli, rf, tmp_path)
    cli.ok(["map", "calibrate", str(tlm), "--query", str(rf["morning"]), "--no-verify", "--sequence", "0", "-q"])
    monkeypatch.setenv("TOPOLOC_VERIFY", value)
    caplog.clear()
    code, err, lines = _localize(rf, tlm, tmp_path / "l.jsonl")
    assert code == 0 and ("verified" in lines[0]) is (verifies and value != "auto"), err
    if verifies and value != "auto":  # against the calibration's record: said, once
        assert sum("calibrated without verification" in r.getMessage() for r in caplog.records) == 1
    code, _, lines = _localize(rf, tlm, tmp_path / "o.jsonl", "--no-verify")
    assert code == 0 and "verified" not in lines[0]  # the option first


def test_the_floor_is_the_runs_else_the_calibrations_else_the_builds_and_another_is_said(
        cli: Cli, rf: dict[str, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    from topoloc.maps import Map

    monkeypatch.delenv("TOPOLOC_VERIFY")
    tlm, tour = _map(cli, rf, tmp_path)
    assert Map.load(tlm).verifier_for(None).rule.min_support == MIN_SUPPORT  # nothing recorded: the default
    built = tmp_path / "b.tlm"
    cli.ok(["map", "build", "--method", "bow", "--map", str(tour), "--vocab", str(rf["vocab"]), "--cache-dir",
            str(rf["cache"]), "--out", str(built), "--min-support", "40", "-q"])
    assert Map.load(built).verifier_for(None).rule.min_support == 40  # the build's
    cal = json.loads(cli.ok(["map", "calibrate", str(built), "--query", str(rf["morning"]), "--verify", "--sequence",
                             "0", "-q"]))
    assert cal["verify"] is True and cal["min_support"] == 40  # calibrated at the build's floor, recorded
    m = Map.load(built)
    m.spec = None  # the calibration's record alone
    assert m.verifier_for(None).rule.min_support == 40
    from topoloc.spec import VerificationSpec

    assert m.verifier_for(None, spec=VerificationSpec(min_support=30)).rule.min_support == 30  # the run's first
    said = "calibrated on answers verified with --min-support"
    caplog.clear()
    code, err, _ = _localize(rf, built, tmp_path / "same.jsonl")
    assert code == 0 and not any(said in r.getMessage() for r in caplog.records), err
    caplog.clear()
    code, err, lines = _localize(rf, built, tmp_path / "other.jsonl", "--min-support", str(MIN_SUPPORT))
    assert code == 0 and lines, err
    assert sum(said in r.getMessage() for r in caplog.records) == 1
    caplog.clear()  # unverified, the floor plays no part
    code, err, _ = _localize(rf, built, tmp_path / "plain.jsonl", "--no-verify", "--min-support", str(MIN_SUPPORT))
    assert code == 0 and not any(said in r.getMessage() for r in caplog.records), err


def test_a_calibration_that_predates_the_recorded_floor_is_said_where_its_floor_was_another(
        cli: Cli, rf: dict[str, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Before calibrations recorded their floor it followed the feature cap (13 at 500 features): such a map's
    threshold was chosen at that floor, which this run no longer verifies with."""
    import dataclasses

    from topoloc.maps import Map
    from topoloc.maps.acceptance import floor_before_it_was_recorded, warn_before_localizing

    monkeypatch.delenv("TOPOLOC_VERIFY")
    tlm, _ = _map(cli, rf, tmp_path)
    cli.ok(["map", "calibrate", str(tlm), "--query", str(rf["morning"]), "--verify", "--sequence", "0", "-q"])
    said = "before maps recorded their support floor"

    def warned(max_features: int, *, record: bool = False, min_support: int | None = None,
               edit: dict | None = None) -> list[str]:
        m = Map.load(tlm)
        m.features = dataclasses.replace(m.features, max_features=max_features)
        if not record:
            m.calibration = {k: v for k, v in (m.calibration or {}).items() if k != "min_support"}
        m.calibration = {**(m.calibration or {}), **(edit or {})}
        caplog.clear()
        warn_before_localizing(m, tlm, m.calibrated_sequence, None, min_support)
        return [r.getMessage() for r in caplog.records if said in r.getMessage()]

    assert floor_before_it_was_recorded(500) == 13 and floor_before_it_was_recorded(1000) == MIN_SUPPORT
    got = warned(500)
    assert len(got) == 1 and f"(13 at 500 features), and this run verifies with {MIN_SUPPORT}" in got[0]
    assert warned(1000) == [] and warned(500, min_support=13) == []  # the same floor as then
    assert warned(500, record=True) == []  # a recorded floor is the one the calibration used
    # A floor recorded but unusable is not a calibration from before the record (the localiser says what it is).
    assert warned(500, edit={"min_support": "25"}) == [] and warned(500, edit={"min_support": 2.5}) == []


@pytest.mark.parametrize("command", ["localize", "evaluate", "calibrate", "slam"])
def test_a_bad_topoloc_verify_is_refused_by_every_command(command: str, cli: Cli, rf: dict[str, Path],
                                                          tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    tlm, _ = _map(cli, rf, tmp_path)
    monkeypatch.setenv("TOPOLOC_VERIFY", "maybe")
    args = {"localize": ["localize", str(tlm), str(rf["query"]), "--out", str(tmp_path / "l.jsonl")],
            "evaluate": ["evaluate", "--method", "bow", "--map", str(rf["map"]), "--query", str(rf["query"]),
                         "--vocab", str(rf["vocab"]), "--out", str(tmp_path / "e")],
            "calibrate": ["map", "calibrate", str(tlm), "--query", str(rf["morning"])],
            "slam": ["slam", str(rf["map"]), "--out", str(tmp_path / "s"), "--vocab", str(rf["vocab"])]}[command]
    cli.error(args, "TOPOLOC_VERIFY")
    cli.error([*args, "--verify"], "TOPOLOC_VERIFY")  # refused even where an option decides


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
    # No reranking among peaks: each query's answer is the sequence's best place, or a route neighbour within
    # the climb to the peak of its support (decision step 3).
    base = _evaluate(cli, rf, tmp_path / "b", "--no-verify", "--sequence", "2")
    moved = np.abs(np.load(tmp_path / "b" / "S.npy").argmax(axis=0) - S.argmax(axis=0))
    assert (moved <= 3).all()
    assert z["candidates"].shape == (S.shape[1], 1) and base["params"]["verify"] is False


def test_evaluate_map_file_scores_as_localize_uses_the_map(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TOPOLOC_VERIFY")
    tlm, _ = _map(cli, rf, tmp_path)
    cli.ok(["map", "calibrate", str(tlm), "--query", str(rf["morning"]), "--sequence", "2", "--no-verify", "-q"])
    base = ["evaluate", "--map-file", str(tlm), "--query", str(rf["query"]), "--cache-dir", str(rf["cache"]), "-q"]
    cli.ok([*base, "--out", str(tmp_path / "a")])
    m = json.loads((tmp_path / "a" / "metrics.json").read_text())
    # The map's calibrated sequence and its recorded --no-verify, as localize would match.
    assert m["params"]["sequence"] == 2 and m["params"]["verify"] is False
    cli.ok([*base, "--out", str(tmp_path / "b"), "--sequence", "0", "--verify"])  # options override the map
    m = json.loads((tmp_path / "b" / "metrics.json").read_text())
    assert m["params"]["sequence"] == 0 and m["params"]["verify"] is True
    config = tmp_path / "run.toml"
    config.write_text(f'map_file = "{tlm}"\nquery = "{rf["query"]}"\nout = "{tmp_path / "c"}"\n'
                      "[sequence]\nlength = 1\n")
    cli.ok(["evaluate", "--config", str(config), "-q"])  # a configuration file's sequence counts as given
    assert json.loads((tmp_path / "c" / "metrics.json").read_text())["params"]["sequence"] == 1
