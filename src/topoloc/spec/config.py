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
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from topoloc.errors import TopolocError, input_error
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
    "confirm": "verification.confirm",
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
            raise TopolocError(f"unknown setting {key!r} for {_label(cls)}{where}; known: {', '.join(fields)}")
        part = PARTS.get(key)
        if part is not None and isinstance(value, Mapping):
            known = {f.name for f in dataclasses.fields(part)}
            extra = sorted(set(value) - known)
            if extra:
                raise TopolocError(f"unknown setting {key}.{extra[0]}{where}; known: "
                                   f"{', '.join(f'{key}.{k}' for k in sorted(known))}")
            default = fields[key].default_factory()  # type: ignore[operator]
            kwargs[key] = dataclasses.replace(default, **value)
        else:
            kwargs[key] = value
    return cls(**kwargs)


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


def load_config(path: str | Path) -> dict[str, Any]:
    """A configuration file's nested settings: TOML, YAML or JSON (``metrics.json``: its ``run.spec``).

    Raises
    ------
    TopolocError
        One line naming the file: missing, unreadable, not a mapping, or of another format.
    """
    path = Path(path)
    if not path.is_file():
        raise input_error("configuration file not found", path)
    suffix = path.suffix.lower()
    try:
        text = path.read_text(encoding="utf-8")
        if suffix == ".toml":
            import tomllib

            data: Any = tomllib.loads(text)
        elif suffix in (".yaml", ".yml"):
            import yaml

            data = yaml.safe_load(text)
        elif suffix == ".json":
            data = json.loads(text)
            if isinstance(data, dict) and isinstance(data.get("run"), dict) and "spec" in data["run"]:
                data = data["run"]["spec"]  # a run's metrics.json: made again from its record
        else:
            raise input_error("configuration file must be .toml, .yaml, .yml or .json", path)
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise input_error(f"configuration file cannot be read ({type(exc).__name__}: {exc})", path) from None
    except Exception as exc:  # yaml.YAMLError without importing yaml where it is not needed
        if type(exc).__module__.startswith("yaml"):
            raise input_error(f"configuration file cannot be read ({type(exc).__name__})", path) from None
        raise
    if not isinstance(data, dict):
        raise input_error("configuration file does not hold a table of settings", path)
    return data


__all__ = [
    "DOTTED_NAMES", "FLAT_NAMES", "load_config", "merge", "nest", "spec_from_dict",
    "spec_from_flat", "spec_to_dict",
]
