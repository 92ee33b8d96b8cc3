"""Run specifications to and from plain data: flat keyword options, nested dicts, configuration files.

* :data:`FLAT_NAMES` is the one table from the flat names a command takes
  (``max_side``, ``vocab_train``, as the command line spells them) to the
  dotted names of the specification (``features.max_side``,
  ``vocabulary.train``); the command line derives its flags from it.
* :func:`spec_from_flat` builds a specification from flat options, as
  ``evaluate(method=..., vocab_train=[...])`` takes them.
* :func:`spec_to_dict` / :func:`spec_from_dict` go to and from the nested
  form that ``metrics.json`` and a map header record.
* :func:`load_config` reads a TOML, YAML or JSON file of that nested form (or
  the ``run.spec`` block of a ``metrics.json``), as kiss-icp's and hloc's
  configurations are read: ``--config FILE``, with flags given on the command
  line overriding it.
"""

from __future__ import annotations

import dataclasses
import json
import reprlib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from topoloc.errors import ParameterError, TopolocError, input_error
from topoloc.spec.parts import PARTS

S = TypeVar("S")

# flat name -> dotted name in a specification; names not listed are fields of the run itself.
FLAT_NAMES: dict[str, str] = {
    "features": "features.method", "max_features": "features.max_features", "max_side": "features.max_side",
    "preprocess": "features.preprocess",
    "vocab": "vocabulary.file", "vocab_train": "vocabulary.train", "vocab_words": "vocabulary.words",
    "seed": "vocabulary.seed",
    "topic": "inputs.topic", "every_s": "inputs.every_s", "every_m": "inputs.every_m",
    "pose_topic": "inputs.pose_topic",
    "tolerance": "ground_truth.tolerance", "tolerance_m": "ground_truth.tolerance_m",
    "ground_truth": "ground_truth.file",
    "sequence": "sequence.length", "sequence_mode": "sequence.mode",
    "verify": "verification.enabled", "verify_candidates": "verification.candidates",
    "confirm": "verification.confirm", "min_support": "verification.min_support",
    "scheduler": "execution.scheduler", "scheduler_timeout": "execution.scheduler_timeout",
    "cache_dir": "execution.cache_dir",
}
DOTTED_NAMES: dict[str, str] = {dotted: flat for flat, dotted in FLAT_NAMES.items()}


def nest(flat: Mapping[str, Any], *, names: Mapping[str, str] | None = None) -> dict[str, Any]:
    """``{"max_side": 640, "method": "bow"}`` -> ``{"features": {"max_side": 640}, "method": "bow"}``.

    ``names`` adds or overrides entries of :data:`FLAT_NAMES` (a command whose
    flag is ``--words`` rather than ``--vocab-words``).
    """
    table = {**FLAT_NAMES, **(names or {})}
    out: dict[str, Any] = {}
    for key, value in flat.items():
        dotted = table.get(key, key)
        head, _, tail = dotted.partition(".")
        if tail:
            out.setdefault(head, {})[tail] = value
        else:
            out[head] = value
    return out


def merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Nested ``base`` with the values of nested ``over`` put in (parts merged key by key)."""
    out: dict[str, Any] = {k: dict(v) if isinstance(v, Mapping) else v for k, v in base.items()}
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = {**out[key], **value}
        else:
            out[key] = value
    return out


def spec_from_dict(cls: type[S], data: Mapping[str, Any], *, source: str | Path | None = None) -> S:
    """The specification ``cls`` from its nested form; an unknown key is a one-line error naming it.

    Parameters
    ----------
    cls : type
        A run specification of :mod:`topoloc.spec.runs` (``EvaluateSpec``, ``MapBuildSpec``...).
    data : mapping
        Fields of ``cls``; the parts as mappings of their own fields.
    source : path, optional
        Named in errors (the configuration file).
    """
    where = f" ({source})" if source is not None else ""
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        if key not in fields:
            raise TopolocError(f"unknown setting {_short(key)} for {_label(cls)}{where}; known: {', '.join(fields)}")
        part = PARTS.get(key)
        if part is not None and isinstance(value, Mapping):
            known = {f.name for f in dataclasses.fields(part)}
            extra = sorted(set(value) - known, key=str)
            if extra:
                raise TopolocError(f"unknown setting {key}.{str(extra[0])[:60]}{where}; known: "
                                   f"{', '.join(f'{key}.{k}' for k in sorted(known))}")
            factory = fields[key].default_factory
            # A part that may be absent (None: decided later, a node's sequence as the map's) starts from its defaults.
            default = factory() if factory is not dataclasses.MISSING else part()
            kwargs[key] = dataclasses.replace(default, **value)
        else:
            kwargs[key] = value
    return cls(**kwargs)


def typed_config(cls: type, data: Mapping[str, Any], *, source: str | Path) -> dict[str, Any]:
    """A configuration file's settings for the specification ``cls``, each checked against its type.

    Names unknown to ``cls`` are left for :func:`spec_from_dict` to refuse;
    a part given as anything but a table, and a value of another type than
    its setting's, are one line naming the setting (as its flag on the command
    line) and the file, as a bad flag is.  Paths come as strings, lists as
    lists (one string for a list of one), floats as integers too.
    """
    where = f" ({source})"
    fields = {f.name for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    out: dict[str, Any] = {}
    for key, value in data.items():
        if key not in fields:
            out[key] = value
            continue
        part = PARTS.get(key)
        if part is None:
            out[key] = _typed(value, hints[key], key, where)
            continue
        if not isinstance(value, Mapping):
            raise ParameterError(key, f"must be a table of settings ({key}.NAME = ...), got {_short(value)}{where}")
        part_hints = typing.get_type_hints(part)
        out[key] = {k: _typed(v, part_hints[k], f"{key}.{k}", where) if k in part_hints else v
                    for k, v in value.items()}
    return out


def _short(value: Any) -> str:
    """A value as an error line shows it: its repr, cut short (a value may be huge)."""
    r = reprlib.Repr()
    r.maxstring, r.maxother, r.maxlist, r.maxdict, r.maxtuple, r.maxlevel = 60, 60, 4, 4, 4, 2
    return r.repr(value)


def _typed(value: Any, hint: Any, param: str, where: str) -> Any:
    """``value`` as the type ``hint`` of setting ``param`` takes it, or one line naming ``param``.

    Files give numbers, strings, lists and tables; a path is a string, a tuple a
    list (or one string), a float an integer too.  Values the flags give pass unchanged.
    """
    if hint is Any:
        return value
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        problems = []
        for arg in (a for a in args if a is not type(None)):
            try:
                return _typed(value, arg, param, where)
            except ParameterError as exc:
                problems.append(exc.detail.split(", got")[0].removeprefix("must be "))
        raise ParameterError(param, f"must be {' or '.join(problems)}, got {_short(value)}{where}")
    if origin is tuple:
        items = [value] if isinstance(value, str | Path) else value
        if not isinstance(items, list | tuple):
            raise ParameterError(param, f"must be a list, got {_short(value)}{where}")
        return tuple(_typed(v, args[0], param, where) for v in items)
    if origin is dict or hint is dict:
        if not isinstance(value, Mapping) or not all(isinstance(k, str) for k in value):
            raise ParameterError(param, f"must be a table of NAME = value, got {_short(value)}{where}")
        return dict(value)
    if hint is Path:
        if isinstance(value, Path) or (isinstance(value, str) and value):
            return Path(value)
        raise ParameterError(param, f"must be a path, got {_short(value)}{where}")
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise ParameterError(param, f"must be true or false, got {_short(value)}{where}")
    if hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ParameterError(param, f"must be a whole number, got {_short(value)}{where}")
    if hint is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
        raise ParameterError(param, f"must be a number, got {_short(value)}{where}")
    if hint is str:
        if isinstance(value, str):
            return value
        raise ParameterError(param, f"must be text, got {_short(value)}{where}")
    return value


def spec_from_flat(cls: type[S], flat: Mapping[str, Any], *, names: Mapping[str, str] | None = None) -> S:
    """The specification ``cls`` from flat options (see :data:`FLAT_NAMES`)."""
    return spec_from_dict(cls, nest(flat, names=names))


def _plain(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    return value


def spec_to_dict(spec: Any) -> dict[str, Any]:
    """The nested form of a specification: JSON-ready (paths as strings), readable by :func:`spec_from_dict`."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(spec):
        value = getattr(spec, f.name)
        out[f.name] = _plain(dataclasses.asdict(value) if dataclasses.is_dataclass(value)
                             and not isinstance(value, type) else value)
    return out


def _label(cls: type) -> str:
    return cls.__name__.removesuffix("Spec")


#: Largest configuration file read (a run's metrics.json is a few kB; docs/results/runs).
CONFIG_MAX_BYTES = 1 << 20
#: Deepest nesting of tables and lists a configuration file may have (a specification has 3 levels).
CONFIG_MAX_DEPTH = 16
#: Most values a configuration file may hold once YAML's aliases are expanded: an alias bomb of a few
#: hundred bytes expands to billions (issue #41), a real configuration to a few hundred.
CONFIG_MAX_VALUES = 100_000

#: Outputs a configuration never names: a run's metrics.json records them, and a new run taking them
#: from it would replace the run it was read from (issue #41).  Name them on the command line.
OUTPUT_FIELDS = ("out", "html", "pairs_out")


