"""Retrieval pairs in hloc's format (``--pairs-out``): names, writing and reading back."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.evaluation.pairs import (
    first_images,
    format_pairs,
    image_names,
    place_names,
    read_pairs,
    retrieval_pairs,
    write_pairs,
)
from topoloc.io.dirs import pairs_marker


def test_names_are_relative_to_one_root_holding_both_traverses(tiny_route: dict[str, Any]) -> None:
    query, map_ = tiny_route["query"], tiny_route["map"]
    root = query.root.parent
    assert map_.root.parent == root
    names = image_names(query)
    assert len(names) == len(query) and all(n.startswith(f"{query.root.name}/") for n in names)
    assert all((root / n).is_file() for n in names)
    firsts = first_images(map_)
    assert sorted(firsts) == sorted(set(map_.places.tolist()))
    for p, name in firsts.items():  # the first image of each place, in traverse order
        assert root / name == map_.images[int(np.flatnonzero(map_.places == p)[0])]


def test_in_memory_images_keep_their_names() -> None:
    t = Traverse.from_images([np.zeros((4, 4), np.uint8)] * 3, name="cam")
    assert image_names(t) == ["cam/0", "cam/1", "cam/2"]


def test_place_names_first_tour_wins_and_unknown_places_are_named_by_id() -> None:
    got = place_names(np.array([1, 2, 3]), [{1: "a/1.png"}, {1: "b/1.png", 2: "b/2.png"}])
    assert got == ["a/1.png", "b/2.png", "place-3"]


def test_round_trip(tmp_path: Path) -> None:
    rows = np.array([[2, 0, 1], [1, 2, 0]])
    pairs = retrieval_pairs(["q/0.png", "q/1.png"], rows, ["m/a.png", "m/b.png", "m/c.png"])
    assert pairs[:3] == [("q/0.png", "m/c.png"), ("q/0.png", "m/a.png"), ("q/0.png", "m/b.png")]
    path = tmp_path / "pairs.txt"
    write_pairs(path, pairs)
    assert path.read_text().splitlines()[0] == "q/0.png m/c.png"  # hloc: one pair a line, a space between
    assert read_pairs(path) == pairs
    assert pairs_marker()(path)
    write_pairs(path, [])
    assert read_pairs(path) == [] and pairs_marker()(path)


def test_refused_names_and_lines(tmp_path: Path) -> None:
    with pytest.raises(TopolocError, match="white space"):
        format_pairs([("q/a b.png", "m/0.png")])
    with pytest.raises(ValueError, match="shape"):
        retrieval_pairs(["q"], np.zeros((2, 1), int), ["m"])
    bad = tmp_path / "bad.txt"
    bad.write_text("one two three\n")
    with pytest.raises(TopolocError, match=r"bad\.txt:1"):
        read_pairs(bad)
    assert not pairs_marker()(bad)
