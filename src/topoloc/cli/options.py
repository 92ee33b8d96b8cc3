"""Every option shared by several commands, defined once with one help text, and the flag of each parameter.

Commands parse their options into a run specification (:mod:`topoloc.spec`)
with :func:`spec_from_cli`; a configuration file (``--config``) gives the
settings a flag does not, and a flag given on the command line overrides it.
Library errors name a parameter (``features.max_side``); :func:`flag_of`
turns it into the flag the user typed (``--max-side``).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer

from topoloc.errors import ParameterError, TopolocError

S = TypeVar("S")

# -- what a run reads -------------------------------------------------------------------------------------
MapToursOption = Annotated[list[Path] | None, typer.Option(
    "--map", metavar="<path>", help="Map traverse (repeatable): a folder, a ROS bag (--topic) or a video.")]
QueryOption = Annotated[Path | None, typer.Option(
    help="Query traverse: a folder, a ROS bag (--topic) or a video.")]
MethodOption = Annotated[str, typer.Option(help="Method name (see `topoloc methods`).")]
ParamOption = Annotated[list[str] | None, typer.Option(
    metavar="<key=value>", help="Method parameter KEY=VALUE (repeatable).")]
ConfigOption = Annotated[Path | None, typer.Option(
    "--config", help="Settings file (TOML, YAML, or a run's metrics.json); flags given here override it.")]
# -- features and vocabulary ------------------------------------------------------------------------------
FeaturesOption = Annotated[str, typer.Option(
    help="Local features: auto (xfeat, on ONNX Runtime; sift with a warning where that is not installed), "
         "xfeat (learned), sift, rootsift, orb, akaze.")]
SlamFeaturesOption = Annotated[str, typer.Option(
    "--features", help="Local features: sift (the default of slam: online FAB-MAP with XFeat merged most of a loop "
                       "into one place on rtabmap_loop, docs/results/learned_features.md), xfeat, rootsift, orb, "
                       "akaze, or auto (xfeat where installed).")]
MaxFeaturesOption = Annotated[int, typer.Option(help="Cap on features per image.")]
MaxSideAutoOption = Annotated[str, typer.Option(
    help="Downscale images to this longer side before extraction; 'auto' = 640 (smaller images "
         "are kept as they are), 0 = never.")]
PreprocessOption = Annotated[str, typer.Option(
    help="Photometric preprocessing: auto (default; CLAHE weighted per image by how far its "
         "histogram is from uniform, so dark night frames are equalised and well-exposed ones barely "
         "touched), none, clahe, equalize.")]
VocabOption = Annotated[Path | None, typer.Option(
    help="Vocabulary file (topoloc vocab train). Without --vocab and --vocab-train, one is trained on the "
         "map's own tours (cached).")]
VocabTrainOption = Annotated[list[Path] | None, typer.Option(
    "--vocab-train", metavar="<path>", help="Folders (searched recursively) to train a vocabulary on (repeatable).")]
VocabWordsOption = Annotated[int, typer.Option(
    help="Words when training a vocabulary (--vocab-train, or the default one on the map's tours).")]
# -- ground truth and matching ----------------------------------------------------------------------------
ToleranceOption = Annotated[str, typer.Option(help="Ground-truth tolerance HARD:SOFT in place ids.")]
ToleranceMOption = Annotated[str | None, typer.Option(
    "--tolerance-m", help="Tolerance HARD:SOFT in metres (needs x,y).")]
SequenceOption = Annotated[int | None, typer.Option(
    help="Sequence matching over each query and the N >= 1 before it (off when not given; with --map-file, "
         "the map's calibrated sequence when not given, 0 = single images).")]
LocalizeSequenceOption = Annotated[int | None, typer.Option(
    "--sequence", help="Sequence matching over each frame and the N before it; 0 = single images. Default: what "
                       "`map calibrate` calibrated the map's threshold with (single images for a map not calibrated "
                       "or calibrated before sequence calibration; docs/protocol.md).")]
CalibrateSequenceOption = Annotated[int | None, typer.Option(
    "--sequence", help="Calibrate the confidence of sequence matching over each frame and the N before it, as "
                       "`localize` then matches by default; 0 = single images. Default: 10 where the tour "
                       "moves along the route (half its steps advance 1-3 places), else 0 (docs/protocol.md).")]
VerifyOption = Annotated[bool | None, typer.Option(
    "--verify/--no-verify", help="Check each answer's candidates by local matches and epipolar geometry and score "
                                 "it by its inliers (docs/protocol.md, Verification). Default: wherever the map's "
                                 "images can be read (a saved map: as it was calibrated or built; maps saved before "
                                 "verification existed are not verified unless asked).")]
#: ``--min-support``'s default: :data:`topoloc.verification.MIN_SUPPORT` (not imported here, where the command line
#: starts fast; tests/cli/test_cli_verify.py holds the two equal).
DEFAULT_MIN_SUPPORT = 25
MinSupportOption = Annotated[int | None, typer.Option(
    "--min-support", help=f"Support (inliers that are distinctive matches) a verified answer needs, at any "
                          f"--max-features (default {DEFAULT_MIN_SUPPORT}, chosen on the development data; against "
                          "a saved map, the floor its calibration, else its build, recorded: docs/protocol.md, "
                          "Verification).", show_default=False)]
ConfirmOption = Annotated[bool, typer.Option(
    "--confirm/--no-confirm", help="Temporal consistency: an answer the previous frame's does not confirm ranks below "
                                   "every confirmed one (docs/protocol.md, Verification; off by default).")]
SequenceModeOption = Annotated[str, typer.Option(
    help="constant: SeqSLAM's constant-velocity lines; acceleration: Cooc-Map's forward paths (II-F).")]
PrefetchOption = Annotated[int, typer.Option(
    help="Frames read and described ahead while one is matched, on one thread per core (-1: two per "
         "core; 0: one frame at a time); the lines are the same.")]
PairsOutOption = Annotated[Path | None, typer.Option(
    "--pairs-out", help="Also write the retrieval pairs of the top K places, 'query_image map_image' a line, as "
                        "hloc and COLMAP read them (a place: its first map image; docs/protocol.md).")]
# -- where it runs and what it shows ----------------------------------------------------------------------
CacheDirOption = Annotated[Path | None, typer.Option(help="Feature/vocabulary cache folder.")]
QuietOption = Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars.")]
SchedulerOption = Annotated[str | None, typer.Option(
    "--scheduler", help="Dask scheduler address (tcp://host:8786): feature extraction and quantisation run on its "
                        "workers, which must see the cache folder at the same path; default $TOPOLOC_SCHEDULER, "
                        "else this machine's threads. Needs pip install 'topoloc[distributed]'.")]
SchedulerTimeoutOption = Annotated[float | None, typer.Option(
    "--scheduler-timeout", help="Seconds to wait for the scheduler and a worker before a one-line error "
                                "(default $TOPOLOC_SCHEDULER_TIMEOUT, else 10).")]
# -- recordings -------------------------------------------------------------------------------------------
TopicOption = Annotated[str | None, typer.Option(
    "--topic", help="Image topic of ROS bags (sensor_msgs/Image or CompressedImage); needed when a bag has "
                    "several.")]
EverySOption = Annotated[float | None, typer.Option(
    "--every-s", help="Bags and videos: keep one frame every T seconds.")]
EveryMOption = Annotated[float | None, typer.Option(
    "--every-m", help="Bags with an odometry, pose or GPS topic: keep one frame every D metres.")]
PoseTopicOption = Annotated[str | None, typer.Option(
    "--pose-topic", help="Bags: the odometry, pose or GPS topic for --every-m and x, y (default: the bag's first).")]

# Command-line names that differ from the specification's flat names (topoloc.spec.FLAT_NAMES).
_CLI_TO_FLAT = {"map": "maps", "param": "params"}
_FLAT_TO_FLAG = {"vocabulary": "--vocab/--vocab-train", "maps": "--map", "params": "--param", "images": "INPUTS",
                 "folders": "FOLDERS", "map_file": "--map-file"}
_NOT_SPEC = {"config", "quiet", "ctx"}
#: Values a command passes under another name than its parameter's: localize's INPUTS become images or a stream.
_CLI_PARAMETER = {"images": "inputs", "stream": "inputs"}
#: A setting that is several of a command's parameters at once.
_GROUPS = {"vocabulary": ("vocab", "vocab_train")}
#: Where a command keeps its own flat names (``vocab train``'s ``--words``), for the errors raised after parsing.
NAMES_KEY = "topoloc.flat_names"


def own_names(ctx: typer.Context, names: Mapping[str, str]) -> None:
    """Record that this command's flags ``names`` (``{"places": "n_places"}``) give the parameters named so."""
    meta = getattr(ctx, "meta", None)
    if meta is not None:  # a context click made (not a stand-in)
        meta[NAMES_KEY] = dict(names)


