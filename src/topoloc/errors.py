"""Exceptions raised for bad input.

A :class:`TopolocError` carries a single-line message that names the problem and
the file; the command-line interface prints it and exits non-zero, so library
code raises it instead of printing.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any


class TopolocError(Exception):
    """Bad input or state that the user can fix (one-line message)."""


class NotFittedError(TopolocError, AttributeError):
    """A method or model was used before ``fit``."""


class ParameterError(TopolocError):
    """A bad value of one named parameter of a run (``features.max_side``, ``sequence.length``).

    The library names the parameter; the command line names the flag it came
    from instead (``topoloc.cli.options``), so one message serves both.

    Parameters
    ----------
    param : str
        Dotted name of the parameter in the run specification (``topoloc.spec``).
    detail : str
        What is wrong, phrased to follow the name: ``"must be >= 1, got 0"``.
        Another parameter it mentions is written ``{name}`` and listed in ``refs``,
        so that the command line can name that one by its flag too (never a
        field name the user did not type, issue #49).
    refs : tuple of str
        The dotted names of the parameters ``detail`` mentions as ``{name}``.
    owner : str
        What the parameter belongs to where it is not a setting of a run
        (``"features"``, ``"seqslam"``): the message then reads
        ``"<owner>: <param> <detail>"``.
    """

    def __init__(self, param: str, detail: str, refs: tuple[str, ...] = (), *, owner: str = "") -> None:
        self.param = param
        self.refs = tuple(refs)
        self.owner = owner
        #: ``detail`` as given, other parameters still ``{name}``.
        self.template = " ".join(detail.split())
        super().__init__(f"{owner}: {param} {self.detail}" if owner else f"{param} {self.detail}")

    @property
    def detail(self) -> str:
        """What is wrong, other parameters named by their names in the specification."""
        return self.render(lambda name: name)

    def render(self, name_of: Callable[[str], str]) -> str:
        """``detail`` with each parameter of ``refs`` named by ``name_of`` (the command line: its flag)."""
        text = self.template
        for ref in self.refs:
            text = text.replace("{" + ref + "}", name_of(ref))
        return text

    def __reduce__(self) -> tuple[Any, ...]:  # a Dask task's error travels back pickled
        return (_parameter_error, (type(self), self.param, self.template, self.refs, self.owner))


class WriteError(TopolocError, OSError):
    """A file that could not be written: disk full, quota exceeded, read-only file system...

    Both a :class:`TopolocError` (the command line prints its one line, exit 2)
    and an :class:`OSError` with the original ``errno``, so code that tolerates
    an unwritable cache (``except OSError``) still does.

    Parameters
    ----------
    errno : int or None
        The ``errno`` of the failed call (``errno.ENOSPC``...).
    strerror : str or None
        Its text (``"No space left on device"``).
    filename : str
        The file being written (the destination, not a temporary name).
    """

    def __init__(self, errno: int | None, strerror: str | None, filename: str) -> None:
        # OSError's own three arguments: the error pickles (a Dask task's error travels back) and keeps errno.
        OSError.__init__(self, errno, strerror, filename)

    @classmethod
    def of(cls, path: str | Path, exc: OSError) -> WriteError:
        """The error of writing ``path`` that failed with ``exc``."""
        reason = exc.strerror or str(exc) or type(exc).__name__
        return exc if isinstance(exc, WriteError) else cls(exc.errno, reason, str(path))

    def __str__(self) -> str:
        return f"cannot write {self.filename}: {self.strerror}"


def _parameter_error(cls: type[ParameterError], param: str, template: str, refs: tuple[str, ...],
                     owner: str) -> ParameterError:
    return cls(param, template, refs, owner=owner)


def input_error(problem: str, path: str | Path | None = None) -> TopolocError:
    """Build a one-line :class:`TopolocError` naming ``problem`` and ``path``."""
    msg = problem if path is None else f"{problem}: {path}"
    return TopolocError(" ".join(msg.split()))
