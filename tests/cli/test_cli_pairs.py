"""``evaluate --top-k K --pairs-out`` and ``localize --pairs-out``: hloc's pairs files, read back."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from topoloc.evaluation.pairs import read_pairs

if TYPE_CHECKING:
    from conftest import Cli


def _evaluate(rf: dict[str, Path], out: Path, *extra: str) -> list[str]:
    return ["evaluate", "--method", "bow", "--map", str(rf["map"]), "--query", str(rf["query"]), "--vocab",
            str(rf["vocab"]), "--cache-dir", str(rf["cache"]), "--out", str(out), "--quiet", *extra]


def _check(pairs: list[tuple[str, str]], rf: dict[str, Path], k: int) -> dict[str, list[str]]:
    """Every name is a file under the one root of both traverses; each query has K distinct map images."""
    root = rf["query"].parent
    assert rf["map"].parent == root
    per: dict[str, list[str]] = {}
    for q, m in pairs:
        assert q.startswith(rf["query"].name + "/") and m.startswith(rf["map"].name + "/")
        assert (root / q).is_file() and (root / m).is_file()
        per.setdefault(q, []).append(m)
    groups = [pairs[i:i + k] for i in range(0, len(pairs), k)]  # one frame's K places, best first
    assert all(len({q for q, _ in g}) == 1 and len({m for _, m in g}) == k for g in groups)
    return per


def test_evaluate_top_k_pairs_out(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    pairs_file = tmp_path / "pairs" / "pairs-retrieval.txt"
    printed = cli.ok(_evaluate(rf, tmp_path / "run", "--top-k", "3", "--pairs-out", str(pairs_file)))
    assert str(pairs_file) in printed
    pairs = read_pairs(pairs_file)
    n_queries = len(list(rf["query"].glob("*.jpg")))
    per = _check(pairs, rf, 3)
    assert len(per) == n_queries == len(pairs) // 3
    # The pairs are the rows of S_topk.npz, best first, each place as its first map image.
    with np.load(tmp_path / "run" / "S_topk.npz") as z:
        rows = z["rows"]
    places = np.load(tmp_path / "run" / "places.npy")
    queries = sorted(per, key=lambda q: sorted(p.name for p in rf["query"].glob("*.jpg")).index(Path(q).name))
    firsts: dict[int, str] = {}
    for line in (rf["map"] / "places.csv").read_text().splitlines()[1:]:
        name, place = line.split(",")[:2]
        firsts.setdefault(int(place), f"{rf['map'].name}/{name}")
    assert [per[q] for q in queries] == [[firsts[int(places[r])] for r in rs] for rs in rows]
    # Again over the earlier pairs file: replaced; a saved map gives the same pairs.
    tlm = tmp_path / "route.tlm"
    cli.ok(["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]), "--out",
            str(tlm), "--cache-dir", str(rf["cache"]), "--quiet"])
    cli.ok(["evaluate", "--map-file", str(tlm), "--query", str(rf["query"]), "--cache-dir", str(rf["cache"]),
            "--out", str(tmp_path / "run2"), "--top-k", "3", "--pairs-out", str(pairs_file), "--quiet"])
    assert read_pairs(pairs_file) == pairs


def test_pairs_out_refusals(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    cli.error(_evaluate(rf, tmp_path / "a", "--pairs-out", str(tmp_path / "p.txt")), "give --top-k")
    image = sorted(rf["query"].glob("*.jpg"))[0]
    cli.error(_evaluate(rf, tmp_path / "b", "--top-k", "2", "--pairs-out", str(image)), "pairs file")
    notes = tmp_path / "notes.txt"
    notes.write_text("my own notes, not pairs\n")
    cli.error(_evaluate(rf, tmp_path / "c", "--top-k", "2", "--pairs-out", str(notes)), "pairs file exists")
    assert notes.read_text() == "my own notes, not pairs\n"
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists() and not (tmp_path / "c").exists()


def test_localize_pairs_out(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    tlm = tmp_path / "route.tlm"
    cli.ok(["map", "build", "--method", "bow", "--map", str(rf["map"]), "--vocab", str(rf["vocab"]), "--out",
            str(tlm), "--cache-dir", str(rf["cache"]), "--quiet"])
    first = sorted(rf["query"].glob("*.jpg"))[0]
    out, pairs_file = tmp_path / "r.jsonl", tmp_path / "pairs.txt"
    summary = json.loads(cli.ok(["localize", str(tlm), str(rf["query"]), str(first), "--out", str(out),
                                 "--top-k", "2", "--pairs-out", str(pairs_file), "--quiet"]))
    assert summary["pairs"] == str(pairs_file)
    pairs = read_pairs(pairs_file)
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    assert len(pairs) == 2 * len(lines)
    per = _check(pairs, rf, 2)
    # The folder's frames and the single file again: each frame's two places, in the order of its line.
    assert Counter(q for q, _ in pairs)[f"{rf['query'].name}/{first.name}"] == 4
    assert [q for q, _ in pairs[::2]] == [f"{rf['query'].name}/{r['image']}" for r in lines]
    info = json.loads(cli.ok(["map", "info", str(tlm), "--json"]))
    assert "place_images" not in info["tours"][0]
    firsts = {}
    for line in (rf["map"] / "places.csv").read_text().splitlines()[1:]:
        name, place = line.split(",")[:2]
        firsts.setdefault(int(place), f"{rf['map'].name}/{name}")
    assert [m for _, m in pairs] == [firsts[p] for r in lines for p, _ in r["top"]]
    assert len(per) == len(lines) - 1
    # A map saved before tours recorded their images still loads; its places are written by id.
    from topoloc.maps import Map

    old = Map.load(tlm)
    for tour in old.tours:
        del tour["place_images"]
    assert old.place_image_names() == [f"place-{p}" for p in old.place_ids.tolist()]
