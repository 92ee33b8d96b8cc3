"""A first run without --vocab/--vocab-train: the default vocabulary is trained on the map's own tours (#27)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from tests.cli.conftest import Cli

from topoloc.maps import Map
from topoloc.vocabulary.vocab import vocabulary_fingerprint


def test_evaluate_without_vocabulary_trains_on_the_map_tours_once(cli: Cli, rf: dict[str, Path],
                                                                   tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    runs = []
    for name in ("first", "again"):
        cli.ok(["evaluate", "--method", "bow", "--map", str(rf["map"]), "--query", str(rf["query"]),
                "--vocab-words", "200", "--cache-dir", str(cache), "--out", str(tmp_path / name), "--quiet"])
        metrics = json.loads((tmp_path / name / "metrics.json").read_text())
        runs.append({**metrics["run"], "recall_at_1": metrics["recall_at_1"]})
    voc = runs[0]["vocabulary"]
    assert voc["used"] and voc["source"] == "map tours" and voc["n_words"] == 200
    assert voc["folders_of_tours"] == [str(rf["map"])] and voc["n_images"] == len(list(rf["map"].glob("*.jpg")))
    # Cached by the tours' fingerprints: the second run loads the same file instead of training again.
    assert runs[1]["vocabulary"]["file"] == voc["file"] and Path(voc["file"]).is_file()
    assert runs[1]["vocabulary"]["objective"] == voc["objective"]
    assert runs[0]["recall_at_1"] > 0.5  # a vocabulary of the noon tour still finds the dusk frames
    assert "\"source\": \"map tours\"" in (tmp_path / "first" / "report.md").read_text()


@pytest.mark.parametrize("method", ["fabmap", "coocmap"])
def test_map_build_without_vocabulary_and_add_trains_it_on_all_tours(cli: Cli, rf: dict[str, Path], tmp_path: Path,
                                                       method: str) -> None:
    out = tmp_path / "m.tlm"
    cli.ok(["map", "build", "--method", method, "--map", str(rf["map"]), "--vocab-words", "200",
            "--cache-dir", str(tmp_path / "cache"), "--out", str(out), "--quiet"])
    built = Map.load(out)
    assert built.vocabulary is not None and built.vocabulary.provenance_["source"] == "map tours"
    before = vocabulary_fingerprint(built.vocabulary)
    assert built.info()["vocabulary"]["trained_on"] == [f"map tours: {rf['map'].name}"]
    # map add builds again from both tours: the words are those a build of both tours trains.
    cli.ok(["map", "add", str(out), str(rf["morning"]), "--cache-dir", str(tmp_path / "cache"), "--quiet"])
    after = Map.load(out)
    assert vocabulary_fingerprint(after.vocabulary) != before and len(after.tours) == 2
    both = tmp_path / "both.tlm"
    cli.ok(["map", "build", "--method", method, "--map", str(rf["map"]), "--map", str(rf["morning"]),
            "--vocab-words", "200", "--cache-dir", str(tmp_path / "cache"), "--out", str(both), "--quiet"])
    assert vocabulary_fingerprint(Map.load(both).vocabulary) == vocabulary_fingerprint(after.vocabulary)
    r = cli.ok(["localize", str(out), str(rf["query"]), "--out", str(tmp_path / "r.jsonl"), "--quiet"])
    assert r and len((tmp_path / "r.jsonl").read_text().splitlines()) == len(list(rf["query"].glob("*.jpg")))


def test_slam_without_vocabulary(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    cli.ok(["slam", str(rf["map"]), "--vocab-words", "200", "--cache-dir", str(tmp_path / "cache"),
            "--out", str(tmp_path / "s"), "--quiet"])
    assert (tmp_path / "s" / "posterior.npy").is_file()
