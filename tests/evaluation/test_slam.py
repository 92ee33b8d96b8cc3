"""``run_slam``: online FAB-MAP over a traverse, its outputs and its argument checks."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.evaluation.slam import run_slam, save_fabmap_model
from topoloc.fabmap.model import FabMapModel
from topoloc.synth.words import loop_sequence as make_loop

V = 400


@pytest.fixture(scope="module")
def model(fabmap_loop_model: FabMapModel) -> FabMapModel:
    return fabmap_loop_model


def loop_sequence(n_places: int = 20, seed: int = 3) -> tuple[list[np.ndarray], np.ndarray]:
    return make_loop(n_places, n_words=V, seed=seed)


def test_run_slam_writes_outputs(model: FabMapModel, tmp_path: Path) -> None:
    seq, truth = loop_sequence(n_places=12)
    images = tuple(tmp_path / f"{k}.jpg" for k in range(len(seq)))
    tr = Traverse(root=tmp_path, images=images, places=np.arange(len(seq)))
    model_file = tmp_path / "m.tfm"
    save_fabmap_model(model, model_file)
    out = tmp_path / "out"
    res = run_slam(tr, out_dir=out, model=model_file, words=seq, min_gap=5)
    post = np.load(out / "posterior.npy")
    assert post.shape == (len(seq), res.n_places + 1)
    with (out / "loop_closures.csv").open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["image", "image_name", "matched_image", "matched_image_name", "probability"]
    assert len(rows) - 1 == len(res.loop_closures()) > 0
    for img, img_name, matched, matched_name, p in rows[1:]:
        assert int(img) >= 12 and int(matched) < 12 and float(p) >= 0.98
        assert (img_name, matched_name) == (f"{img}.jpg", f"{matched}.jpg")
        assert truth[int(img)] == truth[int(matched)]
    assert (out / "loop_closures.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "assignments.csv").is_file() and (out / "slam.json").is_file()
    lcm = res.loop_closure_matrix()
    assert lcm.shape == (len(seq), len(seq))


def test_run_slam_errors(model: FabMapModel, tmp_path: Path) -> None:
    tr = Traverse(root=tmp_path, images=(tmp_path / "a.jpg",), places=np.arange(1))
    with pytest.raises(TopolocError, match="traverse has"):
        run_slam(tr, out_dir=tmp_path / "o", model=model, words=[np.array([1]), np.array([2])])
    with pytest.raises(TopolocError, match="resources"):
        run_slam(tr, out_dir=tmp_path / "o", model=model)
