"""``--method descriptors``: global descriptors computed elsewhere (.npy, HDF5 as hloc writes them)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.evaluation.topk import top_k_of
from topoloc.methods import get_method
from topoloc.methods.global_descriptors import GlobalDescriptors


def _traverse(root: Path, places: list[int], name: str = "t") -> Traverse:
    # The method never reads pixels: a traverse of image names (the files need not exist) is enough.
    return Traverse(root=root, images=tuple(root / f"{i:05d}.jpg" for i in range(len(places))),
                    places=np.asarray(places, np.int64), name=name)


@pytest.mark.parametrize("metric", ["cosine", "l2"])
def test_scores_are_cosine_or_negative_l2_max_over_a_places_images(metric: str, tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    a, b, q = rng.normal(size=(6, 8)), rng.normal(size=(6, 8)), rng.normal(size=(4, 8))
    np.save(tmp_path / "map.npy", np.vstack([a, b]).astype(np.float32))
    np.save(tmp_path / "query.npy", q.astype(np.float32))
    tours = [_traverse(tmp_path, [0, 1, 2, 3, 4, 5]), _traverse(tmp_path, [5, 4, 3, 2, 1, 0])]
    rec = GlobalDescriptors(map=str(tmp_path / "map.npy"), query=str(tmp_path / "query.npy"), metric=metric,
                            confidence="raw")
    S = rec.fit(tours).similarity(_traverse(tmp_path, [0, 1, 2, 3]))
    imgs, places = np.vstack([a, b]), np.r_[0:6, 5:-1:-1]
    if metric == "cosine":
        unit = lambda x: x / np.linalg.norm(x, axis=1, keepdims=True)  # noqa: E731
        per_img = unit(imgs) @ unit(q).T
    else:
        per_img = -np.linalg.norm(imgs[:, None] - q[None], axis=-1)
    expected = np.stack([per_img[places == p].max(axis=0) for p in range(6)])
    np.testing.assert_allclose(S, expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("confidence", ["raw", "margin"])
@pytest.mark.parametrize("metric", ["cosine", "l2"])
def test_faiss_top_k_equals_the_top_k_of_s(metric: str, confidence: str, tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    n = 50
    np.save(tmp_path / "map.npy", rng.normal(size=(2 * n, 16)).astype(np.float32))
    np.save(tmp_path / "query.npy", rng.normal(size=(30, 16)).astype(np.float32))
    places = list(rng.permutation(n)) + list(rng.permutation(n))  # two images per place, in any order
    # raw: faiss's search; margin: dense blocks of score (the margin needs the whole column).
    rec = GlobalDescriptors(map=str(tmp_path / "map.npy"), query=str(tmp_path / "query.npy"), metric=metric,
                            confidence=confidence)
    rec.fit([_traverse(tmp_path, places[:n]), _traverse(tmp_path, places[n:])])
    items = rec.encode(_traverse(tmp_path, list(range(30))))
    rows, scores = rec.top_k(items, 7, block=8)
    want_rows, want_scores = top_k_of(rec.score(items), 7)
    np.testing.assert_array_equal(rows, want_rows)
    np.testing.assert_allclose(scores, want_scores, rtol=1e-4, atol=1e-4)


def test_hloc_hdf5_rows_are_matched_by_image_name_and_a_plain_dataset_is_read(tmp_path: Path) -> None:
    h5py = pytest.importorskip("h5py")
    rng = np.random.default_rng(2)
    desc = rng.normal(size=(5, 4)).astype(np.float32)
    trav = _traverse(tmp_path, [0, 1, 2, 3, 4])
    with h5py.File(tmp_path / "global-feats-netvlad.h5", "w") as f:
        for i in (3, 0, 4, 1, 2):  # hloc writes groups in any order
            f.create_group(f"{i:05d}.jpg").create_dataset("global_descriptor", data=desc[i])
    with h5py.File(tmp_path / "plain.h5", "w") as f:
        f.create_dataset("feats", data=desc)
    hloc = GlobalDescriptors(map=str(tmp_path / "global-feats-netvlad.h5"), query=str(tmp_path / "plain.h5"),
                             dataset="feats")
    with pytest.raises(TopolocError, match="no 2-D dataset 'feats'"):
        hloc.fit(trav)
    hloc.set_params(dataset="global_descriptor").fit(trav)
    np.testing.assert_allclose(hloc.descriptors_, desc / np.linalg.norm(desc, axis=1, keepdims=True), rtol=1e-6)
    plain = GlobalDescriptors(map=str(tmp_path / "plain.h5"), dataset="feats").fit(trav)
    np.testing.assert_array_equal(plain.descriptors_, hloc.descriptors_)
    # hloc names images under the dataset's root: "db/00000.jpg" for the traverse folder "db".
    db = tmp_path / "db"
    with h5py.File(tmp_path / "nested.h5", "w") as f:
        for i in (4, 2, 0, 1, 3):
            f.create_group(f"db/{i:05d}.jpg").create_dataset("global_descriptor", data=desc[i])
    nested = GlobalDescriptors(map=str(tmp_path / "nested.h5")).fit(_traverse(db, [0, 1, 2, 3, 4]))
    np.testing.assert_array_equal(nested.descriptors_, hloc.descriptors_)
    with pytest.raises(TopolocError, match=r"no descriptor for image '00005\.jpg'"):
        nested.fit(_traverse(db, [0, 1, 2, 3, 4, 5]))


def test_hdf5_without_h5py_names_the_extra(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "d.h5").write_bytes(b"\x89HDF\r\n\x1a\n")
    monkeypatch.setitem(sys.modules, "h5py", None)
    with pytest.raises(TopolocError, match=r"pip install 'topoloc\[hdf5\]'") as exc:
        GlobalDescriptors(map=str(tmp_path / "d.h5")).fit(_traverse(tmp_path, [0]))
    assert "\n" not in str(exc.value)


def test_bad_files_are_one_line_errors(tmp_path: Path) -> None:
    np.save(tmp_path / "three.npy", np.ones((3, 4), np.float32))
    np.save(tmp_path / "flat.npy", np.ones(4, np.float32))
    (tmp_path / "junk.npy").write_bytes(b"not numpy")
    trav = _traverse(tmp_path, [0, 1])
    cases = [("three.npy", "has 3 rows but the map traverse has 2 images"), ("flat.npy", "2-D numeric array"),
             ("junk.npy", "cannot read descriptors"), ("missing.npy", "descriptor file does not exist")]
    for name, needle in cases:
        with pytest.raises(TopolocError, match=needle) as exc:
            GlobalDescriptors(map=str(tmp_path / name)).fit(trav)
        assert "\n" not in str(exc.value)
    with pytest.raises(TopolocError, match="no descriptor file for map traverse"):
        GlobalDescriptors().fit(trav)  # no file given and none in the folder


def test_add_tour_reads_the_tour_folders_file_or_refuses(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    rec = get_method("descriptors")().fit(tiny_route["map"])
    n = len(rec.descriptors_)
    rec.add_tour(tiny_route["training"])  # its folder holds descriptors.npy
    assert len(rec.descriptors_) == n + len(tiny_route["training"])
    with pytest.raises(TopolocError, match=r"put descriptors.npy \(one row per image\) in its folder"):
        rec.add_tour(_traverse(tmp_path, [0, 1]))


def test_a_restored_map_takes_queries_from_their_folders(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    np.save(tmp_path / "other.npy", np.zeros((3, 192), np.float32))
    rec = GlobalDescriptors(query=str(tmp_path / "other.npy")).fit(tiny_route["map"])
    meta, arrays = rec.get_state()
    back = GlobalDescriptors.from_state(rec.get_params(), meta, arrays)
    assert back.query == ""
    S = back.similarity(tiny_route["query"])  # the query folder's descriptors.npy, not other.npy
    np.testing.assert_allclose(S, GlobalDescriptors().fit(tiny_route["map"]).similarity(tiny_route["query"]))


def _run(cli: Any, route: dict[str, Any], out: Path, *extra: str) -> dict[str, Any]:
    cli.ok(["evaluate", "--method", "descriptors", "--map", str(route["map"].root),
            "--query", str(route["query"].root), "--out", str(out), "-q", *extra])
    return json.loads((out / "metrics.json").read_text())


def test_evaluate_descriptors_dense_top_k_and_sequence(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from topoloc.cli.main import app

    class Cli:
        def ok(self, args: list[str]) -> None:
            r = CliRunner().invoke(app, args)
            assert r.exit_code == 0, r.output + repr(r.exception)

    cli = Cli()
    files = ["--param", f"map={tiny_route['map'].root / 'descriptors.npy'}",
             "--param", f"query={tiny_route['query'].root / 'descriptors.npy'}"]
    dense = _run(cli, tiny_route, tmp_path / "dense", *files, "--tolerance-m", "3:10")
    assert (tmp_path / "dense" / "S.npy").is_file() and dense["recall_at_1"] > 0.5
    # Every place kept: the same metrics from the sparse S, no dense S or ground truth written.
    full = _run(cli, tiny_route, tmp_path / "top10", *files, "--tolerance-m", "3:10", "--top-k", "100")
    for key in ("auc", "recall_at_100_precision", "recall_at_1", "recall_at_5", "recall_at_10"):
        assert full[key] == pytest.approx(dense[key], abs=1e-9), key
    n_places = full["n_places"]
    assert full["top_k"] == n_places  # K above the number of places keeps them all
    assert not (tmp_path / "top10" / "S.npy").exists() and not (tmp_path / "top10" / "gt_hard.npy").exists()
    z = np.load(tmp_path / "top10" / "S_topk.npz")
    assert z["rows"].shape == z["scores"].shape == (len(tiny_route["query"]), n_places)
    # Fewer places kept, through the folders' own files; R@N beyond K is R@K.
    three = _run(cli, tiny_route, tmp_path / "top3", "--tolerance-m", "3:10", "--top-k", "3", "--recall-at", "1,3,5")
    assert three["recall_at_1"] == dense["recall_at_1"]
    assert three["recall_at_5"] == three["recall_at_3"] <= dense["recall_at_5"]
    seq = _run(cli, tiny_route, tmp_path / "seq", "--sequence", "2")
    assert seq["params"]["sequence"] == 2 and seq["method"] == "descriptors"
    seq_top = _run(cli, tiny_route, tmp_path / "seqtop", "--sequence", "2", "--top-k", "100")
    assert seq_top["auc"] == pytest.approx(seq["auc"], abs=1e-9)
