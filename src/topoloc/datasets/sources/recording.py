"""Opening a path as a recording: the bag or video source that reads it (:func:`open_source`).

Apart from :mod:`~topoloc.datasets.sources.base`, which the sources import,
so that no source module and the module choosing among them import each other.
"""

from __future__ import annotations

from pathlib import Path

from topoloc.datasets.sources.base import FrameSource, Keyframes, is_bag, is_stream_input, stream_traverse
from topoloc.datasets.traverse import Traverse, load_traverse
from topoloc.errors import ParameterError, input_error
from topoloc.io.paths import not_an_input


def open_source(
    path: str | Path, *, topic: str | None = None, every_s: float | None = None, every_m: float | None = None,
    pose_topic: str | None = None, gray: bool = True,
) -> FrameSource:
    """Open a bag or a video for streaming; every check that can fail early is made here.

    Parameters
    ----------
    path : path
        A ``.bag`` file, a rosbag2 folder, or a video file.
    topic : str, optional
        Image topic of a bag (sensor_msgs/Image or CompressedImage); may be left out when the bag
        has one image topic.  Ignored for a video.
    every_s, every_m : float, optional
        Keyframes: one every ``every_s`` seconds, or every ``every_m`` metres (bags with an
        odometry, pose or GPS topic).
    pose_topic : str, optional
        The pose/GPS topic (default: the first odometry, else pose, else GPS topic of the bag).
    gray : bool
        Decode frames grey (as ``localize`` and feature extraction read images) or BGR.

    Raises
    ------
    TopolocError
        Naming the file: not a bag or video, a missing topic (the bag's image topics listed),
        ``--every-m`` without positions, the ``rosbags`` package missing.
    """
    p = Path(path)
    keyframes = Keyframes(every_s=every_s, every_m=every_m)
    if not p.is_file() and not p.is_dir():  # a bag is a file (ROS 1) or a folder (ROS 2), a video a file
        raise input_error(not_an_input(p), p)
    if is_bag(p):
        from topoloc.datasets.sources.rosbag import BagSource

        return BagSource(p, topic=topic, keyframes=keyframes, pose_topic=pose_topic, gray=gray)
    from topoloc.datasets.sources.video import VideoSource

    if every_m is not None:
        raise ParameterError("inputs.every_m", f"needs positions: a bag with an odometry, pose or GPS topic, not a "
                                               f"video: {p}")
    return VideoSource(p, keyframes=keyframes, gray=gray)


def load_input(
    path: str | Path, *, topic: str | None = None, every_s: float | None = None, every_m: float | None = None,
    pose_topic: str | None = None,
) -> Traverse:
    """A traverse from a folder (``load_traverse``), or from a bag or video (:func:`stream_traverse`).

    ``topic``, ``every_s``, ``every_m`` and ``pose_topic`` apply to recordings only (a command may
    take folders and recordings together).
    """
    p = Path(path)
    if p.exists() and not p.is_file() and not p.is_dir():  # a named pipe, a device...: said what it is
        raise input_error(not_an_input(p), p)
    if is_bag(p) or (p.is_file() and is_stream_input(p, images_are_files=False)):
        return stream_traverse(open_source(p, topic=topic, every_s=every_s, every_m=every_m,
                                           pose_topic=pose_topic))
    return load_traverse(p)
