"""Fuzz every loader with truncations, bit flips and random bytes: a one-line TopolocError or a correct load.

A seeded loop (no extra dependency), a few hundred cases in a few seconds: every
damaged file must give :class:`TopolocError` with a one-line message, never
another exception, never a hang; files that survive damage unchanged (a flip in
padding is caught by the checksum too) load as the original.
"""

from __future__ import annotations

import json
import time
import tracemalloc
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from topoloc.cli.main import app
from topoloc.datasets.groundtruth import ground_truth_from_file
from topoloc.datasets.traverse import load_traverse
from topoloc.errors import TopolocError
from topoloc.evaluation.slam import load_fabmap_model, save_fabmap_model
from topoloc.fabmap.model import FabMapModel
from topoloc.features import FeatureExtractor
from topoloc.io.container import _PREFIX, read_container, write_container
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


# -- crafted but checksummed: the content is wrong, every checksum right ---------------------------------
# A file written by someone else (or a bug) passes the CRCs: what it declares must still be checked against
# the bytes it holds before anything of the declared size is allocated.
def _rewrite_meta(path: Path, kind: str, version: int,
                  edit: Callable[[dict[str, Any], dict[str, np.ndarray]], None]) -> None:
    """Alter a container's metadata or arrays and write it again with the project's own writer (checksums right)."""
    meta, stored = read_container(path, kind, version)
    arrays = {k: np.array(a) for k, a in stored.items()}
    edit(meta, arrays)
    write_container(path, kind, version, arrays, meta)


def _rewrite_header(path: Path, edit: Callable[[bytes], bytes]) -> None:
    """Alter a container's raw JSON header and recompute its length and CRC (the payload is kept)."""
    data = path.read_bytes()
    magic, version, hlen, _ = _PREFIX.unpack_from(data)
    header = edit(data[_PREFIX.size: _PREFIX.size + hlen])
    path.write_bytes(_PREFIX.pack(magic, version, len(header), zlib.crc32(header)) + header
                     + data[_PREFIX.size + hlen:])


def _refused_cheaply(path: Path, load: Callable[[Path], Any], needle: str = "") -> str:
    """``load`` refuses ``path`` with one line naming it, within a second and 64 MB of Python-tracked memory."""
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(TopolocError) as exc:
            load(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    msg = str(exc.value)
    assert "\n" not in msg and str(path) in msg and needle in msg, msg
    assert time.perf_counter() - t0 < 1.0 and peak < 64 << 20, (time.perf_counter() - t0, peak)
    return msg


@pytest.fixture(scope="module")
def bow_map(tiny_route: dict[str, Any], tmp_path_factory: pytest.TempPathFactory) -> Path:
    p = tmp_path_factory.mktemp("bow_map") / "bow.tlm"
    Map.build(method="bow", tours=[tiny_route["map"]], vocabulary=tiny_route["vocabulary"]).save(p)
    return p


def _state(meta: dict[str, Any]) -> dict[str, Any]:
    state: dict[str, Any] = meta["state"]
    return state


@pytest.mark.parametrize("case", [
    "sparse_side_1e11", "sparse_side_vs_vocabulary", "sparse_indptr_short", "sparse_indptr_decreasing",
    "sparse_transposed", "sparse_index_outside", "sparse_format", "sparse_negative_shape", "names_a_method",
    "names_a_parameter", "names_private", "state_not_objects",
])
def test_crafted_map_state_is_refused_before_allocation(case: str, bow_map: Path, tmp_path: Path) -> None:
    p = tmp_path / "crafted.tlm"
    p.write_bytes(bow_map.read_bytes())
    n_docs = len(Map.load(bow_map).recognizer.doc_places_)

    def edit(meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        st = _state(meta)
        if case == "sparse_side_1e11":  # map info used to allocate 745 GiB along the words
            st["sparse"]["counts_"] = ["csr", [n_docs, 10**11]]
            st["json"]["n_words_"] = 10**11
        elif case == "sparse_side_vs_vocabulary":  # in range, but not the vocabulary's size
            st["sparse"]["counts_"] = ["csr", [n_docs, 1 << 30]]
            st["json"]["n_words_"] = 1 << 30
        elif case == "sparse_indptr_short":
            st["sparse"]["counts_"] = ["csr", [10**9, 300]]
        elif case == "sparse_indptr_decreasing":
            arrays["state/counts_.indptr"][1] = 10**6
        elif case == "sparse_transposed":  # the same parts read as the other orientation
            st["sparse"]["counts_"] = ["csc", [300, n_docs]]
        elif case == "sparse_index_outside":
            st["sparse"]["counts_"] = ["csr", [n_docs, 1]]
        elif case == "sparse_format":
            st["sparse"]["counts_"] = ["coo", [n_docs, 300]]
        elif case == "sparse_negative_shape":
            st["sparse"]["counts_"] = ["csr", [-n_docs, 300]]
        elif case == "names_a_method":
            st["json"]["score"] = 1
        elif case == "names_a_parameter":
            st["json"]["merge"] = "bogus"
        elif case == "names_private":
            st["json"]["__class__"] = "x"
        else:
            meta["state"] = {"json": [], "arrays": {}, "sparse": 3}

    _rewrite_meta(p, "map", 1, edit)
    _refused_cheaply(p, Map.load)
    r = CliRunner().invoke(app, ["map", "info", str(p)])
    assert r.exit_code == 2 and len(r.stderr.strip().splitlines()) == 1, (r.output, r.exception)


@pytest.mark.parametrize("case", [
    "absurd_shape", "shape_overflows_int64", "negative_shape", "float_shape", "negative_offset", "negative_nbytes",
    "past_the_payload", "deeply_nested", "structured_dtype",
])
def test_crafted_container_header_is_refused(case: str, bow_map: Path, tmp_path: Path) -> None:
    p = tmp_path / "crafted.tlm"
    p.write_bytes(bow_map.read_bytes())

    def edit(raw: bytes) -> bytes:
        header = json.loads(raw)
        entry = next(e for e in header["arrays"] if e["name"] == "places/xy_sums")
        if case == "deeply_nested":  # deeper than Python's JSON parser recurses
            return raw.replace(b'"meta": {', b'"meta": {"x": ' + b"[" * 200_000 + b"]" * 200_000 + b", ", 1)
        if case == "absurd_shape":
            entry["shape"] = [10**11, 3]
        elif case == "shape_overflows_int64":  # the product wraps around in int64
            entry["shape"] = [2**62, 4, 0 + 1]
        elif case == "negative_shape":
            entry["shape"] = [-1, 3]
        elif case == "float_shape":
            entry["shape"] = [1e11, 3]
        elif case == "negative_offset":
            entry["offset"] = -64
        elif case == "negative_nbytes":
            entry["nbytes"] = -8
        elif case == "past_the_payload":
            entry["offset"] = header["payload_nbytes"]
        else:
            entry["dtype"] = "(3,)f8"
        return json.dumps(header, sort_keys=True).encode()

    _rewrite_header(p, edit)
    _refused_cheaply(p, Map.load)


def test_crafted_vocabulary_shape_is_refused(tmp_path: Path) -> None:
    p = tmp_path / "v.tlv"
    word_vocabulary(20).save(p)

    def edit(raw: bytes) -> bytes:
        header = json.loads(raw)
        for e in header["arrays"]:
            e["shape"] = [10**12, *e["shape"][1:]]
        return json.dumps(header, sort_keys=True).encode()

    _rewrite_header(p, edit)
    _refused_cheaply(p, Vocabulary.load, "inconsistent header")
