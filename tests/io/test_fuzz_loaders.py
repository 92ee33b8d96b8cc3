"""Fuzz every loader with truncations, bit flips and random bytes: a one-line TopolocError or a correct load.

A seeded loop (no extra dependency), a few hundred cases in a few seconds: every
damaged file must give :class:`TopolocError` with a one-line message, never
another exception, never a hang; files that survive damage unchanged (a flip in
padding is caught by the checksum too) load as the original.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from topoloc.datasets.groundtruth import ground_truth_from_file
from topoloc.datasets.traverse import load_traverse
from topoloc.errors import TopolocError
from topoloc.evaluation.slam import load_fabmap_model, save_fabmap_model
from topoloc.fabmap.model import FabMapModel
from topoloc.features import FeatureExtractor
from topoloc.maps import Map
from topoloc.synth.words import zipf_occurrence
from topoloc.testing import word_vocabulary
from topoloc.vocabulary import Vocabulary

RNG = np.random.default_rng(20261123)


def _damaged(data: bytes, n: int) -> list[bytes]:
    out = [b"", data[:1], data[:7], data[: len(data) // 2], data[:-1], RNG.bytes(len(data)), RNG.bytes(64)]
    for _ in range(n):
        b = bytearray(data)
        for pos in RNG.integers(0, len(b), int(RNG.integers(1, 4))):
            b[pos] ^= 1 << int(RNG.integers(0, 8))
        out.append(bytes(b))
    return out


def _fuzz(path: Path, load: Callable[[Path], Any], n: int = 40) -> int:
    original = path.read_bytes()
    t0 = time.perf_counter()
    refused = 0
    for blob in _damaged(original, n):
        path.write_bytes(blob)
        try:
            load(path)
        except TopolocError as exc:
            assert "\n" not in str(exc), str(exc)
            refused += 1
        # Any other exception fails the test with its traceback.
    path.write_bytes(original)
    load(path)  # the undamaged file still loads
    assert time.perf_counter() - t0 < 60, "a loader hangs on damaged input"
    return refused


def test_fuzz_vocabulary(tmp_path: Path) -> None:
    p = tmp_path / "v.tlv"
    word_vocabulary(20).save(p)
    assert _fuzz(p, Vocabulary.load) >= 40


def test_fuzz_map_file(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    p = tmp_path / "m.tlm"
    Map.build(method="seqslam", tours=[tiny_route["map"]], params={"ds": 2}).save(p)
    assert _fuzz(p, Map.load, n=30) >= 30


def test_fuzz_fabmap_model(tmp_path: Path) -> None:
    # A Cooc-Map model has no file of its own any more: it lives in map files (fuzzed above).
    fm = FabMapModel.train(zipf_occurrence(30, n_words=60, words_per_image=10, seed=1), n_words=60)
    q = tmp_path / "f.tfm"
    save_fabmap_model(fm, q)
    assert _fuzz(q, load_fabmap_model) >= 40


def test_fuzz_feature_cache_entries(tmp_path: Path) -> None:
    img = tmp_path / "a.png"
    cv2.imwrite(str(img), cv2.GaussianBlur(RNG.integers(0, 255, (64, 64), dtype=np.uint8), (0, 0), 1.2))
    ex = FeatureExtractor(cache_dir=tmp_path / "cache")
    good = ex.extract_path(img)
    (entry,) = list(ex.feature_dir.glob("*.tlf"))
    original = entry.read_bytes()
    for blob in _damaged(original, 40):
        entry.write_bytes(blob)
        # A damaged entry is never an error: it is extracted again (and rewritten).
        np.testing.assert_array_equal(FeatureExtractor(cache_dir=tmp_path / "cache").extract_path(img).descriptors,
                                      good.descriptors)


@pytest.mark.parametrize("kind", ["places", "ground_truth_npy", "ground_truth_npz"])
def test_fuzz_text_and_numpy_inputs(kind: str, tmp_path: Path) -> None:
    folder = tmp_path / "t"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i}.png"), np.full((8, 8), 50 * i, np.uint8))
    trav = load_traverse(folder)
    if kind == "places":
        p = folder / "places.csv"
        p.write_text("image,place,time,x,y\n0.png,0,2024-01-01T10:00:00,1.5,2\n1.png,1,2024-01-01T10:00:01,3,4\n")
        assert _fuzz(p, lambda _: load_traverse(folder)) >= 1
    elif kind == "ground_truth_npy":
        p = tmp_path / "gt.npy"
        rows = np.empty((2, 2), object)
        rows[0] = [0, np.array([1])]
        rows[1] = [1, np.array([0, 2])]
        np.save(p, rows, allow_pickle=True)
        assert _fuzz(p, lambda x: ground_truth_from_file(x, map_traverse=trav, place_ids=np.arange(3),
                                                          n_queries=2)) >= 7
    else:
        p = tmp_path / "gt.npz"
        np.savez(p, GThard=np.eye(3, dtype=bool), GTsoft=np.eye(3, dtype=bool))
        assert _fuzz(p, lambda x: ground_truth_from_file(x, map_traverse=trav, place_ids=np.arange(3),
                                                          n_queries=3)) >= 7