def flag_of(param: str, names: Mapping[str, str] | None = None, *, command: Any = None) -> str:
    """The flag a parameter of a run specification comes from: ``features.max_side`` -> ``--max-side``.

    ``names`` are the command's own flat names for dotted ones (``vocab train``'s ``words``).
    ``command`` (a click command) names it as that command takes it: its option's flag or its
    argument's name (``localize``'s ``MAP_FILE``, not ``evaluate``'s ``--map-file``), so that a
    message never names a flag of another command (issue #49); a setting the command has no
    flag for (one only a ``--config`` file gives) keeps its name in that file.
    """
    from topoloc.spec.config import DOTTED_NAMES

    own = {dotted: flat for flat, dotted in (names or {}).items()}
    parts = []
    for one in param.split("/"):
        flat = own.get(one) or DOTTED_NAMES.get(one, one)
        shown = _command_flag(command, one, flat) if command is not None else None
        if shown is not None:
            parts.append(shown)
        elif command is not None:
            parts.append(one)  # not a flag of this command: the name a configuration file or a method gives it
        else:
            parts.append(_FLAT_TO_FLAG.get(flat) or "--" + flat.replace("_", "-").replace(".", "-"))
    return "/".join(dict.fromkeys(parts))


def _command_flag(command: Any, dotted: str, flat: str) -> str | None:
    """How ``command`` takes the setting ``flat`` (dotted: ``dotted``): ``--flag``, ``ARGUMENT``, or None."""
    by_name = {p.name: p for p in command.params}
    cli = {v: k for k, v in _CLI_TO_FLAT.items()}.get(flat, _CLI_PARAMETER.get(flat, flat))
    found = [by_name[n] for n in _GROUPS.get(flat, (cli,)) if n in by_name]
    shown = []
    for p in found:
        if p.param_type_name == "argument":
            shown.append(p.metavar or (p.name or "").upper())
        else:
            shown.append(max((o for o in p.opts if o.startswith("--")), key=len, default=p.opts[0]))
    return "/".join(shown) or None


