"""Learned state of an object as JSON metadata plus named arrays (what a map file stores).

:func:`object_state` walks the attributes of an object and splits them into
JSON-able values, NumPy arrays and SciPy sparse matrices; :func:`restore_state`
sets them back on an object made without calling ``__init__``.  Nothing is
pickled, so a map file can never run code when it is loaded.  Attributes that
cannot be stored this way (a faiss index, a lock) are named in ``skip`` and
rebuilt by the owner after :func:`restore_state`.
"""

from __future__ import annotations

import inspect
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import scipy.sparse as sp

from topoloc.errors import TopolocError

_SPARSE_PARTS = ("data", "indices", "indptr")
#: Longest side a sparse matrix restored from a file may have (2**31 - 1, SciPy's int32 indices).
#: Its other parts are checked against the bytes present, but a side costs nothing in the file
#: and, once the matrix is converted or summed along it, eight bytes each in memory.
MAX_SPARSE_SIDE = (1 << 31) - 1


def _json_value(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, tuple):
        return [_json_value(v) for v in value]
    return value


def _is_json(value: Any) -> bool:
    if value is None or isinstance(value, bool | int | float | str):
        return True
    if isinstance(value, list | tuple):
        return all(_is_json(v) for v in value)
    if isinstance(value, dict):
        return all(isinstance(k, str) and _is_json(v) for k, v in value.items())
    return isinstance(value, np.generic) and value.dtype.kind in "biuf"


