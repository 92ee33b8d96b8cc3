"""The coocmap method through the PlaceRecognizer contract, with hand-made features."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from topoloc.datasets.traverse import Traverse
from topoloc.errors import NotFittedError, TopolocError
from topoloc.features import FeatureSet
from topoloc.methods.base import Resources
from topoloc.methods.cooc_map import CoocMap, order_tours

N_WORDS = 40
SHAPE = (480, 640)


class FakeResources(Resources):
    """Resources whose images are hand-made feature sets with known words."""

    def __init__(self, images: dict[str, list[tuple[np.ndarray, np.ndarray]]]) -> None:
        voc = SimpleNamespace(n_words_=N_WORDS, descriptor_kind_="sift-128-float32",
                              words_=np.zeros((N_WORDS, 1), np.float32), quantize=None)
        super().__init__(vocabulary=voc)  # type: ignore[arg-type]
        self._img = images

    def features(self, traverse: Traverse, *, timed: bool = True) -> list[FeatureSet]:
        out = []
        for words, xy in self._img[traverse.name]:
            kp = np.zeros((len(words), 5), np.float32)
            kp[:, :2] = xy
            out.append(FeatureSet(kp, words.astype(np.float32)[:, None], SHAPE))
        return out

    def words(self, traverse: Traverse, *, timed: bool = True) -> list[np.ndarray]:
        return [w for w, _ in self._img[traverse.name]]


def _trav(name: str, places: list[int], hour: int | None = None) -> Traverse:
    times = None
    if hour is not None:
        times = np.array([f"2020-01-01T{hour:02d}:00:00"] * len(places), dtype="datetime64[s]")
    return Traverse(root=Path(f"/{name}"), images=tuple(Path(f"/{name}/{i}.png") for i in range(len(places))),
                    places=np.asarray(places, dtype=np.int64), times=times, name=name)


def _scene(rng: np.random.Generator, n: int = 30) -> tuple[np.ndarray, np.ndarray]:
    return rng.integers(0, N_WORDS, n), rng.uniform([0, 0], [640, 480], (n, 2)).astype(np.float32)


def _data() -> tuple[FakeResources, list[Traverse], Traverse]:
    rng = np.random.default_rng(0)
    day = [_scene(rng) for _ in range(6)]
    night = [_scene(rng) for _ in range(6)]  # night shows other features
    # Queries: place 2 at night (shifted 40 px: offsets unchanged), place 4 by day.
    images = {
        "day": day, "night": night,
        "q": [(night[2][0], night[2][1] + 40), (day[4][0][:20], day[4][1][:20] - 30)],
    }
    maps = [_trav("night", list(range(6)), hour=22), _trav("day", list(range(6)), hour=12)]
    return FakeResources(images), maps, _trav("q", [2, 4])


def test_fit_score_recognises_day_and_night() -> None:
    res, maps, query = _data()
    for simultaneous, schedule in [(True, "lazy"), (True, "best_first"), (True, "rounds"),
                                   (False, "lazy")]:
        m = CoocMap(grid_x=6, grid_y=4, simultaneous=simultaneous,
                    schedule=schedule).fit(maps, resources=res)
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


def test_model_path_saves_then_loads(tmp_path: Path) -> None:
    res, maps, query = _data()
    path = tmp_path / "m.coocmap"
    a = CoocMap(grid_x=6, grid_y=4, model_path=str(path)).fit(maps, resources=res)
    assert path.is_file()
    b = CoocMap(grid_x=6, grid_y=4, model_path=str(path)).fit(maps, resources=res)
    items = a.encode(query, resources=res)
    np.testing.assert_array_equal(a.score(items), b.score(items))
    res._vocabulary = SimpleNamespace(  # type: ignore[assignment]
        n_words_=N_WORDS, descriptor_kind_="sift-128-float32",
        words_=np.ones((N_WORDS, 1), np.float32), quantize=None)
    with pytest.raises(TopolocError, match="another vocabulary"):
        CoocMap(grid_x=6, grid_y=4, model_path=str(path)).fit(maps, resources=res)


def test_show_match_draws_query_beside_best_place(tmp_path: Path) -> None:
    import cv2

    from topoloc.methods.show_match import show_match

    res, _, _ = _data()
    rng = np.random.default_rng(1)
    for tour in ("day", "night"):
        (tmp_path / tour).mkdir()
        for i in range(6):
            img = rng.integers(0, 255, (SHAPE[0], SHAPE[1], 3), dtype=np.uint8)
            cv2.imwrite(str(tmp_path / tour / f"{i}.png"), img)
    qpath = tmp_path / "query.png"
    cv2.imwrite(str(qpath), rng.integers(0, 255, (SHAPE[0], SHAPE[1], 3), dtype=np.uint8))
    qw, qxy = res._img["q"][0]  # place 2 at night
    kp = np.zeros((len(qw), 5), np.float32)
    kp[:, :2] = qxy
    res._extractor = SimpleNamespace(  # type: ignore[assignment]
        extract_path=lambda p: FeatureSet(kp, qw.astype(np.float32)[:, None], SHAPE))
    res._vocabulary.quantize = lambda d: d[:, 0].astype(np.int64)  # type: ignore[union-attr,method-assign]
    out = tmp_path / "match.png"
    info = show_match(qpath, [tmp_path / "day", tmp_path / "night"], out, resources=res,
                      grid_x=6, grid_y=4)
    assert info["best_place"] == 2 and info["score"] >= 20
    assert info["map_image"].endswith("night/2.png") and info["n_lines"] >= 20
    drawn = cv2.imread(str(out))
    assert drawn is not None and drawn.shape == (SHAPE[0], 2 * SHAPE[1], 3)
