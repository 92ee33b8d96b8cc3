"""Files written on a machine of the other byte order read as on this one (issue #49), for every kind and method.

A valid Cooc-Map map whose arrays are big-endian gave a traceback from the compiled matcher (numba
takes native arrays only).  The container records each array's dtype with its byte order, so such a
file is valid: every reader brings the arrays to this machine's order.  Generated here for every
method's map, a vocabulary, the container's own dtypes and a ``.npy`` read from elsewhere.
"""

from __future__ import annotations

import json
import struct
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.io.container import read_container, write_container
from topoloc.maps import Map
from topoloc.methods import available_methods

OTHER = ">" if sys.byteorder == "little" else "<"
FAST: dict[str, dict[str, Any]] = {"fabmap": {"n_samples": 20}, "fabmap2": {"n_samples": 20},
                                   "seqslam": {"ds": 3}, "coocmap": {"top_k": 3}}


def in_other_byte_order(src: Path, dst: Path) -> Path:
    """``src`` (a topoloc container) written again with every array of more than one byte in the other order."""
    data = src.read_bytes()
    header = json.loads(data[24:24 + struct.unpack_from("<Q", data, 12)[0]])
    meta, arrays = read_container(src, header["kind"])
    swapped = {k: a.astype(a.dtype.newbyteorder(OTHER)) if a.dtype.itemsize > 1 else a for k, a in arrays.items()}
    write_container(dst, header["kind"], header["kind_version"], swapped, meta)
    kinds = {e["dtype"][0] for e in json.loads(dst.read_bytes()[24:24 + struct.unpack_from("<Q", dst.read_bytes(),
                                                                                             12)[0]])["arrays"]}
    assert OTHER in kinds  # the copy really is in the other order
    return dst


def test_every_dtype_of_the_container_reads_in_this_machines_order(tmp_path: Path) -> None:
    arrays = {f"a_{dt}": np.arange(12).astype(dt).reshape(3, 4) for dt in
              ("int16", "int32", "int64", "uint16", "uint32", "uint64", "float16", "float32", "float64", "complex64")}
    arrays["bool"] = np.array([True, False])
    write_container(tmp_path / "a.bin", "thing", 1, arrays)
    in_other_byte_order(tmp_path / "a.bin", tmp_path / "b.bin")
    for mmap in (False, True):
        _, back = read_container(tmp_path / "b.bin", "thing", mmap=mmap)
        for name, a in arrays.items():
            assert back[name].dtype.isnative and back[name].dtype == a.dtype, name
            np.testing.assert_array_equal(back[name], a)


@pytest.mark.parametrize("method", sorted(available_methods()))
def test_a_map_of_every_method_in_the_other_byte_order_scores_as_written(method: str, tiny_route: dict[str, Any],
                                                                        tmp_path: Path) -> None:
    m = Map.build(method=method, tours=[tiny_route["map"]], params=FAST.get(method, {}),
                  vocabulary=tiny_route["vocabulary"] if method in ("bow", "coocmap", "fabmap", "fabmap2") else None,
                  vocab_train=(), cache_dir=tmp_path / "cache")
    native = m.save(tmp_path / "native.tlm")
    other = Map.load(in_other_byte_order(native, tmp_path / "other.tlm"))
    np.testing.assert_array_equal(other.similarity(tiny_route["query"]), m.similarity(tiny_route["query"]))
    if method != "descriptors":  # it reads descriptors computed elsewhere, not frames
        frame = tiny_route["query_frames"][2]
        assert other.localize(frame) == Map.load(native).localize(frame)


def test_a_vocabulary_in_the_other_byte_order_quantises_as_written(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    from topoloc.vocabulary import Vocabulary

    voc = tiny_route["vocabulary"]
    voc.save(tmp_path / "v.tlv")
    other = Vocabulary.load(in_other_byte_order(tmp_path / "v.tlv", tmp_path / "o.tlv"))
    probe = np.asarray(voc.words_[:20], np.float32) + 0.5
    np.testing.assert_array_equal(other.quantize(probe), voc.quantize(probe))


def test_a_npy_from_elsewhere_in_the_other_byte_order(tmp_path: Path) -> None:
    from topoloc.io.npy import load_npy_safely

    a = np.arange(6, dtype=np.float32).reshape(2, 3)
    np.save(tmp_path / "a.npy", a.astype(a.dtype.newbyteorder(OTHER)))
    back = load_npy_safely(tmp_path / "a.npy")
    assert back.dtype.isnative
    np.testing.assert_array_equal(back, a)


def test_localize_on_a_cooc_map_in_the_other_byte_order(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    """The campaign's case, as a user ran it: one line per frame, as from the map in this machine's order."""
    from typer.testing import CliRunner

    from topoloc.cli.main import app

    tiny_route["vocabulary"].save(tmp_path / "v.tlv")
    native = tmp_path / "native.tlm"
    runner = CliRunner()

    def ok(*args: str) -> None:
        r = runner.invoke(app, [*args, "--cache-dir", str(tmp_path / "cache"), "-q"])
        assert r.exit_code == 0, r.output

    ok("map", "build", "--method", "coocmap", "--map", str(tiny_route["map"].root), "--vocab", str(tmp_path / "v.tlv"),
       "--out", str(native))
    other = in_other_byte_order(native, tmp_path / "other.tlm")
    for m, out in ((native, tmp_path / "a.jsonl"), (other, tmp_path / "b.jsonl")):
        r = runner.invoke(app, ["localize", str(m), str(tiny_route["query"].root), "--out", str(out), "-q"])
        assert r.exit_code == 0, r.output
    assert (tmp_path / "a.jsonl").read_text() == (tmp_path / "b.jsonl").read_text()