def _yaml_load(text: str, path: Path) -> Any:
    """YAML's safe loader, after checking the document's size with its aliases expanded and its depth."""
    import yaml

    nodes = list(yaml.compose_all(text, Loader=yaml.SafeLoader))
    if len(nodes) > 1:
        raise input_error("configuration file holds several YAML documents: give one", path)
    if not nodes:
        return None
    sizes: dict[int, tuple[int, int]] = {}

    def measure(node: Any, depth: int) -> tuple[int, int]:
        """(values when expanded, depth below), each node measured once: aliases share their node."""
        if depth > CONFIG_MAX_DEPTH:
            raise input_error(f"configuration file is nested more than {CONFIG_MAX_DEPTH} levels deep", path)
        if id(node) in sizes:
            return sizes[id(node)]
        children = ([c for pair in node.value for c in pair] if isinstance(node, yaml.MappingNode)
                    else node.value if isinstance(node, yaml.SequenceNode) else [])
        total, deep = 1, 0
        for child in children:
            n, d = measure(child, depth + 1)
            total, deep = total + n, max(deep, d + 1)
        if total > CONFIG_MAX_VALUES:
            raise input_error(f"configuration file expands to more than {CONFIG_MAX_VALUES} values (YAML aliases)",
                              path)
        sizes[id(node)] = (total, deep)
        return total, deep

    measure(nodes[0], 0)
    return yaml.SafeLoader(text).get_single_data()


def _depth(value: Any, path: Path, level: int = 0) -> None:
    if level > CONFIG_MAX_DEPTH:
        raise input_error(f"configuration file is nested more than {CONFIG_MAX_DEPTH} levels deep", path)
    if isinstance(value, Mapping):
        for v in value.values():
            _depth(v, path, level + 1)
    elif isinstance(value, list | tuple):
        for v in value:
            _depth(v, path, level + 1)


def load_config(path: str | Path) -> dict[str, Any]:
    """A configuration file's nested settings: TOML, YAML or JSON (``metrics.json``: its ``run.spec``).

    A configuration file is untrusted input: at most :data:`CONFIG_MAX_BYTES`,
    :data:`CONFIG_MAX_DEPTH` levels deep and (YAML aliases expanded)
    :data:`CONFIG_MAX_VALUES` values; its values are checked against the types of the
    settings by :func:`spec_from_dict`.  A run's ``metrics.json`` gives its
    settings, not its outputs (:data:`OUTPUT_FIELDS`).

    Raises
    ------
    TopolocError
        One line naming the file: missing, unreadable, too large or deep, not a mapping, or of another format.
    """
    path = Path(path)
    if not path.is_file():
        # A named pipe or a device is never opened: reading one would wait, or never end.
        raise input_error("configuration file is not a regular file" if path.exists() else
                          "configuration file not found", path)
    suffix = path.suffix.lower()
    if suffix not in (".toml", ".yaml", ".yml", ".json"):
        raise input_error("configuration file must be .toml, .yaml, .yml or .json", path)
    try:
        with path.open("rb") as fh:
            raw = fh.read(CONFIG_MAX_BYTES + 1)
        if len(raw) > CONFIG_MAX_BYTES:
            raise input_error(f"configuration file is larger than {CONFIG_MAX_BYTES >> 10} KiB", path)
        text = raw.decode("utf-8")
        if suffix == ".toml":
            import tomllib

            data: Any = tomllib.loads(text)
        elif suffix in (".yaml", ".yml"):
            data = _yaml_load(text, path)
        else:
            data = json.loads(text)
            if isinstance(data, dict) and isinstance(data.get("run"), dict) and "spec" in data["run"]:
                data = data["run"]["spec"]  # a run's metrics.json: made again from its record
                if isinstance(data, dict):
                    data = {k: v for k, v in data.items() if k not in OUTPUT_FIELDS}
        _depth(data, path)
    except RecursionError:
        raise input_error(f"configuration file is nested more than {CONFIG_MAX_DEPTH} levels deep", path) from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise input_error(f"configuration file cannot be read ({type(exc).__name__}: {str(exc)[:200]})",
                          path) from None
    except Exception as exc:  # yaml.YAMLError without importing yaml where it is not needed
        if type(exc).__module__.startswith("yaml"):
            raise input_error(f"configuration file cannot be read ({type(exc).__name__})", path) from None
        raise
    if not isinstance(data, dict):
        raise input_error("configuration file does not hold a table of settings", path)
    return data


__all__ = [
    "DOTTED_NAMES", "FLAT_NAMES", "load_config", "merge", "nest", "spec_from_dict",
    "spec_from_flat", "spec_to_dict", "typed_config",
]
