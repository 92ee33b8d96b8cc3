"""Learned state of an object as JSON metadata plus named arrays (what a map file stores).

:func:`object_state` walks the attributes of an object and splits them into
JSON-able values, NumPy arrays and SciPy sparse matrices; :func:`restore_state`
sets them back on an object made without calling ``__init__``.  Nothing is
pickled, so a map file can never run code when it is loaded.  Attributes that
cannot be stored this way (a faiss index, a lock) are named in ``skip`` and
rebuilt by the owner after :func:`restore_state`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import scipy.sparse as sp

from topoloc.errors import TopolocError

_SPARSE_PARTS = ("data", "indices", "indptr")


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

    Raises
    ------
    TopolocError
        If an array named in ``meta`` is missing (a file that does not hold what it says).
    """
    try:
        for name, value in meta["json"].items():
            setattr(obj, name, value)
        for name in meta["arrays"]:
            a = arrays[prefix + name]
            setattr(obj, name, np.array(a) if copy else a)
        for name, (fmt, shape) in meta["sparse"].items():
            parts = [np.array(arrays[f"{prefix}{name}.{part}"]) for part in _SPARSE_PARTS]
            cls = sp.csc_matrix if fmt == "csc" else sp.csr_matrix
            setattr(obj, name, cls(tuple(parts), shape=tuple(shape)))
    except (KeyError, TypeError, ValueError) as exc:
        raise TopolocError(f"stored state of {type(obj).__name__} is incomplete or malformed ({exc})") from None
    return obj


def new_object(cls: type) -> Any:
    """An instance of ``cls`` without running ``__init__`` (its state comes from :func:`restore_state`)."""
    return object.__new__(cls)


__all__ = ["new_object", "object_state", "restore_state"]