def parameter_message(exc: ParameterError) -> str:
    """The one line of a :class:`ParameterError` at the command line: the flags of the command typed.

    A parameter the command has no flag for keeps its own name: a setting
    of a ``--config`` file, or a method's parameter (``--param ds=...``), said
    with what it belongs to (``seqslam: ds must be ...``).
    """
    from typer._click.globals import get_current_context

    ctx = get_current_context(silent=True)
    command = ctx.command if ctx is not None else None
    names = ctx.meta.get(NAMES_KEY) if ctx is not None else None

    def name(p: str) -> str:
        return flag_of(p, names, command=command)

    head = name(exc.param)
    if exc.owner and head == exc.param:
        head = f"{exc.owner}: {exc.param}"
    return f"{head} {exc.render(name)}"


def parse_params(items: list[str]) -> dict[str, str]:
    """``["k=v", ...]`` of ``--param`` (or ``--column``) -> ``{"k": "v"}``."""
    out = {}
    for it in items:
        if "=" not in it:
            raise TopolocError(f"--param {it!r} is not KEY=VALUE")
        k, v = it.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def at_least(flag: str, value: int, low: int) -> int:
    """Refuse a whole-number option below ``low`` with one line naming the flag (before any work)."""
    if value < low:
        raise TopolocError(f"{flag} must be a whole number >= {low}, got {value}")
    return value


