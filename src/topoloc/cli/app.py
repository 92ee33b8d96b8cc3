"""The typer application and what every command shares: one-line errors, common options.

Commands register on :data:`app` from :mod:`topoloc.cli.main` and :mod:`topoloc.cli.maps`
(which both import this module, never each other).
"""

from __future__ import annotations

import functools
import logging
import sys
from collections.abc import Callable
from typing import Annotated, Any, TypeVar

import typer

from topoloc.cli.progress import console
from topoloc.errors import TopolocError

app = typer.Typer(
    name="topoloc",
    help="Appearance-based localisation: evaluate place-recognition methods on image traverses.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
vocab_app = typer.Typer(help="Visual vocabularies.", no_args_is_help=True)
app.add_typer(vocab_app, name="vocab")
bench_app = typer.Typer(help="Speed benchmarks on synthetic data of realistic size.", no_args_is_help=True)
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
        except TopolocError as exc:
            raise _fail(str(exc)) from None
        except KeyboardInterrupt:
            raise _fail("interrupted") from None

    return wrapper  # type: ignore[return-value]


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
) -> None:
    from rich.logging import RichHandler

    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING, format="%(message)s",
        handlers=[RichHandler(console=console, show_path=False)],
    )


# Feature options shared by every command that extracts features.
FeaturesOption = Annotated[str, typer.Option(help="Local features: sift, rootsift, orb, akaze.")]
MaxFeaturesOption = Annotated[int, typer.Option(help="Cap on features per image.")]
MaxSideAutoOption = Annotated[str, typer.Option(
    help="Downscale images to this longer side before extraction; 'auto' = the smallest size among "
         "the traverses when their sizes differ, 0 = never.")]
MaxSideOption = Annotated[int, typer.Option(help="Downscale images to this longer side first (0 = never).")]
# Where per-block work runs (topoloc.cluster); shared by every command that extracts features.
SchedulerOption = Annotated[str | None, typer.Option(
    "--scheduler", help="Dask scheduler address (tcp://host:8786): feature extraction and quantisation run on its "
                        "workers, which must see the cache folder at the same path; default $TOPOLOC_SCHEDULER, "
                        "else this machine's threads. Needs pip install 'topoloc[distributed]'.")]
SchedulerTimeoutOption = Annotated[float | None, typer.Option(
    "--scheduler-timeout", help="Seconds to wait for the scheduler and a worker before a one-line error "
                                "(default $TOPOLOC_SCHEDULER_TIMEOUT, else 10).")]
PreprocessOption = Annotated[str, typer.Option(
    help="Photometric preprocessing: auto (default; CLAHE weighted per image by how far its "
         "histogram is from uniform, so dark night frames are equalised and well-exposed ones barely "
         "touched), none, clahe, equalize.")]


def open_executor(scheduler: str | None, timeout: float | None) -> Any:
    """The run's executor (:func:`topoloc.cluster.connect`): a Dask client, or this machine's threads."""
    from topoloc.cluster import connect

    if timeout is not None and not timeout > 0:
        raise TopolocError(f"--scheduler-timeout must be a positive number of seconds, got {timeout}")
    return connect(scheduler, timeout_s=timeout)


def _parse_params(items: list[str]) -> dict[str, str]:
    out = {}
    for it in items:
        if "=" not in it:
            raise TopolocError(f"--param {it!r} is not KEY=VALUE")
        k, v = it.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def _sequence_length(n: int | None) -> int:
    """``--sequence N``: absent means off; a given N must be >= 1 (0 would silently mean "off")."""
    if n is None:
        return 0
    if n < 1:
        raise TopolocError(f"--sequence must be >= 1 (leave it out to match single images), got {n}")
    return n
