"""What each command runs, as one composed, validated specification.

A run specification is a frozen dataclass of a command's own fields (method,
tours, output) and the parts of :mod:`topoloc.spec.parts`.  It is what
``metrics.json`` and a map's header record (:func:`spec_to_dict`), and what a
configuration file holds (:mod:`topoloc.spec.config`), so any run can be made
again from its record.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from topoloc.errors import ParameterError
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


__all__ = ["EARLIER_RUN", "EvaluateSpec", "LocalizeSpec", "MapBuildSpec", "VocabTrainSpec", "html_page"]
