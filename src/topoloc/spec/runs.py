"""What each command runs, as one composed, validated specification.

A run specification is a frozen dataclass of a command's own fields (method,
tours, output) and the parts of :mod:`topoloc.spec.parts`.  It is what
``metrics.json`` and a map's header record (:func:`spec_to_dict`), and what a
configuration file holds (:mod:`topoloc.spec.config`), so any run can be made
again from its record.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from topoloc.errors import ParameterError, TopolocError
from topoloc.io.dirs import (
    Output,
    check_outputs,
    container_marker,
    html_marker,
    json_marker,
    jsonl_marker,
    pairs_marker,
)
from topoloc.io.paths import is_discard
from topoloc.spec.parts import (
    ExecutionSpec,
    FeatureSpec,
    GroundTruthSpec,
    InputSpec,
    SequenceSpec,
    VerificationSpec,
    VocabularySpec,
    _opt_path,
    _paths,
    distinct_paths,
    parse_recall_at,
)


def _present(*paths: Path | None) -> tuple[Path, ...]:
    return tuple(p for p in paths if p is not None)


def _whole(param: str, value: Any, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ParameterError(param, f"must be a whole number >= {low}, got {value!r}")
    return value


def check_prefetch(value: Any) -> int:
    """Frames ``localize`` reads and describes ahead (``Localizer``): -1 (two per core) or a whole number >= 0."""
    return _whole("prefetch", value, -1)


class _ChecksOutputs:
    """What every run specification says about the paths it reads and writes."""

    def read_paths(self) -> tuple[Path, ...]:
        """Every file and folder the run reads (inputs to protect from its outputs)."""
        raise NotImplementedError

    def outputs(self) -> tuple[Output, ...]:
        """Every file and folder the run writes."""
        raise NotImplementedError

    def check_outputs(self) -> None:
        """Refuse, before any work, outputs that would overwrite an input or a user's files.

        See :func:`topoloc.io.dirs.check_outputs`.

        Raises
        ------
        TopolocError
            One line naming the output and the problem.
        """
        check_outputs(self.outputs(), self.read_paths())


def html_page(html: Path, out: Path | None) -> Path:
    """The file an HTML page given as ``html`` is written to: ``html/index.html`` for a folder or ``out``."""
    # The page of a folder is its index.html (evaluation.html.build_html_report), and so is the
    # page of the run folder itself, which exists by the time the page is written.
    if is_discard(html):
        return html
    if html.is_dir() or (out is not None and Path(os.path.realpath(html)) == Path(os.path.realpath(out))):
        return html / "index.html"
    return html


# An evaluate run folder is recognised by the run block topoloc writes into its metrics.json.
EARLIER_RUN = json_marker("metrics.json", "run")


@dataclass(frozen=True)
class EvaluateSpec(_ChecksOutputs):
    """``topoloc evaluate``: one method on map and query traverses, scored (``docs/protocol.md``).

    Parameters
    ----------
    method : str
        A registered method (``topoloc methods``); empty with ``map_file``.
    params : dict
        The method's parameters (values, or the strings of ``--param KEY=VALUE``).
    maps : tuple of Path
        Map traverses: folders, ROS bags or videos.
    query : Path
        The query traverse.
    out : Path
        Output folder (``docs/protocol.md`` lists its files).
    map_file : Path, optional
        A saved map instead of ``maps`` and ``method``.
    recall_at : str
        The N of R@N to report, e.g. ``"1,5,10,20"``.
    top_k : int
        Keep only the K best places per query (0 = the whole S).
    html : Path, optional
        Also write the browsable HTML page of the run here.
    pairs_out : Path, optional
        Also write the ``top_k`` retrieval pairs of each query in hloc's format
        (:mod:`topoloc.evaluation.pairs`); needs ``top_k``.
    features, vocabulary, inputs, ground_truth, sequence, execution, verification
        The parts (:mod:`topoloc.spec.parts`).
    """

    method: str = ""
    params: dict[str, Any] = field(default_factory=dict)
    maps: tuple[Path, ...] = ()
    query: Path | None = None
    out: Path | None = None
    map_file: Path | None = None
    recall_at: str = "1,5,10"
    top_k: int = 0
    html: Path | None = None
    pairs_out: Path | None = None
    features: FeatureSpec = field(default_factory=FeatureSpec)
    vocabulary: VocabularySpec = field(default_factory=VocabularySpec)
    inputs: InputSpec = field(default_factory=InputSpec)
    ground_truth: GroundTruthSpec = field(default_factory=GroundTruthSpec)
    sequence: SequenceSpec = field(default_factory=SequenceSpec)
    execution: ExecutionSpec = field(default_factory=ExecutionSpec)
    verification: VerificationSpec = field(default_factory=VerificationSpec)

    def __post_init__(self) -> None:
        object.__setattr__(self, "maps", _paths(self.maps))
        for name in ("query", "out", "map_file", "html", "pairs_out"):
            object.__setattr__(self, name, _opt_path(getattr(self, name)))
        object.__setattr__(self, "params", dict(self.params or {}))
        if self.map_file is not None and self.maps:
            raise ParameterError("maps/map_file", "exclude each other: give map tours or a saved map, not both")
        if not self.maps and self.map_file is None:
            raise ParameterError("maps", "needs at least one map traverse (or a saved map: {map_file})", ("map_file",))
        if not self.method and self.map_file is None:
            raise ParameterError("method", "is needed (see `topoloc methods`), or a saved map: {map_file}",
                                 ("map_file",))
        if self.query is None:
            raise ParameterError("query", "is needed: the traverse to localise")
        if self.out is None:
            raise ParameterError("out", "is needed: the output folder")
        parse_recall_at(self.recall_at)
        _whole("top_k", self.top_k, 0)
        if self.pairs_out is not None and not self.top_k:
            raise ParameterError("pairs_out", "writes the K best map images of each query: give {top_k} too",
                                 ("top_k",))
        if self.top_k and self.html is not None:
            raise ParameterError("html", "draws the whole S: leave out {top_k}, or {html}", ("top_k", "html"))
        if self.map_file is not None and (self.params or self.vocabulary.given):
            raise ParameterError("map_file", "fixes its parameters and vocabulary: method parameters and a vocabulary "
                                             f"cannot be given with it ({self.map_file})")

    def read_paths(self) -> tuple[Path, ...]:
        """Map tours, query, map file, vocabulary file or training folders, ground truth, cache folder."""
        return _present(*self.maps, self.query, self.map_file, self.vocabulary.file, *self.vocabulary.train,
                        self.ground_truth.file, self.execution.cache_dir)

    def outputs(self) -> tuple[Output, ...]:
        """The run folder (replaced whole: empty, new, or an earlier run), the HTML page and the pairs file."""
        assert self.out is not None
        outs = [Output(self.out, "run", earlier=EARLIER_RUN, what="run folder")]
        if self.html is not None:
            outs.append(Output(html_page(self.html, self.out), what="HTML page", earlier=html_marker()))
        if self.pairs_out is not None:
            outs.append(Output(self.pairs_out, what="pairs file", earlier=pairs_marker()))
        return tuple(outs)


@dataclass(frozen=True)
class MapBuildSpec(_ChecksOutputs):
    """``topoloc map build``: fit a method on tours and save the map.

    Parameters
    ----------
    method : str
    params : dict
    maps : tuple of Path
        The map's tours.
    out : Path, optional
        The map file to write (None: a map built from Python, not yet saved).
    shards : int
        Partial models of place ranges, one task each, merged (``docs/map_shards.md``).
    features, vocabulary, inputs, execution, verification
        The parts (:mod:`topoloc.spec.parts`); ``verification`` is recorded in
        the map as the default of ``localize`` and ``evaluate --map-file``.
    """

    method: str = ""
    params: dict[str, Any] = field(default_factory=dict)
    maps: tuple[Path, ...] = ()
    out: Path | None = None
    shards: int = 1
    features: FeatureSpec = field(default_factory=FeatureSpec)
    vocabulary: VocabularySpec = field(default_factory=VocabularySpec)
    inputs: InputSpec = field(default_factory=InputSpec)
    execution: ExecutionSpec = field(default_factory=ExecutionSpec)
    verification: VerificationSpec = field(default_factory=VerificationSpec)

    def __post_init__(self) -> None:
        object.__setattr__(self, "maps", _paths(self.maps))
        object.__setattr__(self, "out", _opt_path(self.out))
        object.__setattr__(self, "params", dict(self.params or {}))
        if not self.method:
            raise ParameterError("method", "is needed (see `topoloc methods`)")
        if not self.maps:
            raise ParameterError("maps", "needs at least one tour")
        _whole("shards", self.shards, 1)

    def read_paths(self) -> tuple[Path, ...]:
        """The tours, the vocabulary file or training folders, the cache folder."""
        return _present(*self.maps, self.vocabulary.file, *self.vocabulary.train, self.execution.cache_dir)

    def outputs(self) -> tuple[Output, ...]:
        """The map file (none for a map built from Python, not yet saved)."""
        # An existing file is replaced only when it is a map (a rebuild), never a user's other file.
        return () if self.out is None else (Output(self.out, what="map file", earlier=container_marker("map")),)


@dataclass(frozen=True)
class LocalizeSpec(_ChecksOutputs):
    """``topoloc localize``: frames against a saved map, one result line each.

    Parameters
    ----------
    map_file : Path
    images : tuple of Path
        Image files or folders, ROS bags or videos, in order.
    stream : str, optional
        A camera (``/dev/video0`` or its index) or a network stream URL, read live
        instead of ``images`` (:class:`~topoloc.datasets.sources.live.LiveSource`).
    out : Path
        The JSON-lines file.
    top_k : int
        Places listed per frame.
    pairs_out : Path, optional
        Also write each frame's ``top_k`` places as retrieval pairs in hloc's
        format, a place as its first map image (:mod:`topoloc.evaluation.pairs`).
    prefetch : int
        Frames read and described ahead of the one being matched, on one thread
        per core (-1: two per core; 0: one frame at a time); the lines are the same.
    sequence, inputs, execution, verification
        The parts (:mod:`topoloc.spec.parts`).
    """

    map_file: Path | None = None
    images: tuple[Path, ...] = ()
    stream: str | None = None
    out: Path | None = None
    top_k: int = 5
    pairs_out: Path | None = None
    prefetch: int = -1
    sequence: SequenceSpec = field(default_factory=SequenceSpec)
    inputs: InputSpec = field(default_factory=InputSpec)
    execution: ExecutionSpec = field(default_factory=ExecutionSpec)
    verification: VerificationSpec = field(default_factory=VerificationSpec)

    def __post_init__(self) -> None:
        object.__setattr__(self, "images", _paths(self.images))
        object.__setattr__(self, "map_file", _opt_path(self.map_file))
        object.__setattr__(self, "out", _opt_path(self.out))
        object.__setattr__(self, "pairs_out", _opt_path(self.pairs_out))
        if self.map_file is None:
            raise ParameterError("map_file", "is needed: the map to localise against")
        if self.stream is not None and self.images:
            raise ParameterError("images", f"a camera or stream ({self.stream}) is read alone: give no other input")
        if not self.images and self.stream is None:
            raise ParameterError("images", "needs at least one image, folder or recording, or a camera or stream")
        if self.out is None:
            raise ParameterError("out", "is needed: the JSON-lines file to write")
        _whole("top_k", self.top_k, 1)
        check_prefetch(self.prefetch)

    def read_paths(self) -> tuple[Path, ...]:
        """The map file (memory-mapped while the run writes) and the images, folders or recordings."""
        return _present(self.map_file, *self.images)

    @property
    def to_stdout(self) -> bool:
        """``out`` is ``-``: the lines go to standard output (and the summary to standard error)."""
        return str(self.out) == "-"

    def outputs(self) -> tuple[Output, ...]:
        """The JSON-lines file (none for standard output) and the pairs file."""
        assert self.out is not None
        lines = () if self.to_stdout else (Output(self.out, what="output", earlier=jsonl_marker("frame")),)
        if self.pairs_out is None:
            return lines
        return (*lines, Output(self.pairs_out, what="pairs file", earlier=pairs_marker()))


@dataclass(frozen=True)
class VocabTrainSpec(_ChecksOutputs):
    """``topoloc vocab train``: k-means words from the features of images under folders.

    Parameters
    ----------
    folders : tuple of Path
    out : Path
        The vocabulary file to write.
    features, vocabulary, execution
        The parts; ``vocabulary.words`` and ``vocabulary.seed`` apply,
        ``vocabulary.train`` is ``folders``.
    """

    folders: tuple[Path, ...] = ()
    out: Path | None = None
    features: FeatureSpec = field(default_factory=FeatureSpec)
    vocabulary: VocabularySpec = field(default_factory=VocabularySpec)
    execution: ExecutionSpec = field(default_factory=ExecutionSpec)

    def __post_init__(self) -> None:
        object.__setattr__(self, "folders", distinct_paths("folders", _paths(self.folders)))
        object.__setattr__(self, "out", _opt_path(self.out))
        if not self.folders:
            raise ParameterError("folders", "needs at least one image folder")
        if self.out is None:
            raise ParameterError("out", "is needed: the vocabulary file to write")

    def read_paths(self) -> tuple[Path, ...]:
        """The image folders and the cache folder."""
        return _present(*self.folders, *self.vocabulary.train, self.execution.cache_dir)

    def outputs(self) -> tuple[Output, ...]:
        """The vocabulary file."""
        assert self.out is not None
        return (Output(self.out, what="vocabulary file", earlier=container_marker("vocabulary")),)


@dataclass(frozen=True)
class NodeSpec:
    """``topoloc ros-node`` (ROS 1) and ``topoloc ros2-node`` (ROS 2): an image topic localised against a map.

    One specification for both nodes and every way of setting them: a field's
    flat name (:attr:`PARAMS`) is the node's ROS parameter, the command line's
    flag (``image_topic`` -> ``--image-topic``) and, nested as in every other
    specification, a configuration file's setting (``--config``:
    ``image_topic = "/camera/image_raw"``, ``[sequence] length = 5``,
    ``[verification] enabled = true``).

    Parameters
    ----------
    map_file : Path
        The saved map (parameter ``map``).
    image_topic : str
        The image topic subscribed (``image``, under the node's namespace: remap it).
    queue : int
        Frames that may wait to be matched (1: the newest only); older ones are skipped and counted.
    rate : float
        At most this many frames localised a second (0: as many as the cores allow); the others skipped.
    top_k : int
        Places listed per answer.
    prefetch : int, optional
        Frames decoded and described ahead while one is matched (as ``localize --prefetch``).  None:
        one per core, not ``localize``'s two: a frame taken from the topic waits behind the ones
        already ahead of it, so every extra one adds a frame's time to the latency without adding
        throughput once each core describes one.
    map_frame : str
        ``frame_id`` of the position answers (the map's coordinates).
    watch_map : bool
        Reload the map when its file changes.
    device : str, optional
        Where learned features are extracted (``cpu``, ``cuda``, ``auto``; as ``--device``); None:
        ``$TOPOLOC_DEVICE``, else the CPU.  Fixed for the node's life: its runtime is created once.
    sequence : SequenceSpec, optional
        Sequence matching over each frame and the ``length`` before it (parameters ``sequence``,
        ``sequence_mode``); None: as the map was calibrated (``localize``'s default).
    verification : VerificationSpec
        Geometric verification of each answer (parameters ``verify``, ``verify_candidates``,
        ``min_support``, ``confirm``), decided as ``localize`` decides it.
    """

    map_file: Path | None = None
    image_topic: str = "image"
    queue: int = 1
    rate: float = 0.0
    top_k: int = 5
    prefetch: int | None = None
    map_frame: str = "map"
    watch_map: bool = True
    device: str | None = None
    sequence: SequenceSpec | None = None
    verification: VerificationSpec = field(default_factory=VerificationSpec)

    #: The node's parameters (flat names, as the command line spells them) -> the specification's dotted names.
    PARAMS: ClassVar[dict[str, str]] = {
        "map": "map_file", "image_topic": "image_topic", "queue": "queue", "rate": "rate", "top_k": "top_k",
        "prefetch": "prefetch", "map_frame": "map_frame", "watch_map": "watch_map", "device": "device",
        "sequence": "sequence.length", "sequence_mode": "sequence.mode",
        "verify": "verification.enabled", "verify_candidates": "verification.candidates",
        "min_support": "verification.min_support", "confirm": "verification.confirm",
    }
    #: Parameters fixed for the node's life (a change at run time is refused with this reason).
    FIXED: ClassVar[dict[str, str]] = {
        "device": "the features' runtime is created once per process: restart the node on another device",
    }

    def __post_init__(self) -> None:
        object.__setattr__(self, "map_file", _opt_path(self.map_file))
        if self.map_file is None:
            raise ParameterError("map_file", "is needed: the map to localise against")
        for name in ("image_topic", "map_frame"):
            value = getattr(self, name)
            if not isinstance(value, str) or not value.strip():
                raise ParameterError(name, f"must be a non-empty name, got {value!r}")
        _whole("queue", self.queue, 1)
        _whole("top_k", self.top_k, 1)
        if self.prefetch is not None:
            check_prefetch(self.prefetch)
        if isinstance(self.rate, bool) or not isinstance(self.rate, int | float) or not (
                math.isfinite(self.rate) and self.rate >= 0):
            raise ParameterError("rate", f"must be a finite number of frames a second >= 0, got {self.rate!r}")
        object.__setattr__(self, "rate", float(self.rate))
        if not isinstance(self.watch_map, bool):
            raise ParameterError("watch_map", f"must be true or false, got {self.watch_map!r}")
        if self.device is not None:
            from topoloc.features.learned import DEVICES

            if str(self.device).strip().lower() not in DEVICES:
                raise ParameterError("device", f"must be one of {', '.join(DEVICES)}, got {self.device!r}")
            object.__setattr__(self, "device", str(self.device).strip().lower())

    @classmethod
    def from_params(cls, params: Mapping[str, Any], *, text: bool = False) -> NodeSpec:
        """The specification from flat parameters (:attr:`PARAMS`); a parameter whose value is None is not given.

        ``sequence`` below 0 is a launch file's "not given" (as the map was
        calibrated), and so is ``sequence_mode`` without ``sequence``.  ``text``:
        values may come as text (``"5"``, ``"false"``: ROS 1's parameter server
        keeps what a launch file wrote), converted by the setting's type.
        """
        from topoloc.spec.config import nest, spec_from_dict

        unknown = sorted(set(params) - set(cls.PARAMS))
        if unknown:
            raise TopolocError(f"unknown node parameter {unknown[0]!r}; known: {', '.join(cls.PARAMS)}")
        flat: dict[str, Any] = {}
        for name, value in params.items():
            if value is None:
                continue
            if text:
                value = _from_text(name, value, cls.param_type(name))
            if name == "sequence" and isinstance(value, int) and not isinstance(value, bool) and value < 0:
                continue
            flat[name] = value
        if "sequence" not in flat:
            flat.pop("sequence_mode", None)  # a mode alone: the sequence is the map's, its length and its mode
        return spec_from_dict(cls, nest(flat, names=cls.PARAMS))

    @classmethod
    def params_of(cls, nested: Mapping[str, Any], *, source: str | Path | None = None) -> dict[str, Any]:
        """A configuration file's nested settings as flat parameters; a setting the node lacks is one line."""
        dotted_to_flat = {dotted: flat for flat, dotted in cls.PARAMS.items()}
        where = f" ({source})" if source is not None else ""
        out: dict[str, Any] = {}
        for key, value in nested.items():
            items = ([(f"{key}.{k}", v) for k, v in value.items()] if isinstance(value, Mapping)
                     else [(key, value)])
            for dotted, v in items:
                if dotted not in dotted_to_flat:
                    raise TopolocError(f"unknown setting {dotted} for the ROS node{where}; known: "
                                       f"{', '.join(sorted(dotted_to_flat))}")
                out[dotted_to_flat[dotted]] = v
        return out

    @classmethod
    def defaults(cls) -> dict[str, Any]:
        """Every parameter's default (None: not set, as the map or the environment decides; ``map``: needed)."""
        out: dict[str, Any] = {}
        fields_ = {f.name: f for f in dataclasses.fields(cls)}
        for name, dotted in cls.PARAMS.items():
            head, _, tail = dotted.partition(".")
            f = fields_[head]
            value = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
            out[name] = getattr(value, tail, None) if tail else value
        return out

    @classmethod
    def param_type(cls, name: str) -> type:
        """The type of a parameter's value (``int``, ``float``, ``bool``, ``str``), from the specification's fields."""
        import types
        import typing

        from topoloc.spec.parts import PARTS

        head, _, tail = cls.PARAMS[name].partition(".")
        hint = typing.get_type_hints(PARTS[head] if tail else cls)[tail or head]
        kinds = [a for a in typing.get_args(hint) if a is not type(None)] if isinstance(hint, types.UnionType) \
            else [hint]
        kind = kinds[0]
        return str if kind is Path else kind

    def param_values(self) -> dict[str, Any]:
        """Every parameter's value (None where not set: as the map or the environment decides)."""
        out: dict[str, Any] = {}
        for name, dotted in self.PARAMS.items():
            head, _, tail = dotted.partition(".")
            value = getattr(self, head)
            value = getattr(value, tail) if tail and value is not None else value
            out[name] = os.fspath(value) if isinstance(value, Path) else value
        return out


def _from_text(name: str, value: Any, kind: type) -> Any:
    """A parameter given as text or a number, as ``kind``; anything else is a one-line error naming it."""
    bad = ParameterError(NodeSpec.PARAMS[name], f"must be {_KIND_WORDS[kind]}, got {value!r}")
    if kind is bool:
        if isinstance(value, bool):
            return value
        text = str(value).strip().lower() if isinstance(value, str | int) else ""
        if text not in ("true", "false", "1", "0"):
            raise bad
        return text in ("true", "1")
    if kind in (int, float):
        if isinstance(value, bool) or not isinstance(value, int | float | str):
            raise bad
        try:
            number = float(value)
        except ValueError:
            raise bad from None
        if kind is int:
            if not number.is_integer():
                raise bad
            return int(number)
        return number
    if not isinstance(value, str | int | float | os.PathLike) or isinstance(value, bool):
        raise bad
    return os.fspath(value) if isinstance(value, os.PathLike) else str(value)


_KIND_WORDS = {bool: "true or false", int: "a whole number", float: "a number", str: "text"}


__all__ = ["EARLIER_RUN", "EvaluateSpec", "LocalizeSpec", "MapBuildSpec", "NodeSpec", "VocabTrainSpec",
           "html_page"]
