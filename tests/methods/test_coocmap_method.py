"""The coocmap method through the PlaceRecognizer contract, with hand-made features."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from topoloc.datasets.traverse import Traverse
from topoloc.errors import NotFittedError, TopolocError
from topoloc.methods.base import parse_param
from topoloc.methods.cooc_map import CoocMap, order_tours
from topoloc.resources import InMemoryResources
from topoloc.testing import features_for_words, word_vocabulary

N_WORDS = 40
SHAPE = (480, 640)


def _trav(name: str, places: list[int], hour: int | None = None) -> Traverse:
    times = None
    if hour is not None:
        times = np.array([f"2020-01-01T{hour:02d}:00:00"] * len(places), dtype="datetime64[s]")
    return Traverse(root=Path(f"/{name}"), images=tuple(Path(f"/{name}/{i}.png") for i in range(len(places))),
                    places=np.asarray(places, dtype=np.int64), times=times, name=name)


def _scene(rng: np.random.Generator, n: int = 30) -> tuple[np.ndarray, np.ndarray]:
    return rng.integers(0, N_WORDS, n), rng.uniform([0, 0], [640, 480], (n, 2)).astype(np.float32)


def _feature_traverse(name: str, scenes: list[tuple[np.ndarray, np.ndarray]], places: list[int],
                      hour: int | None = None) -> Traverse:
    times = None
    if hour is not None:
        times = np.array([f"2020-01-01T{hour:02d}:00:00"] * len(places), dtype="datetime64[s]")
    return Traverse.from_features([features_for_words(w, xy, SHAPE) for w, xy in scenes], places,
                                  name=name, times=times)


def _data() -> tuple[InMemoryResources, list[Traverse], Traverse]:
    rng = np.random.default_rng(0)
    day = [_scene(rng) for _ in range(6)]
    night = [_scene(rng) for _ in range(6)]  # night shows other features
    # Queries: place 2 at night (shifted 40 px: offsets unchanged), place 4 by day.
    queries = [(night[2][0], night[2][1] + 40), (day[4][0][:20], day[4][1][:20] - 30)]
    maps = [_feature_traverse("night", night, list(range(6)), hour=22),
            _feature_traverse("day", day, list(range(6)), hour=12)]
    return InMemoryResources(vocabulary=word_vocabulary(N_WORDS)), maps, _feature_traverse("q", queries, [2, 4])


def test_fit_score_recognises_day_and_night() -> None:
    res, maps, query = _data()
    for simultaneous, schedule in [(True, "compiled"), (True, "lazy"), (True, "best_first"), (True, "rounds"),
                                   (False, "lazy")]:
        m = CoocMap(grid_x=6, grid_y=4, simultaneous=simultaneous,
                    schedule=schedule, confidence="raw").fit(maps, resources=res)
        assert m.tour_order_ == ["day", "night"]  # ordered by time of day
        S = m.score(m.encode(query, resources=res))
        assert S.shape == (6, 2) and S.dtype == np.float32
        assert np.argmax(S, axis=0).tolist() == [2, 4]
        assert S[2, 0] >= 20 and S[4, 1] >= 15
    assert m.place_ids_.tolist() == list(range(6))


def test_order_tours_without_times_keeps_given_order() -> None:
    a, b = _trav("a", [0]), _trav("b", [0], hour=3)
    assert [t.name for t in order_tours([a, b])] == ["a", "b"]
    assert [t.name for t in order_tours([_trav("x", [0], 20), b])] == ["b", "x"]


def test_not_fitted_and_bad_params(tmp_path: Path) -> None:
    with pytest.raises(NotFittedError):
        CoocMap().score([(np.array([1]), np.zeros((1, 2), np.uint16))])
    res, maps, _ = _data()
    with pytest.raises(TopolocError, match="top_k"):
        CoocMap(top_k=0).fit(maps, resources=res)
    with pytest.raises(TopolocError, match="schedule"):
        CoocMap(schedule="fast").fit(maps, resources=res)


def test_model_path_is_gone_and_says_what_to_use(tmp_path: Path) -> None:
    # A fitted method is kept one way, in a map file; the old parameter says so in one line.
    for make in (lambda: CoocMap(grid_x=6, grid_y=4, model_path=str(tmp_path / "m.coocmap")),
                 lambda: CoocMap().set_params(model_path="m"),
                 lambda: parse_param(CoocMap, "model_path", "m")):
        with pytest.raises(TopolocError, match="model_path") as err:
            make()
        assert "Map.load" in str(err.value) and "map build" in str(err.value) and "\n" not in str(err.value)
    assert "model_path" not in CoocMap.param_names()
    assert not (tmp_path / "m.coocmap").exists()


def test_match_drawing_draws_query_beside_best_place() -> None:
    from topoloc.drawing.show_match import match_drawing

    res, maps, query = _data()
    method = CoocMap(grid_x=6, grid_y=4).fit(maps, resources=res)
    canvas, info = match_drawing(method, query, maps)  # place 2 at night
    assert info["best_place"] == 2 and info["score"] >= 20
    assert info["map_image"] == "night/2" and info["n_lines"] >= 20
    # Feature traverses have no pixels: drawn on white canvases of the images' size.
    assert canvas.shape == (SHAPE[0], 2 * SHAPE[1], 3) and (canvas < 255).any()
