"""Online FAB-MAP: motion model, data association (Eq. 11) and loop closures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from topoloc.errors import TopolocError
from topoloc.evaluation.slam import write_slam_outputs
from topoloc.fabmap.model import FabMapModel
from topoloc.fabmap.slam import FabMapSlam, motion_prior
from topoloc.synth.words import loop_sequence as make_loop

V = 400


@pytest.fixture(scope="module")
def model(fabmap_loop_model: FabMapModel) -> FabMapModel:
    return fabmap_loop_model


def loop_sequence(n_places: int = 20, seed: int = 3) -> tuple[list[np.ndarray], np.ndarray]:
    return make_loop(n_places, n_words=V, seed=seed)


def test_motion_prior_by_hand() -> None:
    chain = np.array([[0, 1], [1, 2]])
    # at place 1 of a chain: a third stays, a third to each neighbour
    assert np.allclose(motion_prior(np.array([0.0, 1.0, 0.0]), chain, p_uniform=0.0),
                       [1 / 3, 1 / 3, 1 / 3])
    # at the end of the chain: a third stays, the rest goes to the single neighbour
    assert np.allclose(motion_prior(np.array([1.0, 0.0, 0.0]), chain, p_uniform=0.0),
                       [1 / 3, 2 / 3, 0.0])
    # uniform mixing and an isolated place (keeps its mass)
    out = motion_prior(np.array([0.0, 0.0, 0.0, 1.0]), chain, p_uniform=0.2)
    assert np.allclose(out, 0.8 * np.array([0, 0, 0, 1.0]) + 0.05)
    assert out.sum() == pytest.approx(1.0)


@pytest.mark.parametrize("variant", ["fabmap", "fabmap2"])
def test_loop_closures_on_second_pass_only(model: FabMapModel, variant: str) -> None:
    seq, truth = loop_sequence()
    n = len(seq) // 2
    slam = FabMapSlam(model, variant=variant, min_gap=5)
    res = slam.run(seq)
    founders = np.asarray(res.founders)
    # first pass: every image founds its own place, no loop closure
    assert all(s.new_place and not s.loop_closure for s in res.steps[:n])
    assert res.n_places >= n
    lc = res.loop_closures()
    assert all(img >= n for img, _, _ in lc)
    # second pass: most images close the loop with the image of the same place
    correct = [img for img, matched, p in lc if truth[img] == truth[matched] and p >= 0.98]
    assert len(correct) >= 0.75 * n
    assert len(correct) == len(lc)  # no false loop closures
    # merged places (Eq. 11): revisits updated the first-pass places
    assert res.n_places < 2 * n
    assert set(founders[res.image_place[n:][[s.loop_closure for s in res.steps[n:]]]]) <= set(
        range(n))


def test_posterior_rows_and_data_association(model: FabMapModel) -> None:
    seq, _ = loop_sequence(n_places=8)
    res = FabMapSlam(model, normaliser="mean_field", min_gap=2).run(seq)
    post = res.posterior_matrix()
    assert post.shape == (len(seq), res.n_places + 1)
    for k, s in enumerate(res.steps):
        n_k = s.posterior.size - 1
        assert np.isfinite(post[k, :n_k]).all() and np.isnan(post[k, n_k:-1]).all()
        assert np.nansum(post[k]) == pytest.approx(1.0)
        if s.new_place:
            assert post[k, :n_k].max(initial=0.0) < 0.98
    assert post[0, -1] == 1.0  # the first image is always a new place


def test_fabmap_slam_errors(model: FabMapModel) -> None:
    with pytest.raises(TopolocError, match="threshold"):
        FabMapSlam(model, threshold=0.0)
    with pytest.raises(TopolocError, match="variant"):
        FabMapSlam(model, variant="fabmap3")


def test_write_slam_outputs_from_word_arrays(model: FabMapModel, tmp_path: Path) -> None:
    seq, _ = loop_sequence(n_places=6)
    res = FabMapSlam(model, min_gap=3).run(seq)
    paths = write_slam_outputs(res, tmp_path, plot=False)
    assert set(paths) == {"posterior", "loop_closures", "assignments", "summary"}
    assert np.load(paths["posterior"]).shape == (len(seq), res.n_places + 1)
    summary = json.loads(paths["summary"].read_text())
    assert summary["n_images"] == len(seq) and summary["n_places"] == res.n_places
    assert summary["n_loop_closures"] == len(res.loop_closures())


def test_a_loop_closure_the_geometry_rejects_founds_a_new_place(model: FabMapModel) -> None:
    seq, _ = loop_sequence()
    n = len(seq) // 2
    plain = FabMapSlam(model, min_gap=5).run(seq)
    asked: list[tuple[int, int]] = []

    def verify(image: int, place: int) -> bool:
        asked.append((image, place))
        return image % 2 == 0  # odd images' loop closures fail the check

    slam = FabMapSlam(model, min_gap=5, verify=verify)
    res = slam.run(seq)
    # Only loop closures are checked (never the first pass, never staying at the previous image's place).
    assert asked and all(img >= n for img, _ in asked)
    assert {img for img, _ in slam.rejected} == {img for img, _ in asked if img % 2}
    lc = res.loop_closures()
    assert lc and all(img % 2 == 0 for img, _, _ in lc)
    assert all(res.steps[img].new_place for img, _ in slam.rejected)
    assert res.n_places > plain.n_places
    # Accepting every check changes nothing.
    same = FabMapSlam(model, min_gap=5, verify=lambda i, p: True).run(seq)
    assert same.loop_closures() == plain.loop_closures()
