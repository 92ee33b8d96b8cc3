"""Declarative parameter constraints, checked in one place (scikit-learn's ``_parameter_constraints``).

A class lists, for each keyword-only constructor parameter, what values it
accepts; :func:`validate_params` checks them all and raises one
:class:`~topoloc.errors.TopolocError` with a one-line message naming the
owner, the parameter, what it should be and what it got.  Methods call it at
the start of ``fit`` (parameters may be changed by ``set_params`` in between,
as in scikit-learn), and :func:`convert_param` turns the strings of
``--param KEY=VALUE`` into the type of the parameter's default.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from topoloc.errors import TopolocError


@dataclass(frozen=True)
class Interval:
    """A number of ``kind`` (int or float) between ``low`` and ``high``.

    ``closed`` says which ends belong to the interval: ``"both"``,
    ``"left"``, ``"right"`` or ``"neither"``; ``None`` is an open end.
    Integers are accepted for a float interval; booleans never are.
    """

    kind: type
    low: float | None = None
    high: float | None = None
    closed: str = "both"

    def accepts(self, value: Any) -> bool:
        if isinstance(value, bool) or not isinstance(value, int | float):
            return False
        if self.kind is int and not (isinstance(value, int) or float(value).is_integer()):
            return False
        if isinstance(value, float) and math.isnan(value):
            return False
        lo_ok = self.low is None or (value >= self.low if self.closed in ("both", "left") else value > self.low)
        hi_ok = self.high is None or (value <= self.high if self.closed in ("both", "right") else value < self.high)
        return lo_ok and hi_ok

    def describe(self) -> str:
        name = "an integer" if self.kind is int else "a number"
        lo_br = "[" if self.closed in ("both", "left") else "("
        hi_br = "]" if self.closed in ("both", "right") else ")"
        if self.low is not None and self.high is not None:
            return f"{name} in {lo_br}{self.low:g}, {self.high:g}{hi_br}"
        if self.low is not None:
            return f"{name} {'>=' if lo_br == '[' else '>'} {self.low:g}"
        if self.high is not None:
            return f"{name} {'<=' if hi_br == ']' else '<'} {self.high:g}"
        return name


@dataclass(frozen=True)
class Options:
    """One of a fixed set of values."""

    values: tuple[Any, ...]

    def accepts(self, value: Any) -> bool:
        return any(value == v and type(value) is type(v) for v in self.values)

    def describe(self) -> str:
        return "one of " + ", ".join(repr(v) for v in self.values)


@dataclass(frozen=True)
class Check:
    """Any predicate, with the words that describe what it accepts."""

    predicate: Callable[[Any], bool]
    description: str

    def accepts(self, value: Any) -> bool:
        try:
            return bool(self.predicate(value))
        except (TypeError, ValueError):
            return False

    def describe(self) -> str:
        return self.description


@dataclass(frozen=True)
class OfType:
    """An instance of ``kind`` (``bool``, ``str``...)."""

    kind: type

    def accepts(self, value: Any) -> bool:
        if self.kind is not bool and isinstance(value, bool):
            return False
        return isinstance(value, self.kind)

    def describe(self) -> str:
        return {bool: "true or false", str: "a string"}.get(self.kind, f"a {self.kind.__name__}")


Constraint = Interval | Options | Check | OfType


def validate_params(owner: str, params: Mapping[str, Any], constraints: Mapping[str, Constraint]) -> None:
    """Check every parameter that has a constraint.

    Raises
    ------
    TopolocError
        ``"<owner>: <name> must be <description>, got <value>"`` for the first
        parameter that breaks its constraint.
    """
    for key, rule in constraints.items():
        if key not in params:
            continue
        value = params[key]
        if not rule.accepts(value):
            raise TopolocError(f"{owner}: {key} must be {rule.describe()}, got {value!r}")


def keyword_defaults(cls: type) -> dict[str, Any]:
    """The keyword-only parameters of ``cls.__init__`` and their defaults."""
    sig = inspect.signature(cls.__init__)  # type: ignore[misc]
    return {p.name: p.default for p in sig.parameters.values() if p.kind is p.KEYWORD_ONLY}


def convert_param(owner: str, cls: type, key: str, value: str) -> Any:
    """Convert a ``--param KEY=VALUE`` string to the type of the parameter's default.

    Raises
    ------
    TopolocError
        For a parameter ``cls`` does not have, or a value of the wrong type.
    """
    defaults = keyword_defaults(cls)
    if key not in defaults:
        raise TopolocError(f"method {owner!r} has no parameter {key!r} (parameters: {', '.join(defaults)})")
    default = defaults[key]
    try:
        if isinstance(default, bool):
            if value.lower() in {"1", "true", "yes", "on"}:
                return True
            if value.lower() in {"0", "false", "no", "off"}:
                return False
            raise ValueError(value)
        if isinstance(default, int):
            return int(value)
        if isinstance(default, float):
            return float(value)
        if default is None:
            for conv in (int, float):
                try:
                    return conv(value)
                except ValueError:
                    pass
            return None if value.lower() == "none" else value
    except ValueError:
        raise TopolocError(
            f"parameter {key}={value!r} of method {owner!r} should be {type(default).__name__}"
        ) from None
    return value