def object_state(
    obj: Any, *, prefix: str = "", skip: Iterable[str] = (), only: Iterable[str] | None = None
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Split ``vars(obj)`` into ``(meta, arrays)``.

    Parameters
    ----------
    obj : object
    prefix : str
        Prepended to array names (``"model/"``), so several objects share one file.
    skip : iterable of str
        Attributes not to store.
    only : iterable of str, optional
        Store just these attributes.

    Returns
    -------
    meta : dict
        ``{"json": {name: value}, "sparse": {name: [format, shape]}, "arrays": [names]}``.
    arrays : dict of str to ndarray

    Raises
    ------
    TypeError
        For an attribute that is none of JSON-able, ndarray, sparse matrix.
    """
    skipped = set(skip)
    names = list(only) if only is not None else [k for k in vars(obj) if k not in skipped]
    json_part: dict[str, Any] = {}
    sparse_part: dict[str, Any] = {}
    array_names: list[str] = []
    arrays: dict[str, np.ndarray] = {}
    for name in names:
        value = getattr(obj, name)
        if isinstance(value, np.ndarray):
            if value.dtype.hasobject:
                raise TypeError(f"attribute {name!r} is an object array")
            arrays[prefix + name] = value
            array_names.append(name)
        elif sp.issparse(value):
            m = sp.csr_matrix(value) if value.format not in ("csr", "csc") else value
            for part in _SPARSE_PARTS:
                arrays[f"{prefix}{name}.{part}"] = getattr(m, part)
            sparse_part[name] = [m.format, list(m.shape)]
        elif _is_json(value):
            json_part[name] = _json_value(value)
        else:
            raise TypeError(f"attribute {name!r} of {type(obj).__name__} ({type(value).__name__}) is not storable")
    return {"json": json_part, "sparse": sparse_part, "arrays": array_names}, arrays


def restore_state(
    obj: Any, meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray], *, prefix: str = "", copy: bool = False
) -> Any:
    """Set the attributes described by ``meta`` (from :func:`object_state`) on ``obj``; returns ``obj``.

    With ``copy`` the arrays are copied (writeable), for owners that update them
    in place; otherwise they may stay read-only views of a memory-mapped file.

    The state comes from a file, so it is checked before anything is built
    from it: each name must be a public attribute that ``obj`` does not have
    yet (a parameter, a method or a private attribute is never replaced), and
    each sparse matrix must be consistent with its stored parts (index
    pointers of the declared length, increasing, ending on the number of
    values; indices inside the declared shape; sides at most
    :data:`MAX_SPARSE_SIDE`) before SciPy allocates anything of its size.

    Raises
    ------
    TopolocError
        If an array named in ``meta`` is missing or the state is malformed (a
        file that does not hold what it says).
    """
    try:
        parts = (meta["json"], meta["arrays"], meta["sparse"])
        if not (isinstance(parts[0], Mapping) and isinstance(parts[1], list) and isinstance(parts[2], Mapping)):
            raise TypeError("state parts are not an object, a list and an object")
        seen: set[str] = set()
        for name in [*parts[0], *parts[1], *parts[2]]:
            _check_name(obj, name, seen)
        for name, value in parts[0].items():
            setattr(obj, name, value)
        for name in parts[1]:
            a = arrays[prefix + name]
            setattr(obj, name, np.array(a) if copy else a)
        for name, spec in parts[2].items():
            setattr(obj, name, _sparse(name, spec, [arrays[f"{prefix}{name}.{part}"] for part in _SPARSE_PARTS]))
    except (KeyError, TypeError, ValueError) as exc:
        raise TopolocError(f"stored state of {type(obj).__name__} is incomplete or malformed ({exc})") from None
    return obj


def _check_name(obj: Any, name: Any, seen: set[str]) -> None:
    if not isinstance(name, str) or not name.isidentifier() or name.startswith("_"):
        raise ValueError(f"{name!r} is not a public attribute name")
    if name in seen or name in vars(obj):
        raise ValueError(f"attribute {name!r} is stored twice or replaces one the object has")
    attr = inspect.getattr_static(type(obj), name, None)
    if callable(attr) or isinstance(attr, property | classmethod | staticmethod):
        raise ValueError(f"attribute {name!r} would replace a method of {type(obj).__name__}")
    seen.add(name)


def _sparse(name: str, spec: Any, parts: list[np.ndarray]) -> sp.csr_matrix | sp.csc_matrix:
    """A CSR or CSC matrix from its stored parts, each checked against the others first."""
    if not (isinstance(spec, list | tuple) and len(spec) == 2):
        raise ValueError(f"sparse {name!r}: expected [format, shape], got {spec!r}")
    fmt, shape = spec
    if fmt not in ("csr", "csc"):
        raise ValueError(f"sparse {name!r}: format {fmt!r} is not csr or csc")
    if not (isinstance(shape, list | tuple) and len(shape) == 2 and all(
            isinstance(n, int) and not isinstance(n, bool) and 0 <= n <= MAX_SPARSE_SIDE for n in shape)):
        raise ValueError(f"sparse {name!r}: shape {shape!r} is not two whole numbers in 0..{MAX_SPARSE_SIDE}")
    data, indices, indptr = (np.asarray(p) for p in parts)
    major, minor = (shape[0], shape[1]) if fmt == "csr" else (shape[1], shape[0])
    if data.ndim != 1 or indices.ndim != 1 or indptr.ndim != 1:
        raise ValueError(f"sparse {name!r}: parts are not 1-D")
    if indices.dtype.kind not in "iu" or indptr.dtype.kind not in "iu" or data.dtype.kind not in "biuf":
        raise ValueError(f"sparse {name!r}: parts have dtypes {data.dtype}, {indices.dtype}, {indptr.dtype}")
    if len(indptr) != major + 1 or len(indices) != len(data):
        raise ValueError(f"sparse {name!r}: {len(indptr)} index pointers and {len(indices)} indices do not fit "
                         f"shape {list(shape)} with {len(data)} values")
    if indptr[0] != 0 or indptr[-1] != len(data) or (np.diff(indptr) < 0).any():
        raise ValueError(f"sparse {name!r}: index pointers are not increasing from 0 to {len(data)}")
    if len(indices) and (indices.min() < 0 or indices.max() >= minor):
        raise ValueError(f"sparse {name!r}: indices outside 0..{minor - 1}")
    cls = sp.csc_matrix if fmt == "csc" else sp.csr_matrix
    return cls((np.array(data), np.array(indices), np.array(indptr)), shape=(shape[0], shape[1]))


def new_object(cls: type) -> Any:
    """An instance of ``cls`` without running ``__init__`` (its state comes from :func:`restore_state`)."""
    return object.__new__(cls)


__all__ = ["new_object", "object_state", "restore_state"]
