"""What every frame source shares: the frame record, keyframe selection, a recording as a traverse.

A *source* is a recording read as a stream: a ROS 1 bag, a ROS 2 bag (rosbag2
folder, sqlite3 or MCAP storage) or a video file.  :meth:`FrameSource.frames`
is a generator of :class:`Frame` (time in seconds, pixels, name, position): one
frame is decoded at a time and nothing is kept, so memory does not grow with
the recording's length.  Frames not selected as keyframes are not decoded.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar, NamedTuple, Protocol

import numpy as np

from topoloc._params import Check, Configurable, Constraint
from topoloc.datasets.traverse import IMAGE_SUFFIXES, Traverse
from topoloc.errors import TopolocError, input_error

VIDEO_SUFFIXES = frozenset({
    ".mp4", ".m4v", ".mov", ".avi", ".mkv", ".webm", ".mpg", ".mpeg", ".wmv", ".flv", ".ts", ".mts",
    ".m2ts", ".ogv", ".3gp", ".mjpeg", ".mjpg", ".h264", ".h265", ".hevc",
})


class Frame(NamedTuple):
    """One frame of a recording.

    Attributes
    ----------
    time_s : float
        Seconds: the message's header stamp (else the bag's record time), Unix epoch, for bags;
        seconds from the start for a video.
    image : ndarray of uint8, shape (H, W) grey or (H, W, 3) BGR
    name : str
        ``<file name>#<index>``, the index counting every message of the topic (every video frame).
    xy : tuple of float or None
        Position in metres from the pose or GPS message nearest in time, when the bag has one.
    number : int
        The frame's number in the recording: the ``<index>`` of its name (every message of the
        topic, every video frame counted, kept or not).
    """

    time_s: float
    image: np.ndarray
    name: str
    xy: tuple[float, float] | None = None
    number: int = 0


class FrameSource(Protocol):
    """A recording read one frame at a time."""

    path: Path
    absolute_time: bool  # True when ``time_s`` is a Unix time (bags), False for seconds from the start (video)
    has_positions: bool

    def frames(self) -> Iterator[Frame]:
        """The keyframes, in recording order, decoded one at a time.

        Once they are all read, ``frames_seen`` (where a source has it) is the number of
        frames or messages the recording held, keyframes or not.
        """
        ...

    def __len__(self) -> int:
        """Messages or frames in the recording before keyframe selection (an upper bound; 0 if unknown)."""
        ...


def _distance(value: Any) -> bool:
    return value is None or (isinstance(value, numbers.Real) and not isinstance(value, bool)
                             and math.isfinite(value) and float(value) >= 0)


@dataclass
class Keyframes(Configurable):
    """Keep a frame when ``every_s`` seconds or ``every_m`` metres have passed since the last kept one.

    The first frame is always kept; with neither set, every frame is.  Distance is the straight
    line from the last keyframe's position.
    """

    every_s: float | None = None
    every_m: float | None = None
    _t: float | None = field(default=None, init=False, repr=False)
    _xy: tuple[float, float] | None = field(default=None, init=False, repr=False)

    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {
        "every_s": Check(_distance, "a number >= 0 (or None)"),
        "every_m": Check(_distance, "a number >= 0 (or None)"),
    }

    @classmethod
    def param_owner(cls) -> str:
        return "keyframes"

    def __post_init__(self) -> None:
        self.validate_params()
        if self.every_s is not None and self.every_m is not None:
            raise TopolocError("keyframes: give every_s or every_m, not both")

    def keep(self, time_s: float, xy: tuple[float, float] | None = None) -> bool:
        """Whether the frame at ``time_s`` (at ``xy``) is a keyframe; remembers it if so."""
        if self._t is not None:
            if self.every_s is not None and time_s - self._t < self.every_s:
                return False
            if self.every_m is not None:
                if xy is None or self._xy is None:
                    return False
                if math.hypot(xy[0] - self._xy[0], xy[1] - self._xy[1]) < self.every_m:
                    return False
        elif self.every_m is not None and xy is None:
            return False
        self._t, self._xy = time_s, xy
        return True


def is_bag(path: Path) -> bool:
    """A ROS 1 bag (``.bag`` file) or a ROS 2 bag (a folder with ``metadata.yaml``, or a file in one)."""
    return path.suffix.lower() == ".bag" or (path.is_dir() and (path / "metadata.yaml").is_file()) or (
        path.is_file() and path.suffix.lower() in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file())


def is_stream_input(path: str | Path, *, images_are_files: bool = True) -> bool:
    """Whether ``path`` is read as a recording (bag or video) rather than a folder or an image file.

    A file is a video when its suffix is a video's, or (``images_are_files``) when it is neither
    an image OpenCV can read nor a known image suffix; a folder is a recording only if it is a
    rosbag2 folder.
    """
    p = Path(path)
    if is_bag(p):
        return True
    if not p.is_file():
        return False
    suffix = p.suffix.lower()
    if suffix in VIDEO_SUFFIXES:
        return True
    if suffix in IMAGE_SUFFIXES:
        return False
    if not images_are_files:
        return True
    from topoloc.datasets.decode import has_image_reader

    return p.stat().st_size > 0 and not has_image_reader(p)


def stream_traverse(source: FrameSource, *, name: str | None = None) -> Traverse:
    """The keyframes of a recording as an in-memory traverse (times, and x, y when the bag has positions).

    The keyframes are decoded into memory (grey by default, a third of BGR): a map built from the
    recording needs features of every keyframe anyway.  ``localize`` does not use this; it streams.
    """
    images: list[np.ndarray] = []
    times: list[float] = []
    xy: list[tuple[float, float]] = []
    have_xy = source.has_positions
    for f in source.frames():
        images.append(f.image)
        times.append(f.time_s)
        if have_xy:
            xy.append(f.xy if f.xy is not None else (math.nan, math.nan))
    if not images:
        raise input_error("the recording gives no frames (empty topic or video, or no keyframe)", source.path)
    stamps = None
    if source.absolute_time:
        stamps = np.asarray([round(t * 1e3) for t in times], dtype=np.int64).astype("datetime64[ms]")
    label = name or source.path.name
    trav = Traverse.from_images(images, name=label, times=stamps,
                                xy=np.asarray(xy, dtype=np.float64) if have_xy else None)
    return replace(trav, source=recording_source(source))


def recording_source(source: FrameSource) -> dict[str, Any]:
    """The file and frame selection of a recording: what a map records to name a tour read from it.

    ``{"file": absolute path, "topic", "pose_topic", "every_s", "every_m"}``, leaving out those that are
    unset (a video has no topic).
    """
    keyframes = getattr(source, "keyframes", None)
    found = {"file": str(Path(source.path).resolve()), "topic": getattr(source, "topic", None),
             "pose_topic": getattr(source, "pose_topic", None),
             "every_s": getattr(keyframes, "every_s", None), "every_m": getattr(keyframes, "every_m", None)}
    return {k: v for k, v in found.items() if v is not None}


def describe_source(source: Mapping[str, Any]) -> str:
    """``"rec.bag, topic /cam, every 2 m"``: a recording's file and frame selection in words."""
    parts = [str(source.get("file", "?"))]
    if source.get("topic"):
        parts.append(f"topic {source['topic']}")
    if source.get("every_s") is not None:
        parts.append(f"every {source['every_s']:g} s")
    if source.get("every_m") is not None:
        parts.append(f"every {source['every_m']:g} m" + (f" of {source['pose_topic']}" if source.get("pose_topic")
                                                          else ""))
    return ", ".join(parts)
