"""Options and helpers for commands that read ROS bags and videos as well as image folders."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from topoloc.errors import TopolocError

if TYPE_CHECKING:  # numpy is not imported when the command line starts
    import numpy as np

TopicOption = Annotated[str | None, typer.Option(
    "--topic", help="Image topic of ROS bags (sensor_msgs/Image or CompressedImage); needed when a bag has "
                    "several.")]
EverySOption = Annotated[float | None, typer.Option(
    "--every-s", help="Bags and videos: keep one frame every T seconds.")]
EveryMOption = Annotated[float | None, typer.Option(
    "--every-m", help="Bags with an odometry, pose or GPS topic: keep one frame every D metres.")]
PoseTopicOption = Annotated[str | None, typer.Option(
    "--pose-topic", help="Bags: the odometry, pose or GPS topic for --every-m and x, y (default: the bag's first).")]


def check_recording_options(paths: list[Path], topic: str | None, every_s: float | None,
                            every_m: float | None, pose_topic: str | None = None) -> None:
    """Refuse --topic/--every-s/--every-m/--pose-topic when no input is a bag or a video (they would do nothing)."""
    from topoloc.datasets.sources import is_stream_input

    given = [flag for flag, v in (("--topic", topic), ("--every-s", every_s), ("--every-m", every_m),
                                  ("--pose-topic", pose_topic)) if v is not None]
    # A missing input is left to the loaders, whose message names it.
    if given and all(p.exists() for p in paths) and not any(is_stream_input(p, images_are_files=False)
                                                            for p in paths):
        verb = "applies" if len(given) == 1 else "apply"
        raise TopolocError(f"{'/'.join(given)} {verb} to ROS bags and videos only, and no input is one")


def load_tours(paths: list[Path], topic: str | None, every_s: float | None, every_m: float | None,
               pose_topic: str | None = None) -> list[Any]:
    """Traverses from folders, bags and videos (the keyframes of a recording held in memory)."""
    from topoloc.datasets.sources import load_input

    check_recording_options(paths, topic, every_s, every_m, pose_topic)
    return [load_input(p, topic=topic, every_s=every_s, every_m=every_m, pose_topic=pose_topic) for p in paths]


def localize_frames(
    inputs: list[Path], *, topic: str | None, every_s: float | None, every_m: float | None,
    pose_topic: str | None = None,
) -> tuple[int, Iterator[tuple[str, float | None, np.ndarray]]]:
    """``(frames at most, iterator of (name, time_s or None, grey image))`` over image files, folders, bags, videos.

    Every input is opened and checked before the first frame; bags and videos are then streamed
    (one frame decoded at a time, nothing kept).
    """
    from topoloc.datasets.sources import FrameSource, is_stream_input, open_source
    from topoloc.maps.map import iter_inputs, read_frame

    check_recording_options(inputs, topic, every_s, every_m, pose_topic)
    parts: list[list[Path] | FrameSource] = []
    for item in inputs:
        if is_stream_input(item):
            parts.append(open_source(item, topic=topic, every_s=every_s, every_m=every_m, pose_topic=pose_topic))
        else:
            parts.append(list(iter_inputs([item])))
    total = sum(len(p) for p in parts)

    def frames() -> Iterator[tuple[str, float | None, np.ndarray]]:
        for part in parts:
            if isinstance(part, list):
                for path in part:
                    yield path.name, None, read_frame(path)
            else:
                for f in part.frames():
                    yield f.name, f.time_s, f.image

    return total, frames()
