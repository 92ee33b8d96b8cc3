"""The typer application and what every command shares: one-line errors, common options, conventional usage.

Commands register on :data:`app` from :mod:`topoloc.cli.main` and :mod:`topoloc.cli.maps`
(which both import this module, never each other).

The command line follows the conventions a user expects of a Unix tool (issue #49): ``-h`` and
``--help`` everywhere, ``-V``/``--version``, ``-q`` and ``-v`` both before and after the command
word, what a command needs shown in its usage line and marked in its help, and one error style
for every error, the command line's own usage errors included: one line
``topoloc: error: ...`` on standard error, exit status 2.
"""

from __future__ import annotations

import copy
import errno
import functools
import logging
import os
import sys
from collections.abc import Callable, Sequence
from typing import Annotated, Any, TypeVar

import typer
import typer.core

# typer >= 0.29 carries its own copy of click: its usage errors are these (pyproject pins the version).
from typer._click.exceptions import ClickException, NoArgsIsHelpError

from topoloc.errors import ParameterError, TopolocError

#: ``-h`` beside ``--help`` on every command (click gives the context's setting to every subcommand).
CONTEXT_SETTINGS = {"help_option_names": ["-h", "--help"]}


class TopolocCommand(typer.core.TyperCommand):
    """A command whose usage line names what it needs, in capitals (``MAP_FILE INPUTS... --out FILE``).

    ``needed`` names the parameters a run cannot do without (python names:
    ``"map_file"``, ``"out"``) or gives a group of alternatives verbatim
    (``"(--map PATH... --method NAME | --map-file FILE)"``).  Such a value may
    also come from ``--config``, so click does not require it; the usage line
    shows it without brackets and its help says ``[required]``.
    """

    needed: tuple[str, ...] = ()

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        configurable = any(p.name == "config" for p in self.params)
        for p in self.params:
            if p.name in self.needed and p.param_type_name == "option":
                text = getattr(p, "help", None) or ""
                p.help = f"{text} [required{', or set in --config' if configurable else ''}]".strip()  # type: ignore[attr-defined]

    def collect_usage_pieces(self, ctx: Any) -> list[str]:
        pieces = [self.options_metavar] if self.options_metavar else []
        named = {p.name: p for p in self.params}
        for p in self.params:
            if p.param_type_name == "argument":
                pieces.append(_argument_usage(p, needed=bool(p.required or p.name in self.needed)))
        for item in self.needed:
            one = named.get(item)
            if one is None:
                pieces.append(item)  # a group of alternatives, as written
            elif one.param_type_name == "option":
                pieces.append(_option_usage(one, ctx))
        # Options click itself requires (no default) are needed too.
        pieces += [_option_usage(p, ctx) for p in self.params
                   if p.param_type_name == "option" and p.required and p.name not in self.needed]
        return pieces


def _argument_usage(p: Any, *, needed: bool) -> str:
    name = p.metavar or (p.name or "").upper()
    name = name if needed else f"[{name}]"
    return name + ("..." if p.nargs != 1 else "")


def _option_usage(p: Any, ctx: typer.Context) -> str:
    # The value as the help shows it (``--out <path>``).
    flag = max(p.opts, key=len)
    value = "" if getattr(p, "is_flag", False) else " " + (p.metavar or p.display_type(ctx))
    return flag + value + ("..." if getattr(p, "multiple", False) else "")


def needs(*names: str) -> type[TopolocCommand]:
    """The command class of a command that needs ``names`` (:class:`TopolocCommand`), for ``@app.command(cls=...)``."""
    return type("TopolocCommand", (TopolocCommand,), {"needed": names})


class TopolocGroup(typer.core.TyperGroup):
    """A group whose commands all take ``-q`` and ``-v``, and whose errors are all one line ``topoloc: error: ...``.

    Click prints its own usage errors (a missing option, an unknown flag, a value
    of the wrong type) as ``Usage: ...`` and ``Error: ...`` lines; :meth:`main`
    gives them the form every other error has, so that a script or a user reads
    one style.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        for cmd in self.commands.values():
            _add_shared_options(cmd)

    def main(self, args: Sequence[str] | None = None, prog_name: str | None = None, complete_var: str | None = None,
             standalone_mode: bool = True, windows_expand_args: bool = True, **extra: Any) -> Any:
        try:
            rv = super().main(args=args, prog_name=prog_name, complete_var=complete_var, standalone_mode=False,
                              windows_expand_args=windows_expand_args, **extra)
        except NoArgsIsHelpError as exc:
            if not standalone_mode:
                raise
            exc.show()  # the help of a group named alone: what it offers, not an error to read
            sys.exit(exc.exit_code)
        except ClickException as exc:
            if not standalone_mode:
                raise
            print(f"topoloc: error: {usage_error_line(exc)}", file=sys.stderr)
            sys.exit(2)
        except typer.Abort:  # end of input where a value was asked for: no command of topoloc asks, still one line
            if not standalone_mode:
                raise
            print("topoloc: error: aborted", file=sys.stderr)
            sys.exit(2)
        if standalone_mode:
            sys.exit(rv if isinstance(rv, int) else 0)
        return rv


def usage_error_line(exc: ClickException) -> str:
    """Click's message of a usage error as one line, with where to look: ``missing option '--query' (see ...)``."""
    text = " ".join(exc.format_message().split())
    text = text[:1].lower() + text[1:] if text[:2] != text[:2].upper() else text
    ctx = getattr(exc, "ctx", None)
    return f"{text.rstrip('.')} (see '{ctx.command_path} --help')" if ctx is not None else text.rstrip(".")


