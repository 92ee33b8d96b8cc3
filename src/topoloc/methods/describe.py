"""Each method's parameters explained, from the numpy-style docstring of its class (``topoloc methods NAME``)."""

from __future__ import annotations

import inspect
import re
from dataclasses import dataclass
from typing import Any

from topoloc._params import keyword_defaults
from topoloc.methods import get_method

_HEADING = re.compile(r"^(\w[\w ]*)\n-{3,}$", re.M)
# Sphinx roles: :func:`~a.b.name` -> name, :class:`text <target>` -> text, :mod:`a.b` -> a.b.
_ROLE = re.compile(r":[\w:]+:`(~?)([^`<]*?)\s*(?:<[^`>]*>)?`")
# reST inline literals, emphasis and default roles: ``x`` / *x* / `x` -> x.
_LITERAL = re.compile(r"``(.+?)``|(?<![\w*])\*(\S(?:.*?\S)?)\*(?![\w*])|`([^`]+)`")


def plain_text(text: str) -> str:
    """A docstring fragment as plain text for a terminal: Sphinx roles and reST markup reduced to their words.

    ``:func:`~topoloc.a.b``` becomes ``b`` (the ``~`` form shows the last name,
    as Sphinx does), ``:class:`Name <target>``` its text, and double back-quoted
    literals and ``*emphasis*`` their content.
    """

    def role(m: re.Match[str]) -> str:
        target = m.group(2)
        return target.rsplit(".", 1)[-1] if m.group(1) else target

    text = _ROLE.sub(role, text)
    return _LITERAL.sub(lambda m: next(g for g in m.groups() if g is not None), text)


@dataclass(frozen=True)
class ParameterDoc:
    """One constructor parameter: name, default, declared type and explanation (empty when undocumented).

    The texts are the docstring's (reST); :func:`plain_text` reads them in a terminal.
    """

    name: str
    default: Any
    type: str
    text: str


def _sections(doc: str) -> dict[str, str]:
    """``{heading: body}`` of a numpy-style docstring; the text before the first heading under ``""``."""
    out: dict[str, str] = {}
    marks = list(_HEADING.finditer(doc))
    out[""] = doc[: marks[0].start()].strip() if marks else doc.strip()
    for i, m in enumerate(marks):
        end = marks[i + 1].start() if i + 1 < len(marks) else len(doc)
        out[m.group(1).strip()] = doc[m.end():end].strip("\n")
    return out


def _parameter_entries(body: str) -> dict[str, tuple[str, str]]:
    """``{name: (type, text)}`` of a Parameters section; ``a, b : int`` documents both."""
    out: dict[str, tuple[str, str]] = {}
    names: list[str] = []
    kind = ""
    lines: list[str] = []

    def flush() -> None:
        text = " ".join(" ".join(lines).split())
        for n in names:
            out[n] = (kind, text)

    for line in body.splitlines():
        if line and not line[0].isspace():
            flush()
            head, _, kind = line.partition(" : ")
            names = [n.strip() for n in head.split(",") if n.strip()]
            kind, lines = kind.strip(), []
        else:
            lines.append(line.strip())
    flush()
    return out


def describe_method(name: str) -> tuple[str, list[ParameterDoc]]:
    """The summary of method ``name`` and its keyword parameters with defaults and explanations.

    Raises
    ------
    TopolocError
        For an unknown method (from the registry).
    """
    cls = get_method(name)
    sections = _sections(inspect.getdoc(cls) or "")
    summary = sections[""].split("\n\n")[0].replace("\n", " ")
    # A subclass documents its own parameters; those it inherits are documented by its bases.
    entries: dict[str, tuple[str, str]] = {}
    for klass in cls.__mro__:
        doc = klass.__dict__.get("__doc__")
        if doc:
            for k, v in _parameter_entries(_sections(inspect.cleandoc(doc)).get("Parameters", "")).items():
                entries.setdefault(k, v)
    params = [ParameterDoc(k, v, *entries.get(k, ("", ""))) for k, v in keyword_defaults(cls).items()]
    return summary, params
