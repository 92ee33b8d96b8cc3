"""Output folders that are either the old run or the new one, whole, and early checks of output paths.

:func:`staged_dir` lets a command write every file of a run into a hidden
sibling folder and then puts it in place with one atomic exchange
(``renameat2(RENAME_EXCHANGE)`` on Linux): a run killed at any moment leaves the
folder as it was before, or as the new run wrote it, never a mixture.  Where
the exchange is not available (another OS, another file system) two renames
are used, and a kill between them leaves the old run in a hidden folder beside
``out``, which the next run removes.  Staging folders carry their writer's
process id, so a run never removes the staging folder of another run still
writing into the same ``out``.

:func:`check_output_dir` and :func:`check_output_file` prove, before any long
work starts, that an output can be written: they create and remove a probe
file where the output will go.

:func:`check_outputs` proves, before any work, that a command's outputs
destroy nothing of the user's: no output is one of the command's inputs (or a
file inside an input folder), a folder replaced whole holds nothing, or an
earlier output of the same command recognised by its marker file (an
``evaluate`` run by its ``metrics.json`` with a ``run`` block), never an input
nor the working folder, and every output is a regular file or a folder, named
within the file system's limits.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import json
import logging
import os
import re
import shutil
import stat
import tempfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from topoloc.errors import WriteError, input_error
from topoloc.io.container import umask
from topoloc.io.lock import TAG_PATTERN, remove_stale, writer_tag
from topoloc.io.paths import is_discard, kind_of, through_link

log = logging.getLogger(__name__)

_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two paths (Linux ``renameat2``); False where unsupported."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    res = fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    return res == 0


def _probe(folder: Path, what: Path) -> None:
    try:
        fd, name = tempfile.mkstemp(prefix=".topoloc-probe-", dir=folder)
        os.close(fd)
        os.unlink(name)
    except OSError as exc:
        raise input_error(f"cannot write the output here ({exc.strerror or type(exc).__name__})", what) from None


def check_output_dir(path: str | Path) -> None:
    """Refuse, before any work, an output folder that is a file or cannot be created or written.

    Raises
    ------
    TopolocError
        One line naming the path.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise input_error("output folder is a file", path)
    existing = path
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise input_error("output folder is inside a file", path)
    # Nothing is created yet (a run refused later leaves no folder): the nearest existing
    # folder must take a new entry, which is what creating the output needs.
    _probe(existing, path)


def check_output_file(path: str | Path) -> None:
    """Refuse, before any work, an output file that is a folder or whose folder cannot be written."""
    path = Path(path)
    if path.is_dir():
        raise input_error("output is a folder, not a file", path)
    if path.exists() and not os.access(path, os.W_OK):
        raise input_error("output file is not writable", path)
    check_output_dir(path.parent if str(path.parent) else Path("."))


@contextlib.contextmanager
def staged_dir(out: str | Path) -> Iterator[Path]:
    """Write a run into a hidden sibling of ``out``, then put it in place whole.

    Yields the staging folder; on normal exit it replaces ``out`` (the old
    content is removed), on an exception it is removed and ``out`` is untouched.
    The staging folder is named ``.OUT.staging-PID-HOST-XXXXXXXX`` after its
    writer (:func:`topoloc.io.lock.writer_tag`): a run removes the staging
    folders of runs killed before they finished, never those of a run still
    writing.  Runs into one ``out`` at the same time each put their own run in
    place whole as they finish, so ``out`` ends as the last one to finish wrote it.

    ``out`` named through a symbolic link is the folder the link points at: the
    run there is replaced and the link kept (issue #49: the link was replaced by
    the new run, and a staging link left behind).  ``out`` the null device
    (``/dev/null``): the run is written into a temporary folder and discarded.
    """
    if is_discard(out):
        with tempfile.TemporaryDirectory(prefix="topoloc-discarded-") as tmp:
            yield Path(tmp)
        return
    out = through_link(Path(out))
    out.parent.mkdir(parents=True, exist_ok=True)
    # Left by runs killed before they finished (never part of a result), and untagged ones
    # of older versions once they are an hour old.
    stale = re.compile(rf"^\.{re.escape(out.name)}\.staging-(?:{TAG_PATTERN}-|(?!\d+-[0-9a-f]{{8}}-))")
    remove_stale(out.parent, stale, _remove_tree)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-{writer_tag()}-", dir=out.parent))
    try:
        yield stage
    except BaseException as exc:
        shutil.rmtree(stage, ignore_errors=True)
        if isinstance(exc, OSError) and exc.filename is not None and Path(exc.filename).is_relative_to(stage):
            # Named as the user will look for it, not by the hidden folder that is gone now.
            final = out / Path(exc.filename).relative_to(stage)
            raise WriteError(exc.errno, exc.strerror or type(exc).__name__, str(final)) from None
        raise
    os.chmod(stage, _DIR_MODE)
    _put_in_place(stage, out)


