"""Reading ``.npy`` files from strangers: plain arrays and pickled object arrays, nothing that runs code.

VPR-Bench ships its ground truth as a pickled object array (one row per query:
its id and an array of matching map places).  ``np.load(..., allow_pickle=True)``
would run whatever code a hostile file carries, and even NumPy's own array
reconstruction is not safe on damaged input: an object array whose pickled
shape announces more elements than its list holds makes ``ndarray.__setstate__``
read past the list and crash the interpreter (found by
``tests/io/test_fuzz_loaders.py``).  So the unpickler here never hands pickled
state to NumPy: arrays, dtypes and scalars are rebuilt by this module from
checked pieces (shape against element count or byte length, dtype kind against
a short list), and anything else in the pickle is refused.
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np

__all__ = ["load_npy_safely"]

#: dtype kinds a pickled array may have: bool, integers, floats, complex, objects.
_KINDS = frozenset("biufcO")
#: Most elements a pickled array may announce (about 1 GB of int64).
_MAX_ELEMENTS = 1 << 27


class _NdarrayMarker:
    """Stands for ``numpy.ndarray`` inside a pickle; only :func:`_reconstruct` accepts it."""


_NDARRAY = _NdarrayMarker()


def _check_shape(shape: Any) -> tuple[int, ...]:
    if not isinstance(shape, tuple) or not all(isinstance(n, int) and n >= 0 for n in shape):
        raise pickle.UnpicklingError(f"bad array shape {shape!r}")
    if int(np.prod(shape, dtype=np.float64)) > _MAX_ELEMENTS:
        raise pickle.UnpicklingError(f"array shape {shape} is too large")
    return shape


class _DtypeStub:
    """Collects ``numpy.dtype``'s pickled arguments and state, then builds a checked dtype."""

    def __init__(self, spec: Any, align: Any = False, copy: Any = True) -> None:
        if not isinstance(spec, str):
            raise pickle.UnpicklingError(f"bad dtype {spec!r}")
        try:
            dt = np.dtype(spec)
        except TypeError as exc:
            raise pickle.UnpicklingError(f"bad dtype {spec!r}") from exc
        if dt.kind not in _KINDS or dt.fields is not None or dt.subdtype is not None:
            raise pickle.UnpicklingError(f"refusing dtype {spec!r}")
        self.dtype = dt

    def __setstate__(self, state: Any) -> None:
        # (version, byte order, subarray, names, fields, elsize, alignment, flags)
        if not isinstance(state, tuple) or len(state) < 5 or any(s is not None for s in state[2:5]):
            raise pickle.UnpicklingError("bad dtype state")
        order = state[1]
        if order not in ("<", ">", "|", "="):
            raise pickle.UnpicklingError(f"bad dtype byte order {order!r}")
        if order in ("<", ">"):
            self.dtype = self.dtype.newbyteorder(order)


class _ArrayStub:
    """Stands for an array while the pickle is read; :meth:`__setstate__` builds the real one."""

    def __init__(self) -> None:
        self.value: np.ndarray | None = None

    def __setstate__(self, state: Any) -> None:
        if not isinstance(state, tuple) or len(state) != 5:
            raise pickle.UnpicklingError("bad array state")
        _, shape, dtype, fortran, data = state
        shape = _check_shape(shape)
        if not isinstance(dtype, _DtypeStub) or not isinstance(fortran, bool):
            raise pickle.UnpicklingError("bad array state")
        dt, n = dtype.dtype, int(np.prod(shape, dtype=np.int64))
        order: Literal["C", "F"] = "F" if fortran else "C"
        if dt.kind == "O":
            if not isinstance(data, list) or len(data) != n:
                raise pickle.UnpicklingError(f"object array of shape {shape} holds {_length(data)} elements")
            flat = np.empty(n, dtype=object)
            for i, item in enumerate(data):
                flat[i] = _resolve(item)
            # NumPy pickles an object array's elements in C order whatever its layout
            # (its raw bytes, below, in memory order).
            obj = flat.reshape(shape)
            self.value = np.asfortranarray(obj) if fortran else obj
            return
        if not isinstance(data, bytes) or len(data) != n * dt.itemsize:
            raise pickle.UnpicklingError(f"array of shape {shape} and dtype {dt} holds {_length(data)} bytes")
        self.value = np.frombuffer(data, dtype=dt, count=n).reshape(shape, order=order).copy()


