"""``load_npy_safely``: same arrays as ``np.load``, damaged or hostile pickles refused without crashing."""

from __future__ import annotations

import io
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from topoloc.io.npy import load_npy_safely


def _npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=True)
    return buf.getvalue()


def _vpr_rows() -> np.ndarray:
    rows = np.empty((2, 2), object)
    rows[0] = [0, np.array([1])]
    rows[1] = [1, np.array([0, 2])]
    return rows


@pytest.mark.parametrize("arr", [
    np.arange(12, dtype=np.int64).reshape(3, 4),
    np.asfortranarray(np.arange(6, dtype=">f4").reshape(2, 3)),
    np.array([True, False]),
])
def test_plain_arrays_are_read_as_numpy_reads_them(arr: np.ndarray) -> None:
    got = load_npy_safely(_npy(arr))
    np.testing.assert_array_equal(got, arr)
    # In this machine's byte order, whatever the file's (issue #49: compiled code takes native arrays only).
    assert got.dtype == arr.dtype.newbyteorder("=") and got.dtype.isnative


def test_object_rows_of_vpr_bench_are_rebuilt() -> None:
    rows = _vpr_rows()
    rows[1, 0] = np.int64(7)  # a pickled NumPy scalar
    got = load_npy_safely(_npy(rows))
    assert got.dtype == object and got.shape == (2, 2)
    assert got[0, 0] == 0 and got[1, 0] == 7 and isinstance(got[1, 0], np.int64)
    np.testing.assert_array_equal(got[1, 1], [0, 2])
    assert got[1, 1].dtype == np.array([0, 2]).dtype


def test_fortran_object_array_keeps_its_order() -> None:
    rows = np.asfortranarray(np.array([[1, "a"], [2.5, None]], dtype=object))
    got = load_npy_safely(_npy(rows))
    assert got.tolist() == rows.tolist()


def test_shape_longer_than_its_elements_is_refused_not_a_crash(tmp_path: Path) -> None:
    # NumPy's own __setstate__ reads past the list here and kills the interpreter (segfault);
    # run in a child so a regression fails this test instead of the whole session.
    data = _npy(_vpr_rows())
    pos = data.index(b"K\x02K\x02\x86")  # the pickled shape (2, 2)
    bad = data[:pos] + b"K\x22" + data[pos + 2:]
    f = tmp_path / "bad.npy"
    f.write_bytes(bad)
    code = ("import pickle, sys\nfrom pathlib import Path\nfrom topoloc.io.npy import load_npy_safely\n"
            f"try:\n    load_npy_safely(Path({str(f)!r}))\nexcept pickle.UnpicklingError as e:\n"
            "    print(e); sys.exit(3)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 3, (r.returncode, r.stderr[-500:])
    assert "holds 4 elements" in r.stdout


class _Evil:
    def __reduce__(self) -> tuple[object, tuple[str]]:
        return (os.system, ("echo pwned",))


def test_pickle_that_calls_a_function_is_refused() -> None:
    rows = np.empty(1, object)
    rows[0] = _Evil()
    with pytest.raises(pickle.UnpicklingError, match="refusing to load"):
        load_npy_safely(_npy(rows))


def test_structured_dtype_is_refused() -> None:
    rows = np.empty(1, object)
    rows[0] = np.zeros(2, dtype=[("a", "i4"), ("b", "f4")])
    with pytest.raises(pickle.UnpicklingError):
        load_npy_safely(_npy(rows))


def test_truncated_plain_array_is_refused() -> None:
    with pytest.raises(ValueError, match="header announces"):
        load_npy_safely(_npy(np.arange(10))[:-3])
