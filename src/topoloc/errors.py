"""Exceptions raised for bad input.

A :class:`TopolocError` carries a single-line message that names the problem and
the file; the command-line interface prints it and exits non-zero, so library
code raises it instead of printing.
"""

from __future__ import annotations

from pathlib import Path


class TopolocError(Exception):
    """Bad input or state that the user can fix (one-line message)."""


class NotFittedError(TopolocError, AttributeError):
    """A method or model was used before ``fit``."""


def input_error(problem: str, path: str | Path | None = None) -> TopolocError:
    """Build a one-line :class:`TopolocError` naming ``problem`` and ``path``."""
    msg = problem if path is None else f"{problem}: {path}"
    return TopolocError(" ".join(msg.split()))