def command_group(**kwargs: Any) -> typer.Typer:
    """A typer application (the top one or a group of subcommands) with plain help.

    Plain help, not rich's panels: flags show as flags (``-q, --quiet``) rather
    than with a type (``--quiet -q <bool>``), text such as ``topoloc[ros]`` is
    printed as written (rich markup would take ``[ros]`` for a style), and the
    help reads the same in a terminal and a file.
    """
    return typer.Typer(rich_markup_mode=None, no_args_is_help=True, cls=TopolocGroup, add_completion=False,
                       context_settings=CONTEXT_SETTINGS, **kwargs)


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
            from topoloc.cli.options import parameter_message

            raise _fail(parameter_message(exc)) from None
        except TopolocError as exc:
            raise _fail(str(exc)) from None
        except KeyboardInterrupt:
            raise _fail("interrupted") from None
        except OSError as exc:
            if exc.errno == errno.EPIPE:  # `topoloc ... | head`: the reader has all it wanted; said nowhere
                _quiet_broken_pipe()
                raise typer.Exit(code=1) from None
            # The last resort for a file the library did not name (a full disk, a read-only folder):
            # one line rather than a traceback; the writers that can name the file raise WriteError.
            raise _fail(os_error_line(exc)) from None

    return wrapper  # type: ignore[return-value]


def _quiet_broken_pipe() -> None:
    # Python would print "Exception ignored ... BrokenPipeError" flushing the closed stream at exit.
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # a stream without a descriptor (a test runner's)
        pass


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


def _verbose(value: bool) -> None:
    # Before the command or after it: the log level of this process (basicConfig ran in the app's callback).
    if value:
        logging.getLogger().setLevel(logging.INFO)


def _quiet(value: bool) -> None:
    if value:
        from topoloc.cli import progress

        progress.QUIET = True


VerboseOption = Annotated[bool, typer.Option("--verbose", "-v", help="Log progress details.", callback=_verbose)]
QuietEverywhereOption = Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars.", callback=_quiet)]


def _shared_params() -> dict[str, Any]:
    """``-v`` and ``-q`` as typer builds them, to give to every command that does not declare its own."""
    holder = typer.Typer(rich_markup_mode=None)

    @holder.command()
    def shared(verbose: VerboseOption = False, quiet: QuietEverywhereOption = False) -> None:  # pragma: no cover
        """Not a command: the shape of the shared options."""

    return {p.name: p for p in typer.main.get_command(holder).params}


_SHARED: dict[str, Any] = {}


def _add_shared_options(cmd: Any) -> None:
    """Give ``cmd`` ``-v/--verbose`` and ``-q/--quiet`` where it lacks them (taking no value of its own)."""
    if not _SHARED:
        _SHARED.update(_shared_params())
    have = {o for p in cmd.params for o in getattr(p, "opts", ())}
    for shared in _SHARED.values():
        if not set(shared.opts) & have:
            extra = copy.copy(shared)
            extra.expose_value = False  # the command's function does not take it: the callback does the work
            cmd.params.append(extra)


app = command_group(
    name="topoloc",
    help="Appearance-based localisation: evaluate place-recognition methods on image traverses.",
    pretty_exceptions_enable=False,
)
vocab_app = command_group(help="Visual vocabularies.")
app.add_typer(vocab_app, name="vocab")
bench_app = command_group(help="Speed benchmarks on synthetic data of realistic size.")
app.add_typer(bench_app, name="bench")


@app.callback()
def _setup(
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log progress details.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars (as -q after the command).")] = False,
    version: Annotated[bool, typer.Option(
        "--version", "-V", help="Print the version and exit.", callback=_print_version, is_eager=True)] = False,
    device: Annotated[str | None, typer.Option(
        "--device", help="Where learned features (--features xfeat) are extracted: cpu (default), cuda, or auto "
                         "(CUDA where onnxruntime-gpu or PyTorch sees one). Sets TOPOLOC_DEVICE for this run and its "
                         "local workers.",
    )] = None,
) -> None:
    from topoloc.cli import progress
    from topoloc.cli.progress import LogHandler

    progress.QUIET = quiet  # each run starts from what was typed before the command (a test runs many)
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
    # basicConfig sets the level only once per process; a second command in the same process (tests) sets it too.
    logging.getLogger().setLevel(logging.INFO if verbose else logging.WARNING)