@contextlib.contextmanager
def writing_into(folder: str | Path) -> Iterator[Path]:
    """The folder a command writes its files into: ``folder``, or a temporary one discarded for ``/dev/null``."""
    if is_discard(folder):
        with tempfile.TemporaryDirectory(prefix="topoloc-discarded-") as tmp:
            yield Path(tmp)
        return
    yield Path(folder)


def _remove_tree(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink()


def _put_in_place(stage: Path, out: Path) -> None:
    """Make ``stage`` the folder ``out``, whatever other runs into ``out`` do at the same time."""
    # Another run may put its folder in place between any two of these steps; each step that
    # finds the ground moved starts over, so one run ends in place whole and nothing is mixed.
    for _ in range(1000):
        if not os.path.lexists(out):
            try:
                os.rename(stage, out)
                return
            except OSError as exc:
                if exc.errno in (errno.ENOTEMPTY, errno.EEXIST) and os.path.lexists(out):
                    continue  # another run's folder arrived first: exchange with it
                raise
        if _exchange(stage, out):
            shutil.rmtree(stage, ignore_errors=True)  # now holds the run it replaced
            return
        if not os.path.lexists(out):
            continue  # gone between the check and the exchange (another run's two renames)
        old = stage.with_name(stage.name + "-old")
        try:
            os.rename(out, old)
        except FileNotFoundError:
            continue
        try:
            os.rename(stage, out)
        except OSError as exc:
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                raise
            # Another run put its folder in place after ours moved the old one aside: it is
            # whole and newer than the old one, so it stays.
            shutil.rmtree(stage, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)
        return
    raise OSError(f"could not put the run in place: {out}")  # pragma: no cover - 1000 lost races


# mkdtemp makes 0700 folders; a run folder gets what any folder the user creates gets.
_DIR_MODE = 0o777 & ~umask()


# -- outputs against inputs -----------------------------------------------------------------------------
# The longest prefix and suffix a write adds to an output's name: ``.NAME.staging-old-PID`` of
# staged_dir and ``.NAME.XXXXXXXX.tmp`` of atomic writes; a name the file system takes but whose
# temporary sibling it refuses would fail after the work, not before.
_NAME_EXTRA = 32

Earlier = Callable[[Path], bool]


@dataclass(frozen=True)
class Output:
    """One path a command writes, and how.

    Parameters
    ----------
    path : Path
        The file or folder.
    kind : {"file", "folder", "run"}
        ``"file"``: one file, replaced atomically.  ``"folder"``: files are
        written into it, the others left as they are.  ``"run"``: the folder
        is replaced whole (:func:`staged_dir`).
    names : tuple of str, optional
        For ``"folder"``: the entries the command writes in it; None when any
        entry may be written (e.g. images linked by ``convert``).
    earlier : callable
        Whether an existing file or folder is an earlier output of the same
        command, which may be replaced (:func:`json_marker`, :func:`container_marker`,
        :func:`jsonl_marker`, :func:`html_marker`, :func:`png_marker`).  Required
        for a ``"file"``: an output that cannot tell its own earlier file from a
        user's would replace any file (issue #49: ``--html notes.txt``).
    what : str
        How the refusal names the command's output (``"run folder"``).
    """

    path: Path
    kind: str = "file"
    names: tuple[str, ...] | None = None
    earlier: Earlier | None = None
    what: str = "output"

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))
        if self.kind not in ("file", "folder", "run"):
            raise ValueError(f"Output.kind must be file, folder or run, got {self.kind!r}")
        if self.kind == "file" and self.earlier is None:
            raise ValueError("an Output file needs earlier: the test that tells its own earlier output from a "
                             "user's file")


