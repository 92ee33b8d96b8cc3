"""Declarative parameter constraints, checked in one place (scikit-learn's ``_parameter_constraints``).

A class lists, for each keyword-only constructor parameter, what values it
accepts; :func:`validate_params` checks them all and raises one
:class:`~topoloc.errors.TopolocError` with a one-line message naming the
owner, the parameter, what it should be and what it got.  Methods call it at
the start of ``fit`` (parameters may be changed by ``set_params`` in between,
as in scikit-learn), and :func:`convert_param` turns the strings of
``--param KEY=VALUE`` into the type of the parameter's default.

:class:`Configurable` is the one way a class declares and checks its
parameters: recognisers, the vocabulary, the feature settings (a frozen
dataclass that validates in ``__post_init__``) and the models of the algorithm
packages all inherit it, so every bad parameter reads the same:
``"<owner>: <name> must be <what>, got <value>"``.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Self

from topoloc.errors import ParameterError, TopolocError


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
        # numbers.Real/Integral also admit NumPy scalars (np.int64 is no int), which
        # models of the algorithm packages are often given; NumPy's bool is no Real.
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            return False
        if not isinstance(value, numbers.Integral) and math.isnan(value):
            return False
        if self.kind is int and not (isinstance(value, numbers.Integral) or float(value).is_integer()):
            return False
        x: Any = value
        lo_ok = self.low is None or (x >= self.low if self.closed in ("both", "left") else x > self.low)
        hi_ok = self.high is None or (x <= self.high if self.closed in ("both", "right") else x < self.high)
        return bool(lo_ok and hi_ok)

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
    """One of a fixed set of values.

    ``unknown`` names what a value is (``"feature method"``) where the error
    should start ``unknown <unknown> <value>``, the wording users have seen.
    """

    values: tuple[Any, ...]
    unknown: str = ""

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
            if isinstance(rule, Options) and rule.unknown:
                raise ParameterError(key, f"must be {rule.describe()}: unknown {rule.unknown} {value!r}", owner=owner)
            raise param_error(owner, key, rule.describe(), value)


def param_error(owner: str, name: str, expected: str, value: Any) -> ParameterError:
    """The one-line error of a parameter: ``"<owner>: <name> must be <expected>, got <value>"``.

    Also for the few rules that compare two parameters (``sidewalk_m`` against
    ``street_width_m``), so that they read like the rest.  A
    :class:`~topoloc.errors.ParameterError` naming ``name``: the command line
    names the flag a value came from instead (``--max-features``, not
    ``max_features``, issue #49).
    """
    return ParameterError(name, f"must be {expected}, got {value!r}", owner=owner)


def unknown_param_error(owner: str, key: str, names: Sequence[str],
                        renamed: Mapping[str, str] | None = None) -> TopolocError:
    """``"<owner> has no parameter <key> (parameters: ...)"``, or the new name of a renamed one."""
    if renamed and key in renamed:
        return TopolocError(f"{owner} has no parameter {key!r}: it is now called {renamed[key]!r}")
    return TopolocError(f"{owner} has no parameter {key!r} (parameters: {', '.join(names)})")


def removed_param_error(owner: str, key: str, instead: str) -> TopolocError:
    """``"<owner> has no parameter <key> any more: <instead>"``, for a parameter that was removed."""
    return TopolocError(f"{owner} has no parameter {key!r} any more: {instead}")


def rename_params(params: Mapping[str, Any], renamed: Mapping[str, str]) -> dict[str, Any]:
    """``params`` with old names replaced by their new ones (what files written before a rename hold).

    A new name given as well wins over the old one.
    """
    out: dict[str, Any] = {}
    for key, value in params.items():
        if key in renamed:
            if renamed[key] not in params:
                out[renamed[key]] = value
        else:
            out[key] = value
    return out


class Configurable:
    """Parameters declared once and checked by :func:`validate_params`.

    A subclass lists its parameters as the keyword-only arguments of
    ``__init__`` (or the fields of a dataclass) and what each accepts in
    :attr:`parameter_constraints`; it gets ``get_params``, ``set_params`` and
    ``validate_params``.  It calls ``self.validate_params()`` where its
    parameters must hold (a model's ``__init__``, a dataclass's
    ``__post_init__``; a recogniser at the start of ``fit``).
    """

    #: What each parameter accepts (see the constraint classes above).
    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {}
    #: Old parameter name -> new name.  The old name is refused with a one-line
    #: error naming the new one; files that stored it are read through
    #: :meth:`upgrade_params`.
    renamed_params: ClassVar[Mapping[str, str]] = {}
    #: Parameter that no longer exists -> what to use instead.  It is refused with a
    #: one-line error saying so; files that stored it are read without it
    #: (:meth:`upgrade_params`).
    removed_params: ClassVar[Mapping[str, str]] = {}
    #: Whether ``set_params`` checks at once (and leaves the object unchanged on
    #: an error) instead of at the next use, as scikit-learn's estimators do.
    validate_on_set: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if (cls.renamed_params or cls.removed_params) and "__init__" in vars(cls):
            cls.__init__ = _refusing_renamed(cls.__init__, cls)  # type: ignore[method-assign]

    @classmethod
    def param_owner(cls) -> str:
        """The name that starts this class's parameter errors (default: the class name)."""
        return cls.__name__

    @classmethod
    def _unknown_owner(cls) -> str:
        return cls.param_owner()

    @classmethod
    def param_names(cls) -> list[str]:
        """Names of the parameters: keyword-only ``__init__`` arguments, or a dataclass's init fields."""
        if dataclasses.is_dataclass(cls):
            return [f.name for f in dataclasses.fields(cls) if f.init]
        return list(keyword_defaults(cls))

    @classmethod
    def upgrade_params(cls, params: Mapping[str, Any]) -> dict[str, Any]:
        """Parameters as stored by an older version, under today's names (:attr:`renamed_params`)."""
        kept = {k: v for k, v in params.items() if k not in cls.removed_params}
        return rename_params(kept, cls.renamed_params)

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The parameters and their current values."""
        return {k: getattr(self, k) for k in self.param_names()}

    def set_params(self, **params: Any) -> Self:
        """Set parameters by name and return self.

        Raises
        ------
        TopolocError
            For a name that is not a parameter (or an old name, with the new
            one), or on a frozen dataclass; with :attr:`validate_on_set`, for a
            value that breaks its constraint, leaving every parameter as it was.
        """
        if dataclasses.is_dataclass(self) and type(self).__dataclass_params__.frozen:
            # Frozen settings key caches and files: changing them in place would break that.
            raise TopolocError(f"{self.param_owner()} settings cannot be changed: make new ones with "
                               "dataclasses.replace")
        names = self.param_names()
        for key in params:
            if key in self.removed_params:
                raise removed_param_error(self._unknown_owner(), key, self.removed_params[key])
            if key not in names:
                raise unknown_param_error(self._unknown_owner(), key, sorted(names), self.renamed_params)
        old = {k: getattr(self, k) for k in params}
        for key, value in params.items():
            setattr(self, key, value)
        if self.validate_on_set:
            try:
                self.validate_params()
            except TopolocError:
                for key, value in old.items():
                    setattr(self, key, value)
                raise
        return self

    def validate_params(self) -> None:
        """Check every parameter against :attr:`parameter_constraints` (one-line TopolocError)."""
        validate_params(self.param_owner(), self.get_params(), self.parameter_constraints)


def _refusing_renamed(init: Callable[..., None], cls: type[Configurable]) -> Callable[..., None]:
    """``init`` that answers an old parameter name with its new one instead of Python's TypeError."""
    renamed = cls.renamed_params
    removed = cls.removed_params

    @functools.wraps(init)
    def wrapper(self: Any, *args: Any, **kwargs: Any) -> None:
        for key in kwargs:
            if key in removed:
                raise removed_param_error(type(self)._unknown_owner(), key, removed[key])
            if key in renamed:
                raise unknown_param_error(type(self)._unknown_owner(), key, (), renamed)
        init(self, *args, **kwargs)

    return wrapper


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
    removed = getattr(cls, "removed_params", {})
    if key in removed:
        raise removed_param_error(f"method {owner!r}", key, removed[key])
    if key not in defaults:
        raise unknown_param_error(f"method {owner!r}", key, list(defaults), getattr(cls, "renamed_params", None))
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
