"""FAB-MAP as a method (fabmap, fabmap2) and model persistence tied to a vocabulary."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.datasets.traverse import Traverse
from topoloc.errors import NotFittedError, TopolocError
from topoloc.evaluation.slam import load_fabmap_model, save_fabmap_model
from topoloc.fabmap.model import FabMapModel
from topoloc.fabmap.place_map import DenseMap
from topoloc.methods.base import parse_param
from topoloc.methods.fab_map import FabMap, FabMap2
from topoloc.resources import InMemoryResources
from topoloc.synth.words import zipf_occurrence
from topoloc.vocabulary import Vocabulary
from topoloc.vocabulary.vocab import vocabulary_fingerprint

V = 300


def _vocabulary(seed: int = 0, n_words: int = V) -> Vocabulary:
    """A vocabulary of ``n_words`` random SIFT-space words (FAB-MAP only needs its size and identity)."""
    words = np.random.default_rng(seed).random((n_words, 128)).astype(np.float32)
    return Vocabulary.from_words(words, descriptor_kind="sift-128-float32")


def _rows(x: Any) -> list[np.ndarray]:
    return [x.indices[x.indptr[i]:x.indptr[i + 1]].astype(np.int64) for i in range(x.shape[0])]


def _observe(words: np.ndarray, rng: np.random.Generator, fresh: np.ndarray) -> np.ndarray:
    kept = words[rng.random(words.size) < 0.7]
    # features repeat words: word ids with duplicates, as a quantiser returns them
    return np.concatenate([kept, kept[:3], rng.choice(fresh, size=6, replace=False)])


@pytest.fixture(scope="module")
def world() -> dict[str, Any]:
    rng = np.random.default_rng(0)
    places = _rows(zipf_occurrence(25, n_words=V, words_per_image=35, seed=1, permutation_seed=0))
    training = _rows(zipf_occurrence(200, n_words=V, words_per_image=35, seed=2, permutation_seed=0))
    fresh = zipf_occurrence(200, n_words=V, words_per_image=35, seed=3, permutation_seed=0)
    fr = _rows(fresh)
    ids = np.arange(100, 125)  # place ids need not start at 0
    map_a = [_observe(places[i], rng, fr[i]) for i in range(25)]
    map_b = [_observe(places[i], rng, fr[25 + i]) for i in range(25)]
    q_idx = rng.permutation(25)[:15]
    queries = [_observe(places[i], rng, fr[50 + k]) for k, i in enumerate(q_idx)]
    voc = _vocabulary()
    res = InMemoryResources(vocabulary=voc, training=Traverse.from_words(training, name="training"))
    return {
        "res": res,
        "maps": [Traverse.from_words(map_a, ids, name="a"), Traverse.from_words(map_b[::-1], ids[::-1], name="b")],
        "query": Traverse.from_words(queries, ids[q_idx], name="q"),
        "truth": ids[q_idx],
        "ids": ids,
        "voc": voc,
        "training": training,
    }


def test_not_fitted() -> None:
    with pytest.raises(NotFittedError):
        FabMap().score([np.array([1, 2])])
    with pytest.raises(NotFittedError):
        FabMap2().score([np.array([1, 2])])


@pytest.mark.parametrize("cls", [FabMap, FabMap2])
@pytest.mark.parametrize("output", ["loglik", "posterior"])
def test_localisation(world: dict[str, Any], cls: type[FabMap], output: str) -> None:
    m = cls(output=output, tours="merge", confidence="raw").fit(world["maps"], resources=world["res"])
    assert m.name in ("fabmap", "fabmap2") and m.uses_vocabulary
    assert np.array_equal(m.place_ids_, world["ids"])
    # two map traverses of the same places merged into one model per place (Eq. 11)
    assert m.map_.n_places == 25
    items = m.encode(world["query"], resources=world["res"])
    S = m.score(items)
    assert S.shape == (25, 15) and S.dtype == np.float32
    assert np.isfinite(S).all()
    hits = (m.place_ids_[np.argmax(S, axis=0)] == world["truth"]).mean()
    assert hits >= 0.9
    if output == "posterior":
        assert (S >= 0).all() and (S.sum(axis=0) <= 1 + 1e-5).all()


def test_loglik_is_eq4_and_options(world: dict[str, Any]) -> None:
    res = world["res"]
    base = FabMap(tours="merge", confidence="raw").fit(world["maps"], resources=res)
    items = base.encode(world["query"], resources=res)
    S = base.score(items)
    obs = base.obs_model_.observe(items[0])
    assert isinstance(base.map_, DenseMap)
    expected = [base.obs_model_.log_likelihood_single(e, obs) for e in base.map_.places.E]
    assert np.allclose(S[:, 0], expected, rtol=1e-5)
    # naive Bayes, mean field, bail-out all work and agree on the best place
    for kw in ({"naive_bayes": True}, {"bailout": True},
               {"output": "posterior", "normaliser": "mean_field", "smoothing": 0.99}):
        S2 = FabMap(tours="merge", **kw).fit(world["maps"], resources=res).score(items)
        assert S2.shape == S.shape
        assert (np.argmax(S2, axis=0) == np.argmax(S, axis=0)).mean() >= 0.9


def test_bad_params(world: dict[str, Any]) -> None:
    with pytest.raises(TopolocError, match="output"):
        FabMap(output="tfidf").fit(world["maps"], resources=world["res"])
    with pytest.raises(TopolocError, match="normaliser"):
        FabMap(normaliser="exact").fit(world["maps"], resources=world["res"])
    assert parse_param(FabMap, "output", "posterior") == "posterior"
    assert parse_param(FabMap2, "naive_bayes", "true") is True
    assert parse_param(FabMap, "p_new", "0.5") == 0.5


def test_missing_training_images(world: dict[str, Any]) -> None:
    # A vocabulary that records no training folders, and no training images given.
    with pytest.raises(TopolocError, match="training images"):
        FabMap().fit(world["maps"], resources=InMemoryResources(vocabulary=world["voc"]))


def test_model_save_load_and_vocabulary_binding(world: dict[str, Any], tmp_path: Path) -> None:
    voc = world["voc"]
    model = FabMapModel.train(world["training"], vocabulary=voc)
    assert model.vocabulary == vocabulary_fingerprint(voc)
    path = tmp_path / "fabmap.tfm"
    save_fabmap_model(model, path)
    loaded = load_fabmap_model(path, vocabulary=voc)
    for name in ("parents", "p_z", "p_z_given_parent", "p_e", "edge_mi", "joint_p",
                 "train_indptr", "train_indices"):
        assert np.array_equal(getattr(model, name), getattr(loaded, name)), name
    assert (loaded.root, loaded.p_fp, loaded.p_fn, loaded.n_words) == (
        model.root, model.p_fp, model.p_fn, model.n_words)
    # a method no longer reads a model file: a fitted method, model included, is kept in its map file
    for cls in (FabMap, FabMap2):
        with pytest.raises(TopolocError, match="model_path") as refused:
            cls(model_path=str(path))
        assert "Map.load" in str(refused.value) and "\n" not in str(refused.value)
    with pytest.raises(TopolocError, match="any more"):
        parse_param(FabMap2, "model_path", str(path))

    # another vocabulary (same size, other centres): refused, naming the file
    with pytest.raises(TopolocError, match="another vocabulary") as err:
        load_fabmap_model(path, vocabulary=_vocabulary(seed=1))
    assert str(path) in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(TopolocError, match="visual words"):
        load_fabmap_model(path, vocabulary=_vocabulary(n_words=V + 1))

    # truncated and corrupted files
    data = path.read_bytes()
    (tmp_path / "trunc.tfm").write_bytes(data[: len(data) // 2])
    with pytest.raises(TopolocError, match="truncated"):
        load_fabmap_model(tmp_path / "trunc.tfm")
    bad = bytearray(data)
    bad[-3] ^= 0xFF
    (tmp_path / "bad.tfm").write_bytes(bytes(bad))
    with pytest.raises(TopolocError, match=r"corrupt|checksum"):
        load_fabmap_model(tmp_path / "bad.tfm")
    with pytest.raises(TopolocError, match="not found"):
        load_fabmap_model(tmp_path / "missing.tfm")


def test_detector_validation(world: dict[str, Any]) -> None:
    with pytest.raises(TopolocError, match="detector"):
        FabMapModel.train(world["training"], n_words=V, p_fp=0.5, p_fn=0.6)
    with pytest.raises(TopolocError, match="at least 2"):
        FabMapModel.train(world["training"][:1], n_words=V)


@pytest.mark.parametrize("cls", [FabMap, FabMap2])
def test_separate_tours_score_a_place_by_its_best_image(world: dict[str, Any], cls: type[FabMap]) -> None:
    res = world["res"]
    a, b = world["maps"]
    sep = cls(tours="separate", confidence="raw").fit([a, b], resources=res)
    items = sep.encode(world["query"], resources=res)
    S = sep.score(items)
    # Each image its own model: the place's log-likelihood is the best of its two tours' images.
    Sa = cls(confidence="raw").fit([a], resources=res).score(items)
    Sb = cls(confidence="raw").fit([b], resources=res).score(items)
    np.testing.assert_allclose(S, np.maximum(Sa, Sb), rtol=1e-5)
    assert len(sep.model_row_) == 50 and np.array_equal(sep.place_ids_, world["ids"])
    post = cls(tours="separate", output="posterior", confidence="raw").fit([a, b], resources=res).score(items)
    assert (post >= 0).all() and (post.sum(axis=0) <= 1 + 1e-5).all()
    hits = (world["ids"][np.argmax(S, axis=0)] == world["truth"]).mean()
    assert hits >= 0.9


@pytest.mark.parametrize("cls", [FabMap, FabMap2])
def test_logodds_output_is_the_logit_of_the_posterior(world: dict[str, Any], cls: type[FabMap]) -> None:
    res = world["res"]
    a, b = world["maps"]
    post_m = cls(tours="separate", output="posterior", confidence="raw").fit([a, b], resources=res)
    items = post_m.encode(world["query"], resources=res)
    post = post_m.score(items).astype(np.float64)
    logit = cls(tours="separate", output="logodds").fit([a, b], resources=res).score(items).astype(np.float64)
    assert logit.shape == post.shape
    # Same ranking within every query, and the same probabilities wherever float32 can still tell.
    np.testing.assert_array_equal(np.argmax(logit, axis=0), np.argmax(post, axis=0))
    mid = (post > 1e-4) & (post < 1 - 1e-4)
    np.testing.assert_allclose(1 / (1 + np.exp(-logit[mid])), post[mid], rtol=1e-3, atol=1e-6)