def _length(data: Any) -> str:
    return str(len(data)) if isinstance(data, (list, bytes)) else type(data).__name__


def _reconstruct(cls: Any, shape: Any, typecode: Any) -> _ArrayStub:
    if cls is not _NDARRAY:
        raise pickle.UnpicklingError("only plain arrays can be reconstructed")
    return _ArrayStub()


def _scalar(dtype: Any, data: Any = None) -> Any:
    if not isinstance(dtype, _DtypeStub) or dtype.dtype.kind == "O":
        raise pickle.UnpicklingError("bad scalar")
    if not isinstance(data, bytes) or len(data) != dtype.dtype.itemsize:
        raise pickle.UnpicklingError("bad scalar")
    return np.frombuffer(data, dtype=dtype.dtype, count=1)[0]


def _resolve(item: Any) -> Any:
    """Replace stubs (in lists and tuples too) by the values they built."""
    if isinstance(item, _ArrayStub):
        if item.value is None:
            raise pickle.UnpicklingError("array without state")
        return item.value
    if isinstance(item, _DtypeStub):
        return item.dtype
    if isinstance(item, list):
        return [_resolve(x) for x in item]
    if isinstance(item, tuple):
        return tuple(_resolve(x) for x in item)
    return item


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles NumPy arrays and plain containers through the checked stubs above."""

    _GLOBALS: ClassVar[dict[tuple[str, str], Any]] = {
        ("numpy.core.multiarray", "_reconstruct"): _reconstruct,
        ("numpy._core.multiarray", "_reconstruct"): _reconstruct,
        ("numpy.core.multiarray", "scalar"): _scalar,
        ("numpy._core.multiarray", "scalar"): _scalar,
        ("numpy", "ndarray"): _NDARRAY,
        ("numpy", "dtype"): _DtypeStub,
        ("builtins", "list"): list,
        ("builtins", "tuple"): tuple,
    }

    def find_class(self, module: str, name: str) -> Any:
        try:
            return self._GLOBALS[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name}") from None


def load_npy_safely(source: Path | bytes) -> np.ndarray:
    """Read a ``.npy`` file (or its bytes) without running code from it.

    Plain arrays are read directly: the header must announce exactly the bytes
    that follow it, so a damaged header cannot make the reader allocate more than
    the file holds.  Object arrays (pickled) are rebuilt by a restricted
    unpickler from checked pieces (see the module docstring).

    Parameters
    ----------
    source : Path or bytes

    Returns
    -------
    ndarray

    Raises
    ------
    ValueError, pickle.UnpicklingError, EOFError
        On any damaged or disallowed content; callers turn them into one-line errors.
    """
    data = source if isinstance(source, bytes) else source.read_bytes()
    fh = io.BytesIO(data)
    major, _ = np.lib.format.read_magic(fh)
    read_header = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
    shape, fortran, dtype = read_header(fh)
    if dtype.hasobject:
        arr = _resolve(_NumpyOnlyUnpickler(fh).load())
        if not isinstance(arr, np.ndarray):
            raise ValueError("not an array")
        return arr
    needed = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if needed != len(data) - fh.tell():
        raise ValueError(f"header announces {needed} bytes of data, the file holds {len(data) - fh.tell()}")
    arr = np.frombuffer(data, dtype=dtype, count=int(np.prod(shape, dtype=np.int64)), offset=fh.tell())
    if not dtype.isnative:  # written on a machine of the other byte order: this machine's order (issue #49)
        arr = arr.astype(dtype.newbyteorder("="))
    return arr.reshape(shape, order="F" if fortran else "C")
