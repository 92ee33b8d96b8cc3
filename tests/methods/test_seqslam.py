"""SeqSLAM as a method: preprocessing, difference matrix, fit/encode/score."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

import topoloc.methods.seq_slam as seqslam_mod
from topoloc.datasets.traverse import Traverse, load_traverse
from topoloc.errors import NotFittedError, TopolocError
from topoloc.methods.base import parse_param
from topoloc.methods.seq_slam import SeqSLAM, SingleImageSeqSLAM
from topoloc.resources import InMemoryResources
from topoloc.seqslam import difference_matrix, patch_normalize, preprocess_image

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"


# ------------------------------------------------------------ synthetic world
def _panorama(n_places: int, seed: int) -> np.ndarray:
    """A smooth random strip world, 64 px high, 64 px per place."""
    rng = np.random.default_rng(seed)
    pano = cv2.GaussianBlur(rng.random((64, 64 * n_places + 128)), (0, 0), 5.0)
    pano = (pano - pano.min()) / (pano.max() - pano.min())
    return (255 * pano).astype(np.float64)


def _write_traverse(
    folder: Path, pano: np.ndarray, places: list[int], *, shift: int = 0,
    gain: float = 1.0, offset: float = 0.0, noise: float = 0.0, seed: int = 0,
    sidecar: bool = False,
) -> Traverse:
    """Place k is the 128 x 64 crop at x = 64 k + shift, with a brightness change."""
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    names = []
    for i, k in enumerate(places):
        crop = pano[:, 64 * k + shift : 64 * k + shift + 128] * gain + offset
        crop = crop + rng.normal(0, noise, crop.shape) if noise else crop
        name = f"img{i:03d}.png"
        cv2.imwrite(str(folder / name), np.clip(crop, 0, 255).astype(np.uint8))
        names.append(name)
    if sidecar:
        rows = "".join(f"{n},{k}\n" for n, k in zip(names, places, strict=True))
        (folder / "places.csv").write_text("image,place\n" + rows)
    return load_traverse(folder)


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Traverse]:
    root = tmp_path_factory.mktemp("strip")
    n = 40
    pano = _panorama(n, seed=1)
    return {
        "map": _write_traverse(root / "map", pano, list(range(n))),
        # Night-like query: shifted a few pixels, darker, lower contrast, noisy.
        "query": _write_traverse(root / "query", pano, list(range(n)), shift=6, gain=0.35,
                                 offset=20, noise=20.0, seed=2),
        # A second map traverse covering only the first half, much brighter.
        "map2": _write_traverse(root / "map2", pano, list(range(20)), gain=0.6, offset=90,
                                sidecar=True),
    }


# --------------------------------------------------------------- preprocessing
def test_patch_normalize_statistics() -> None:
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (20, 30)).astype(np.uint8)
    img[:8, :8] = 77  # a flat patch
    z = patch_normalize(img, 8)
    assert z.shape == img.shape
    assert (z[:8, :8] == 0).all()
    for y0 in (0, 8, 16):  # includes the 4-row patches cut by the border
        for x0 in (8, 16, 24):
            p = z[y0 : y0 + 8, x0 : x0 + 8]
            assert abs(p.mean()) < 1e-9
            assert p.std(ddof=1) == pytest.approx(1.0)
    # Invariant to brightness and contrast within each patch.
    np.testing.assert_allclose(patch_normalize(0.5 * img.astype(float) + 40, 8)[8:, 8:],
                               z[8:, 8:], atol=1e-9)
    with pytest.raises(ValueError, match="patch_size"):
        patch_normalize(img, 1)


def test_preprocess_image_resizes_and_quantises() -> None:
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (96, 200, 3)).astype(np.uint8)
    v = preprocess_image(img)
    assert v.dtype == np.uint8 and v.shape == (64 * 32,)
    # levels_per_std=1 is OpenSeqSLAM's 127 + round(z): a handful of levels.
    v1 = preprocess_image(img, levels_per_std=1.0)
    assert set(np.unique(v1).tolist()) <= set(range(119, 136))
    raw = preprocess_image(img, width=20, height=10, patch_size=0)
    assert raw.shape == (200,)
    small = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    np.testing.assert_array_equal(
        raw, cv2.resize(small, (20, 10), interpolation=cv2.INTER_AREA).ravel()
    )


def test_difference_matrix_is_mean_absolute_difference() -> None:
    rng = np.random.default_rng(2)
    db = rng.integers(0, 256, (17, 50)).astype(np.uint8)
    q = rng.integers(0, 256, (5, 50)).astype(np.uint8)
    want = np.abs(db[:, None, :].astype(int) - q[None, :, :].astype(int)).mean(axis=2)
    got = difference_matrix(db, q)
    assert got.shape == (17, 5) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, rtol=1e-6)
    assert difference_matrix(db, q[:0]).shape == (17, 0)
    with pytest.raises(ValueError, match="sizes"):
        difference_matrix(db, q[:, :10])


# ------------------------------------------------------------------- method
def test_seqslam_recovers_the_route(world: dict[str, Traverse]) -> None:
    res = InMemoryResources(n_jobs=1)
    m = SeqSLAM().fit([world["map"]], resources=res)
    np.testing.assert_array_equal(m.place_ids_, np.arange(40))
    items = m.encode(world["query"], resources=res)
    assert len(items) == 40 and items[0].shape == (64 * 32,)
    S = m.score(items)
    assert S.shape == (40, 40) and S.dtype == np.float32
    right = np.argmax(S, axis=0) == np.arange(40)
    assert right.mean() >= 0.95
    # The per-image work is recorded for the evaluation's ms_features.
    assert sum(len(ms) for ms in res.image_ms.values()) == 80


def test_single_image_and_acceleration_variants(world: dict[str, Traverse]) -> None:
    res = InMemoryResources(n_jobs=1)
    single = SingleImageSeqSLAM().fit([world["map"]], resources=res)
    assert not single.scores_whole_sequence and SeqSLAM.scores_whole_sequence
    assert "ds" not in single.get_params()
    items = single.encode(world["query"], resources=res)
    S1 = single.score(items)
    assert S1.shape == (40, 40)
    # Scored query by query (as the evaluation does) it gives the same block.
    cols = np.concatenate([single.score([it]) for it in items], axis=1)
    np.testing.assert_allclose(cols, S1)
    assert (np.argmax(S1, axis=0) == np.arange(40)).mean() >= 0.8
    acc = SeqSLAM(search="acceleration").fit([world["map"]], resources=res)
    Sa = acc.score(items)
    assert (np.argmax(Sa, axis=0) == np.arange(40)).mean() >= 0.9
    # The uniqueness margin keeps the best matches and makes them positive.
    base = SeqSLAM().fit([world["map"]], resources=res).score(items)
    uniq = SeqSLAM(uniqueness=10).fit([world["map"]], resources=res).score(items)
    np.testing.assert_array_equal(np.argmax(uniq, axis=0), np.argmax(base, axis=0))
    assert (uniq.max(axis=0) > 0).all()


def test_several_map_traverses_take_the_best_image(world: dict[str, Traverse]) -> None:
    res = InMemoryResources(n_jobs=1)
    both = SeqSLAM().fit([world["map"], world["map2"]], resources=res)
    np.testing.assert_array_equal(both.place_ids_, np.arange(40))
    one = SeqSLAM().fit([world["map"]], resources=res)
    two = SeqSLAM().fit([world["map2"]], resources=res)
    np.testing.assert_array_equal(two.place_ids_, np.arange(20))
    Q = np.stack(both.encode(world["query"], resources=res))
    D = both.place_differences(Q)
    D1, D2 = one.place_differences(Q), two.place_differences(Q)
    np.testing.assert_allclose(D[:20], np.minimum(D1[:20], D2), rtol=1e-6)
    np.testing.assert_allclose(D[20:], D1[20:], rtol=1e-6)
    assert both.score(list(Q)).shape == (40, 40)


def test_blocks_of_queries_give_the_same_scores(
    world: dict[str, Traverse], monkeypatch: pytest.MonkeyPatch
) -> None:
    res = InMemoryResources(n_jobs=1)
    for search in ("constant", "acceleration"):
        m = SeqSLAM(search=search).fit([world["map"]], resources=res)
        items = m.encode(world["query"], resources=res)
        full = m.score(items)
        with monkeypatch.context() as mp:
            mp.setattr(seqslam_mod, "_MIN_BLOCK_QUERIES", 7)
            mp.setattr(seqslam_mod, "_MAX_BLOCK_CELLS", 1)
            np.testing.assert_allclose(m.score(items), full, rtol=1e-6, atol=1e-6)


def test_not_fitted_and_bad_items(world: dict[str, Traverse]) -> None:
    res = InMemoryResources(n_jobs=1)
    m = SeqSLAM()
    with pytest.raises(NotFittedError):
        m.score([np.zeros(2048, np.uint8)])
    with pytest.raises(NotFittedError):
        m.encode(world["query"], resources=res)
    m.fit([world["map"]], resources=res)
    with pytest.raises(TopolocError, match="shape"):
        m.score([np.zeros(100, np.uint8)])
    with pytest.raises(TopolocError, match="dtype"):
        m.score([np.zeros(2048, np.float32)])
    assert m.score([]).shape == (40, 0)


def test_parameters(world: dict[str, Traverse]) -> None:
    assert SeqSLAM.param_names() == [
        "width", "height", "patch_size", "levels_per_std", "enhance_window", "enhance_floor", "ds",
        "v_min", "v_max", "v_step", "search", "max_skip", "step_penalty", "uniqueness", "confidence",
    ]
    assert SingleImageSeqSLAM.param_names() == [
        "width", "height", "patch_size", "levels_per_std", "enhance_window", "enhance_floor", "uniqueness",
        "confidence",
    ]
    p = SeqSLAM().get_params()
    assert (p["width"], p["height"], p["patch_size"], p["ds"], p["enhance_window"]) == (
        64, 32, 8, 10, 10)
    assert (p["v_min"], p["v_max"], p["v_step"]) == (0.8, 1.2, 0.1)
    assert parse_param(SeqSLAM, "ds", "5") == 5
    assert parse_param(SeqSLAM, "search", "acceleration") == "acceleration"
    assert p["enhance_floor"] is True and parse_param(SeqSLAM, "enhance_floor", "false") is False
    res = InMemoryResources(n_jobs=1)
    for bad in ({"search": "zigzag"}, {"patch_size": 1}, {"v_min": 1.5}, {"ds": -1},
                {"levels_per_std": 0.0}, {"enhance_window": -2}, {"enhance_floor": "yes"}, {"uniqueness": -1}):
        with pytest.raises(TopolocError):
            SeqSLAM(**bad).fit([world["map"]], resources=res)


def test_the_floor_is_what_enhanced_differences_use(world: dict[str, Traverse]) -> None:
    from topoloc.sequence.search import contrast_enhance

    res = InMemoryResources(n_jobs=1)
    for floor in (True, False):
        m = SeqSLAM(enhance_floor=floor).fit([world["map"]], resources=res)
        Q = np.stack(m.encode(world["query"], resources=res))
        np.testing.assert_array_equal(m.enhanced_differences(Q),
                                      contrast_enhance(m.place_differences(Q), window=10, spread_floor=floor))


# ------------------------------------------------------- degenerate frames (#12)
def _degenerate(kind: str, seed: int) -> np.ndarray:
    """A 64 x 32 frame without structure: the issue's recipe and its relatives."""
    rng = np.random.default_rng(seed)
    if kind == "dark":  # value 6 with ~12 scattered pixels of 20-90 (issue #12)
        im = np.full((32, 64), 6, np.uint8)
        idx = rng.choice(im.size, 12, replace=False)
        im.flat[idx] = rng.integers(20, 90, 12)
        return im
    if kind == "uniform":
        return np.full((32, 64), 128, np.uint8)
    if kind == "overexposed":
        return np.full((32, 64, 3), 255, np.uint8)
    assert kind == "featureless"  # a faint smooth gradient, no texture
    return np.tile(np.linspace(100, 104, 64), (32, 1)).astype(np.uint8)


