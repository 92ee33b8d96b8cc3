"""Saved state and later tours: every method round-trips through a container, and A then B equals A+B."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.io.container import read_container, write_container
from topoloc.methods import available_methods, get_method
from topoloc.resources import InMemoryResources

FAST: dict[str, dict[str, Any]] = {"fabmap": {"n_samples": 20}, "fabmap2": {"n_samples": 20, "output": "posterior"},
                                   "seqslam": {"ds": 3}, "coocmap": {"top_k": 3}}


def _res(route: dict[str, Any]) -> InMemoryResources:
    return InMemoryResources(vocabulary=route["vocabulary"], training=route["training"])


def _first_part(t: Traverse, n: int) -> Traverse:
    keep = t.places < n
    return Traverse(root=t.root, images=tuple(p for p, k in zip(t.images, keep, strict=True) if k),
                    places=t.places[keep], times=None if t.times is None else t.times[keep], name=t.name + "_part")


@pytest.mark.parametrize("name", available_methods())
def test_state_round_trips_through_a_memory_mapped_container(name: str, tiny_route: dict[str, Any],
                                                             tmp_path: Path) -> None:
    cls = get_method(name)
    res = _res(tiny_route)
    rec = cls(**FAST.get(name, {})).fit(tiny_route["map"], resources=res)
    S = rec.similarity(tiny_route["query"])
    meta, arrays = rec.get_state()
    write_container(tmp_path / "m.bin", "test-state", 1, arrays, meta)
    meta2, arrays2 = read_container(tmp_path / "m.bin", "test-state", 1, mmap=True)
    back = cls.from_state(rec.get_params(), meta2, arrays2, resources=res)
    np.testing.assert_array_equal(back.place_ids_, rec.place_ids_)
    np.testing.assert_array_equal(back.similarity(tiny_route["query"]), S)


# A landmark map adds a tour by online learning (Sec. V), which is what fitting does with
# tours="first"; with its default tours="separate" fitting makes the tour's images nodes instead.
ADD_TOUR_PARAMS: dict[str, dict[str, Any]] = {**FAST, "landmarks": {"tours": "first"}}


@pytest.mark.parametrize("name", available_methods())
def test_adding_a_tour_equals_fitting_on_both(name: str, tiny_route: dict[str, Any], tmp_path: Path) -> None:
    cls = get_method(name)
    res = _res(tiny_route)
    a, b = tiny_route["map"], tiny_route["training"]  # noon, then the morning tour
    both = cls(**ADD_TOUR_PARAMS.get(name, {})).fit([a, b], resources=res)
    # Through a saved state, as `topoloc map add` does.
    meta, arrays = cls(**ADD_TOUR_PARAMS.get(name, {})).fit([a], resources=res).get_state()
    write_container(tmp_path / "a.bin", "test-state", 1, arrays, meta)
    meta, arrays = read_container(tmp_path / "a.bin", "test-state", 1, mmap=True)
    later = cls.from_state(both.get_params(), meta, arrays, resources=res).add_tour(b)
    np.testing.assert_array_equal(later.place_ids_, both.place_ids_)
    np.testing.assert_array_equal(later.similarity(tiny_route["query"]), both.similarity(tiny_route["query"]))


def test_a_landmark_map_of_separate_tours_adds_a_tour_by_online_learning(tiny_route: dict[str, Any]) -> None:
    cls = get_method("landmarks")
    res = _res(tiny_route)
    m = cls().fit([tiny_route["map"]], resources=res)
    nodes = m.node_place_.copy()
    m.add_tour(tiny_route["training"])
    # No new nodes (that would rebuild the landmarks); every image was counted at a node.
    np.testing.assert_array_equal(m.node_place_, nodes)
    assert m.model_.node_count_.sum() == len(tiny_route["map"]) + len(tiny_route["training"])


@pytest.mark.parametrize("name", sorted(set(available_methods()) - {"landmarks"}))
def test_a_tour_with_new_places_adds_rows(name: str, tiny_route: dict[str, Any]) -> None:
    cls = get_method(name)
    res = _res(tiny_route)
    part = _first_part(tiny_route["map"], 5)
    both = cls(**FAST.get(name, {})).fit([part, tiny_route["training"]], resources=res)
    later = cls(**FAST.get(name, {})).fit([part], resources=res)
    assert len(later.place_ids_) < len(both.place_ids_)
    later.add_tour(tiny_route["training"])
    np.testing.assert_array_equal(later.place_ids_, both.place_ids_)
    np.testing.assert_array_equal(later.similarity(tiny_route["query"]), both.similarity(tiny_route["query"]))


def test_landmarks_refuse_new_places_but_learn_known_ones(tiny_route: dict[str, Any]) -> None:
    res = _res(tiny_route)
    rec = get_method("landmarks")().fit([_first_part(tiny_route["map"], 5)], resources=res)
    with pytest.raises(TopolocError, match="places the map has no node for"):
        rec.add_tour(tiny_route["training"])
    before = rec.model_.node_count_.sum()
    rec.add_tour(_first_part(tiny_route["training"], 5))
    assert rec.model_.node_count_.sum() > before
