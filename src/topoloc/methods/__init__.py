"""Place-recognition methods and their registry.

A method is one module of this package holding a :class:`PlaceRecognizer`
subclass with a ``name``; the registry finds it by importing the package's
modules on first use (not at ``import topoloc``, so that the CLI starts
fast).  Classes defined elsewhere join with :func:`register_method`, or from
an installed package through the ``topoloc.methods`` entry-point group
(``name = "package.module:Class"``).  ``get_method(name)`` returns the class.
"""

from __future__ import annotations

import importlib
import inspect
import logging
import pkgutil
import threading

from topoloc.errors import TopolocError
from topoloc.methods.base import PlaceRecognizer, RecognizerTags, map_place_ids

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "topoloc.methods"

_registry: dict[str, type[PlaceRecognizer]] = {}
_discovered = False
_lock = threading.Lock()


def _check_class(cls: object) -> type[PlaceRecognizer]:
    if not (isinstance(cls, type) and issubclass(cls, PlaceRecognizer)):
        raise TopolocError(f"{cls!r} is not a PlaceRecognizer subclass")
    if not cls.__dict__.get("name"):
        raise TopolocError(f"{cls.__name__} has no name of its own: set the class attribute `name`")
    if inspect.isabstract(cls):
        raise TopolocError(f"{cls.__name__} does not implement {', '.join(sorted(cls.__abstractmethods__))}")
    return cls


def _add(cls: type[PlaceRecognizer], *, replace: bool) -> None:
    old = _registry.get(cls.name)
    if old is not None and old is not cls and not replace:
        raise TopolocError(f"method name {cls.name!r} is taken by {old.__module__}.{old.__qualname__}")
    _registry[cls.name] = cls


def _discover() -> dict[str, type[PlaceRecognizer]]:
    """The registry, filled on first use from this package's modules and the entry points."""
    global _discovered
    if _discovered:
        return _registry
    with _lock:
        if _discovered:
            return _registry
        builtin: dict[str, type[PlaceRecognizer]] = {}
        for info in pkgutil.iter_modules(__path__, __name__ + "."):
            if info.name.rpartition(".")[2].startswith("_"):
                continue
            module = importlib.import_module(info.name)
            for obj in vars(module).values():
                # A class counts where it is defined (modules also import other methods' classes).
                if (isinstance(obj, type) and issubclass(obj, PlaceRecognizer) and obj.__module__ == module.__name__
                        and obj.__dict__.get("name") and not inspect.isabstract(obj)):
                    if obj.name in builtin and builtin[obj.name] is not obj:
                        raise TopolocError(f"two methods are named {obj.name!r}: {builtin[obj.name].__qualname__} "
                                           f"and {obj.__qualname__}")
                    builtin[obj.name] = obj
        # Classes registered before the first look-up (register_method) keep their place.
        _registry.update({k: v for k, v in builtin.items() if k not in _registry})
        for ep in _entry_points():
            try:
                _add(_check_class(ep.load()), replace=False)
            except Exception as exc:  # a broken plug-in must not take the built-in methods down with it
                log.warning("topoloc: skipped method plug-in %s (%s): %s", ep.name, ep.value, exc)
        _discovered = True
    return _registry


def _entry_points() -> list[importlib.metadata.EntryPoint]:
    import importlib.metadata

    return list(importlib.metadata.entry_points(group=ENTRY_POINT_GROUP))


def register_method(cls: type[PlaceRecognizer], *, replace: bool = False) -> type[PlaceRecognizer]:
    """Make a recogniser class available as ``get_method(cls.name)`` (``Map.build``, ``evaluate``, ``Map.load``).

    Usable as a class decorator.  Check the class first with
    :func:`topoloc.testing.check_recognizer`.

    Parameters
    ----------
    cls : type
        A :class:`PlaceRecognizer` subclass with its own ``name`` that
        implements ``_fit``, ``_encode`` and ``_score``.
    replace : bool
        Replace a class registered under the same name (default: refuse).

    Returns
    -------
    cls

    Raises
    ------
    TopolocError
        For a class that is not a complete recogniser, or a name already taken.
    """
    _check_class(cls)
    _discover()
    with _lock:
        _add(cls, replace=replace)
    return cls


def unregister_method(name: str) -> None:
    """Remove a method registered with :func:`register_method` (tests, plug-in reloads).

    Raises
    ------
    TopolocError
        For an unknown name.
    """
    registry = _discover()
    with _lock:
        if registry.pop(name, None) is None:
            raise TopolocError(f"unknown method {name!r} (available: {', '.join(available_methods())})")


def available_methods() -> list[str]:
    """Names accepted by ``topoloc evaluate --method``."""
    return sorted(_discover())


def get_method(name: str) -> type[PlaceRecognizer]:
    """The method class registered under ``name``."""
    try:
        return _discover()[name]
    except KeyError:
        raise TopolocError(
            f"unknown method {name!r} (available: {', '.join(available_methods())})"
        ) from None


__all__ = [
    "PlaceRecognizer", "RecognizerTags", "available_methods",
    "get_method", "map_place_ids", "register_method", "unregister_method",
]