def sequence_length(n: int | None) -> int:
    """``--sequence N``: absent means off; a given N must be >= 1 (0 would silently mean "off")."""
    if n is None:
        return 0
    if n < 1:
        raise TopolocError(f"--sequence must be >= 1 (leave it out to match single images), got {n}")
    return n


def spec_from_cli(cls: type[S], ctx: typer.Context, values: Mapping[str, Any], *, config: Path | None = None,
                  names: Mapping[str, str] | None = None) -> S:
    """The run specification ``cls`` from a command's option values (and ``--config``).

    Without ``config`` every value counts; with it, only the options given on
    the command line (or in the environment) override the file's settings.
    """
    from topoloc.spec import load_config, merge, nest, spec_from_dict
    from topoloc.spec.config import typed_config

    if names:
        own_names(ctx, names)
    flat: dict[str, Any] = {}
    for key, value in values.items():
        if key in _NOT_SPEC:
            continue
        if config is not None:
            # Values a command renamed from its parameter (localize's INPUTS split into images and a stream).
            source = ctx.get_parameter_source(_CLI_PARAMETER.get(key, key))
            if getattr(source, "name", None) not in ("COMMANDLINE", "ENVIRONMENT"):
                continue
        if key == "param":
            value = parse_params(value or [])
        elif key == "sequence":
            value = sequence_length(value)
        elif isinstance(value, list):
            value = tuple(value)
        flat[_CLI_TO_FLAT.get(key, key)] = value
    given = nest(flat, names=names)
    base: dict[str, Any] = {}
    if config is not None:
        base = drop_alternatives(typed_config(cls, load_config(config), source=config), given)
        out = given.get("out")
        if out is not None and Path(config).resolve().is_relative_to(Path(out).resolve()):
            raise ParameterError("out", f"would replace the configuration file it is read from: {config}")
    try:
        return spec_from_dict(cls, merge(base, given), source=config)
    except ParameterError as exc:
        if config is None or any(_dotted(given, p) not in (None, (), [], "") for p in exc.param.split("/")):
            raise
        # A value the file set, not a flag: say where it came from.
        raise ParameterError(exc.param, f"{exc.template} (set in {config})", exc.refs) from None


#: Settings that are alternatives to one another: a flag giving one replaces a file's other (issue #41).
ALTERNATIVES = (("ground_truth.tolerance", "ground_truth.tolerance_m"), ("vocabulary.file", "vocabulary.train"),
                ("maps", "map_file"), ("images", "stream"))
#: A flag giving the first replaces the file's settings it fixes: a saved map fixes the method, its
#: parameters and its vocabulary (a file's ``method = "bow"`` is for building from ``maps``).
FIXES = {"map_file": ("method", "params", "vocabulary.file", "vocabulary.train", "vocabulary.words")}


def _dotted(nested: Mapping[str, Any], name: str) -> Any:
    head, _, tail = name.partition(".")
    value = nested.get(head)
    return (value.get(tail) if isinstance(value, Mapping) else None) if tail else value


def drop_alternatives(base: dict[str, Any], given: Mapping[str, Any]) -> dict[str, Any]:
    """A file's settings less those that a setting given as a flag replaces (flags always win).

    Settings of :data:`ALTERNATIVES` exclude each other; given one of a group
    on the command line, the file's others of the group are left out.
    """
    out = {k: dict(v) if isinstance(v, Mapping) else v for k, v in base.items()}

    def given_here(name: str) -> bool:
        return _dotted(given, name) not in (None, (), [], "", {})

    def drop(name: str) -> None:
        head, _, tail = name.partition(".")
        if tail and isinstance(out.get(head), dict):
            out[head].pop(tail, None)
        elif not tail:
            out.pop(head, None)

    for group in ALTERNATIVES:
        if any(given_here(name) for name in group):
            for name in group:
                if not given_here(name):
                    drop(name)
    for flag, fixed in FIXES.items():
        if given_here(flag):
            for name in fixed:
                if not given_here(name):
                    drop(name)
    return out
