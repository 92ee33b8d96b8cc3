"""The typer application and what every command shares: one-line errors, common options.

Commands register on :data:`app` from :mod:`topoloc.cli.main` and :mod:`topoloc.cli.maps`
(which both import this module, never each other).
"""

from __future__ import annotations

import errno
import functools
import logging
import os
import sys
from collections.abc import Callable
from typing import Annotated, Any, TypeVar

import typer

from topoloc.errors import ParameterError, TopolocError


def command_group(**kwargs: Any) -> typer.Typer:
    """A typer application (the top one or a group of subcommands) with plain help.

    Plain help, not rich's panels: flags show as flags (``-q, --quiet``) rather
    than with a type (``--quiet -q <bool>``), text such as ``topoloc[ros]`` is
    printed as written (rich markup would take ``[ros]`` for a style), and the
    help reads the same in a terminal and a file.
    """
    return typer.Typer(rich_markup_mode=None, no_args_is_help=True, **kwargs)


app = command_group(
    name="topoloc",
    help="Appearance-based localisation: evaluate place-recognition methods on image traverses.",
    add_completion=False,
    pretty_exceptions_enable=False,
)
vocab_app = command_group(help="Visual vocabularies.")
app.add_typer(vocab_app, name="vocab")
bench_app = command_group(help="Speed benchmarks on synthetic data of realistic size.")
app.add_typer(bench_app, name="bench")

F = TypeVar("F", bound=Callable[..., Any])


def _fail(message: str) -> typer.Exit:
    # One line on stderr, non-zero exit: the contract for bad input.
    print(f"topoloc: error: {message}", file=sys.stderr)
    return typer.Exit(code=2)


def handle_errors(fn: F) -> F:
    """Turn :class:`TopolocError` into a one-line message and exit status 2."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except ParameterError as exc:
            from topoloc.cli.options import flag_of

            raise _fail(f"{flag_of(exc.param)} {exc.detail}") from None
        except TopolocError as exc:
            raise _fail(str(exc)) from None
        except KeyboardInterrupt:
            raise _fail("interrupted") from None
        except OSError as exc:
            # The last resort for a file the library did not name (a full disk, a read-only folder):
            # one line rather than a traceback; the writers that can name the file raise WriteError.
            raise _fail(os_error_line(exc)) from None

    return wrapper  # type: ignore[return-value]


_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG})


def os_error_line(exc: OSError) -> str:
    """``cannot write|read or write FILE: REASON`` for an :class:`OSError` that reached the command line."""
    verb = "write" if exc.errno in _WRITE_ERRNOS else "read or write"
    reason = exc.strerror or str(exc) or type(exc).__name__
    name = exc.filename2 if exc.filename2 is not None else exc.filename
    return f"cannot {verb} {name}: {reason}" if name is not None else f"cannot {verb} a file: {reason}"


def _print_version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        try:
            typer.echo(f"topoloc {version('topoloc')}")
        except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
            typer.echo("topoloc (not installed)")
        raise typer.Exit()


@app.callback()
def _setup(
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log progress details.")] = False,
    version: Annotated[bool, typer.Option(
        "--version", help="Print the version and exit.", callback=_print_version, is_eager=True)] = False,
    device: Annotated[str | None, typer.Option(
        "--device", help="Where learned features (--features xfeat) are extracted: cpu (default), cuda, or auto "
                         "(CUDA where onnxruntime-gpu or PyTorch sees one). Sets TOPOLOC_DEVICE for this run and its "
                         "local workers.",
    )] = None,
) -> None:
    from topoloc.cli.progress import LogHandler

    if device is not None:
        from topoloc.features.learned import parse_device

        try:
            name = parse_device(device)
        except TopolocError as exc:
            raise _fail(f"--{exc}") from None
        # An environment variable, not a setting passed down: Dask workers started from here inherit it.
        os.environ["TOPOLOC_DEVICE"] = name

    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(message)s",
                        handlers=[LogHandler()])