def _strip_frames(pano: np.ndarray, n: int, **kw: float) -> list[np.ndarray]:
    rng = np.random.default_rng(int(kw.get("seed", 0)))
    shift, gain = int(kw.get("shift", 0)), kw.get("gain", 1.0)
    out = []
    for k in range(n):
        crop = pano[:, 64 * k + shift : 64 * k + shift + 128] * gain + kw.get("offset", 0.0)
        if kw.get("noise", 0.0):
            crop = crop + rng.normal(0, kw["noise"], crop.shape)
        out.append(np.clip(crop, 0, 255).astype(np.uint8))
    return out


@pytest.mark.parametrize("kind", ["dark", "uniform", "overexposed", "featureless"])
@pytest.mark.parametrize("where", ["first", "middle"])
@pytest.mark.parametrize("floor", [True, False])
def test_one_degenerate_frame_does_not_capture_the_queries(kind: str, where: str, floor: bool) -> None:
    # Issue #12's recipe on a synthetic route: the same structureless frame is
    # put into both traverses (first, or in the middle), as a tunnel or a
    # blanked camera gives.  It patch-normalises to (almost) all zeros, which
    # is closer to every image than the true place is; before the fix the
    # trajectories of the first places sat on it for all ds + 1 frames and it
    # was the best match of every query.
    n = 60
    pano = _panorama(n, seed=4)
    summer = _strip_frames(pano, n)
    winter = _strip_frames(pano, n, shift=6, gain=0.35, offset=20, noise=20.0, seed=5)
    at = 0 if where == "first" else n // 2
    summer[at], winter[at] = _degenerate(kind, 1), _degenerate(kind, 2)
    res = InMemoryResources(n_jobs=1)
    m = SeqSLAM(enhance_floor=floor).fit([Traverse.from_images(summer, name="summer")], resources=res)
    D = m.place_differences(np.stack(m.encode(Traverse.from_images(winter), resources=res)))
    others = np.delete(np.arange(n), at)
    # The degenerate image is nearer to most queries than their own place is...
    assert np.mean(D[at, others] < D[others, others]) > 0.5
    S = m.score(m.encode(Traverse.from_images(winter, name="winter"), resources=res))
    best = np.argmax(S, axis=0)
    # ...yet no query with a sequence behind it (query 0 has a single frame, so
    # it is matched as single images are) takes it more than one place from
    # its own (neighbouring crops overlap by half), and the route is recovered.
    far = np.abs(np.arange(n) - at) > 1
    assert np.sum((best == at) & far & (np.arange(n) >= 1)) == 0
    assert np.mean(np.abs(best - np.arange(n)) <= 1) >= 0.9


# ---------------------------------------------------------------- real data
@pytest.mark.realdata
def test_nordland_first_200_frames() -> None:
    root = DATA / "nordland_64x32"
    if not (root / "summer").is_dir() or not (root / "winter").is_dir():
        pytest.skip(f"{root} is not available")

    def first(t: Traverse, n: int = 200) -> Traverse:
        return Traverse(root=t.root, images=t.images[:n], places=t.places[:n])

    summer = first(load_traverse(root / "summer"))
    winter = first(load_traverse(root / "winter"))
    res = InMemoryResources()
    m = SeqSLAM().fit([summer], resources=res)
    S = m.score(m.encode(winter, resources=res))
    right = np.abs(np.argmax(S, axis=0) - np.arange(200)) <= 2
    assert right.mean() > 0.5  # chance is about 5 / 200
