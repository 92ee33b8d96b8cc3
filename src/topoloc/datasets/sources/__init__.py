"""Recordings as traverses: ROS 1 / ROS 2 bags (``rosbag``) and video files (``video``), streamed.

:func:`open_source` opens one (checks first), :meth:`FrameSource.frames` yields
:class:`Frame` ``(time_s, image, name, xy)`` lazily, :func:`stream_traverse` / :func:`load_input`
give an in-memory :class:`~topoloc.datasets.traverse.Traverse` of the keyframes (map building,
evaluation); ``topoloc localize`` streams frames without keeping them.
"""

from topoloc.datasets.sources.base import (
    VIDEO_SUFFIXES,
    Frame,
    FrameSource,
    Keyframes,
    describe_source,
    is_bag,
    is_stream_input,
    recording_source,
    stream_traverse,
)
from topoloc.datasets.sources.recording import load_input, open_source

__all__ = [
    "VIDEO_SUFFIXES",
    "Frame",
    "FrameSource",
    "Keyframes",
    "describe_source",
    "is_bag",
    "is_stream_input",
    "load_input",
    "open_source",
    "recording_source",
    "stream_traverse",
]