def json_marker(name: str, key: str) -> Earlier:
    """A test of an earlier output: ``folder/name`` is a JSON object whose ``key`` is an object.

    ``json_marker("metrics.json", "run")`` recognises an ``evaluate`` run folder:
    topoloc writes its ``run`` block (a user's ``metrics.json`` is unlikely to have one).
    """

    def earlier(folder: Path) -> bool:
        marker = folder / name
        try:
            if not marker.is_file() or marker.stat().st_size > _MARKER_MAX:
                return False
            data = json.loads(marker.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return False
        return isinstance(data, dict) and isinstance(data.get(key), dict)

    return earlier


_MARKER_MAX = 16 * 2**20


def container_marker(kind: str) -> Earlier:
    """A test of an earlier output file: a topoloc container holding ``kind`` (``"map"``, ``"vocabulary"``).

    Only the fixed part and the header are read, so a large map costs nothing to recognise.
    """

    def earlier(file: Path) -> bool:
        from topoloc.io.container import container_kind

        return container_kind(file) == kind

    return earlier


def _first_line(file: Path) -> bytes | None:
    """The first line of ``file`` (at most ``_MARKER_MAX`` bytes), or None when it cannot be read."""
    try:
        with open(file, "rb") as fh:
            return fh.readline(_MARKER_MAX)
    except OSError:
        return None


def jsonl_marker(key: str) -> Earlier:
    """A test of an earlier output file: empty, or JSON lines whose first line is an object with ``key``.

    ``jsonl_marker("frame")`` recognises what ``localize`` writes; a user's text file is not.
    """

    def earlier(file: Path) -> bool:
        first = _first_line(file)
        if first is None:
            return False
        if not first.strip():
            return True
        try:
            data = json.loads(first)
        except ValueError:
            return False
        return isinstance(data, dict) and key in data

    return earlier


def pairs_marker() -> Earlier:
    """A test of an earlier pairs file (``--pairs-out``): empty, or a first line of two names (``query map``).

    A user's text file whose first line is not two words is not replaced.
    """

    def earlier(file: Path) -> bool:
        first = _first_line(file)
        if first is None:
            return False
        try:
            return not first.strip() or len(first.decode("utf-8").split()) == 2
        except UnicodeDecodeError:
            return False

    return earlier


#: The first bytes of a file that the page markers look into (the style sheet comes before older pages' text).
_PAGE_HEAD = 256 * 1024

#: What every HTML page topoloc writes says right after its charset (evaluation.html, evaluation.slam_html).
HTML_GENERATOR = "<meta name='generator' content='topoloc'>"
#: Pages written before the generator line: the line under their title.
_OLDER_PAGES = (b"<p class='meta'>topoloc report of ", b"<p class='meta'>topoloc slam run ")


def html_marker() -> Earlier:
    """A test of an earlier HTML page of topoloc (``--html``): its generator line, or an older page's first line.

    A user's page, notes or any other file at the path is not one, and is never replaced.
    """

    def earlier(file: Path) -> bool:
        try:
            with open(file, "rb") as fh:
                head = fh.read(_PAGE_HEAD)
        except OSError:
            return False
        return HTML_GENERATOR.encode() in head or (head.startswith(b"<!DOCTYPE html>")
                                                   and any(m in head for m in _OLDER_PAGES))

    return earlier


#: The PNG text chunk (``tEXt``, keyword ``Software``) of every drawing topoloc writes (``show-match``).
PNG_SOFTWARE = b"Software\x00topoloc"
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_marker() -> Earlier:
    """A test of an earlier drawing of topoloc: a PNG whose first chunks say ``Software: topoloc``."""

    def earlier(file: Path) -> bool:
        try:
            with open(file, "rb") as fh:
                head = fh.read(4096)
        except OSError:
            return False
        return head.startswith(_PNG_SIGNATURE) and PNG_SOFTWARE in head

    return earlier


def signed_png(data: bytes) -> bytes:
    """An encoded PNG with a ``tEXt`` chunk ``Software: topoloc`` after its header (what :func:`png_marker` finds)."""
    import struct
    import zlib

    if not data.startswith(_PNG_SIGNATURE):
        raise ValueError("not a PNG")
    end_of_header = len(_PNG_SIGNATURE) + 8 + struct.unpack(">I", data[8:12])[0] + 4  # IHDR: length, type, data, CRC
    chunk = struct.pack(">I", len(PNG_SOFTWARE)) + b"tEXt" + PNG_SOFTWARE
    chunk += struct.pack(">I", zlib.crc32(b"tEXt" + PNG_SOFTWARE))
    return data[:end_of_header] + chunk + data[end_of_header:]


def _resolved(path: Path) -> Path:
    # strict=False: the part that does not exist yet is kept as written, under the real parents.
    return Path(os.path.realpath(path))


def _within(inner: Path, outer: Path) -> bool:
    return inner == outer or outer in inner.parents


def _same(a: Path, b: Path) -> bool:
    # Hard links and bind mounts name one file under two paths: compare the files themselves.
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _check_name(path: Path, what: str) -> None:
    real = _resolved(path)
    existing = real
    while not os.path.exists(existing) and existing != existing.parent:
        existing = existing.parent
    try:
        name_max = os.pathconf(existing, "PC_NAME_MAX")
        path_max = os.pathconf(existing, "PC_PATH_MAX")
    except (OSError, ValueError):
        name_max, path_max = 255, 4096
    for part in real.relative_to(existing).parts or (real.name,):
        if len(os.fsencode(part)) + _NAME_EXTRA > name_max:
            raise input_error(f"{what} name is too long for this file system ({len(os.fsencode(part))} bytes; "
                              f"at most {name_max - _NAME_EXTRA} leaves room for the temporary file beside it)",
                              path)
    if len(os.fsencode(str(real))) + _NAME_EXTRA > path_max:
        raise input_error(f"{what} path is too long for this file system", path)


def _not_special(path: Path, what: str, *, folder: bool) -> None:
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return
    except OSError as exc:
        raise input_error(f"cannot use the {what} ({exc.strerror or type(exc).__name__})", path) from None
    # The wording of check_output_dir and check_output_file, whose checks these extend.
    if stat.S_ISDIR(mode):
        if not folder:
            raise input_error(f"{what} is a folder, not a file", path)
    elif not stat.S_ISREG(mode):
        kind = kind_of(path)
        if folder:
            raise input_error(f"{what} is {kind}, not a folder", path)
        raise input_error(f"{what} is {kind}, not a regular file (it would be replaced)", path)
    elif folder:
        raise input_error("output folder is a file", path)


def _check_against_inputs(target: Path, inputs: list[tuple[Path, Path]], what: str, shown: Path) -> None:
    real = _resolved(target)
    for given, real_in in inputs:
        if real == real_in or _same(target, given):
            raise input_error(f"{what} is an input of this command ({given}) and would be overwritten", shown)
        if real_in.is_dir() and real_in in real.parents and os.path.lexists(target):
            raise input_error(f"{what} is a file of input folder {given} and would be overwritten", shown)


def _holds_user_files(folder: Path, names: tuple[str, ...] | None) -> str | None:
    """The first entry of ``folder`` a write would replace: a file, or a folder that is not empty."""
    try:
        entries = sorted(folder.iterdir()) if names is None else [folder / n for n in names]
    except OSError:
        return None
    for entry in entries:
        if not os.path.lexists(entry):
            continue
        if entry.is_dir() and not entry.is_symlink():
            if names is None or any(entry.iterdir()):
                return entry.name
        else:
            return entry.name
    return None


def check_outputs(outputs: Iterable[Output], inputs: Iterable[str | Path | None]) -> None:
    """Refuse, before any work, outputs that would destroy an input or a user's file.

    Paths are compared resolved (links followed) and as files (hard links): an
    output named through a link is judged, and later written, where the link
    points.  The null device (``/dev/null``) is accepted for any output: it is
    discarded.  Refused: an output ``"-"`` (standard output is not a file here); an output
    that is an input, or an existing file inside an input folder; a file output
    that is a folder, device, fifo or socket; a ``"folder"`` output that is an
    input, or whose entries to write exist and are not an earlier output of the
    command; a ``"run"`` output (replaced whole) that is the working folder or
    holds it, is or holds an input, or holds anything but an earlier output of
    the command; two outputs at one path; a name too long for the file system.
    Then each output must be writable (:func:`check_output_file`,
    :func:`check_output_dir`).

    Parameters
    ----------
    outputs : iterable of Output
    inputs : iterable of path
        Every file and folder the command reads (maps, map files, images,
        folders, recordings, vocabularies, ground truth); None and missing
        paths are skipped (their readers name them).

    Raises
    ------
    TopolocError
        One line naming the output and the problem.
    """
    ins = [(Path(p), _resolved(Path(p))) for p in inputs if p is not None and str(p) != ""]
    ins = [(p, r) for p, r in ins if os.path.lexists(p)]
    seen: dict[Path, Path] = {}
    cwd = _resolved(Path.cwd())
    for out in outputs:
        path, what = out.path, out.what
        if str(path) == "-":
            raise input_error(f"{what} cannot be standard output ('-'): name a file or folder", path)
        if is_discard(path):
            continue  # /dev/null: the output is discarded, nothing is written (issue #49)
        real = _resolved(path)
        if real in seen:
            raise input_error(f"{what} is also another output of this command ({seen[real]})", path)
        seen[real] = path
        _check_name(path, what)
        if out.kind == "file":
            _not_special(path, what, folder=False)
            _check_against_inputs(path, ins, what, path)
            if out.earlier is not None and path.is_file() and not out.earlier(path):
                raise input_error(f"{what} exists and is not an earlier output of this command, which would "
                                  "overwrite it: name a new file", path)
            check_output_file(through_link(path))  # written where a link points
            continue
        _not_special(path, what, folder=True)
        if out.kind == "run":
            if _within(cwd, real):
                raise input_error(f"{what} is the working folder or holds it, and would be replaced", path)
            for given, real_in in ins:
                if _within(real_in, real) or _same(path, given):
                    raise input_error(f"{what} holds an input of this command ({given}) and would be replaced",
                                      path)
        else:
            for given, real_in in ins:
                if real == real_in or _same(path, given):
                    raise input_error(f"{what} is an input of this command ({given})", path)
            for name in out.names or ():
                _check_against_inputs(path / name, ins, what, path / name)
        if path.is_dir() and not (out.earlier is not None and out.earlier(path)):
            entry = _holds_user_files(path, None if out.kind == "run" else out.names)
            if entry is not None:
                verb = "replaced" if out.kind == "run" else "overwritten"
                raise input_error(f"{what} holds {entry!r}, not an earlier output of this command, which would be "
                                  f"{verb}: choose a new or empty folder", path)
        check_output_dir(through_link(path))


__all__ = ["HTML_GENERATOR", "Output", "check_output_dir", "check_output_file", "check_outputs", "html_marker",
           "json_marker", "png_marker", "signed_png", "staged_dir", "writing_into"]
