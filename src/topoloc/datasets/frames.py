"""Frames one at a time from image files, folders, ROS bags and videos, every input checked first.

What ``localize`` reads: unlike a :class:`~topoloc.datasets.traverse.Traverse`,
nothing is held in memory but the frame being decoded.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.datasets.traverse import image_entry, natural_key, read_image
from topoloc.errors import input_error
from topoloc.io.paths import not_an_input


def iter_inputs(inputs: Sequence[str | Path]) -> Iterator[Path]:
    """Image files named directly or found in folders (natural order), in the order given.

    Raises
    ------
    TopolocError
        For an input that does not exist or a folder without images (checked before any is yielded).
    """
    files: list[Path] = []
    for item in map(Path, inputs):
        if item.is_dir():
            found = sorted((p for p in item.iterdir() if image_entry(p)),
                           key=lambda p: natural_key(p.name))
            if not found:
                raise input_error("folder holds no images", item)
            files.extend(found)
        elif item.is_file():
            files.append(item)
        else:
            raise input_error(not_an_input(item), item)
    from topoloc.datasets.decode import has_image_reader

    # Before the first frame: an empty file or one no decoder recognises (its header) stops the run
    # here, not after an hour of frames; a file damaged further in still fails when it is reached.
    for f in files:
        if f.stat().st_size == 0:
            raise input_error("image file is empty", f)
        if not has_image_reader(f):
            raise input_error("not an image OpenCV can read", f)
    yield from files


def frame_index(item: tuple[Any, ...]) -> int | None:
    """A frame's number in its input: the fourth of ``(name, time_s, image, index)``; None where a source gives none.

    What a ``localize`` line calls ``frame`` (issue #49): for one input, its index in that input;
    the frames of a recording not kept (``--every-s``, ``--every-m``), of a camera skipped to keep
    up or refused by the decoding leave gaps.
    """
    return int(item[3]) if len(item) > 3 and item[3] is not None else None


def read_frame(path: Path) -> np.ndarray:
    """A grey frame from a file, decoded as the map's own images were (one-line error if unreadable)."""
    return read_image(path, gray=True)


def frame_stream(
    inputs: Sequence[Path], *, topic: str | None = None, every_s: float | None = None, every_m: float | None = None,
    pose_topic: str | None = None, on_frame: Callable[[str], None] | None = None,
    check_name: Callable[[str, Path], None] | None = None,
) -> tuple[int, Iterator[tuple[str, float | None, np.ndarray, int]]]:
    """``(frames at most, iterator of (name, time_s or None, grey image, index))`` over files, folders, bags, videos.

    Every input is opened and checked before the first frame; bags and videos
    are then streamed (one frame decoded at a time, nothing kept).  ``index``
    (:func:`frame_index`) numbers every frame of the inputs in order, a
    recording's frames not kept (``--every-s``, ``--every-m``) included: for one
    input, the frame's index in it (the ``#index`` of a recording's frame name).  ``on_frame``,
    when given, is called before each frame is yielded with the frame's name
    under one image root: ``<folder name>/<file name>`` for an image file
    (named or in a folder), ``<recording stem>/<frame name>`` for a bag or video
    (what ``localize --pairs-out`` writes).  ``check_name(name, file)``, when given, is called on
    each of those names (a recording's: its stem) before the first frame.
    """
    from topoloc.datasets.sources import FrameSource, is_stream_input, open_source

    parts: list[list[Path] | FrameSource] = []
    for item in inputs:
        if is_stream_input(item):
            parts.append(open_source(item, topic=topic, every_s=every_s, every_m=every_m, pose_topic=pose_topic))
        else:
            parts.append(list(iter_inputs([item])))
    total = sum(len(p) for p in parts)
    if check_name is not None:  # the names ``on_frame`` will give, checked before the first frame
        for part in parts:
            if isinstance(part, list):
                for path in part:
                    check_name(f"{path.resolve().parent.name}/{path.name}", path)
            else:
                check_name(Path(part.path).stem, Path(part.path))

    def frames() -> Iterator[tuple[str, float | None, np.ndarray, int]]:
        base = 0  # the frames of the inputs before this one: a recording's all counted, kept or not
        for part in parts:
            if isinstance(part, list):
                for path in part:
                    image = read_frame(path)
                    if on_frame is not None:
                        on_frame(f"{path.resolve().parent.name}/{path.name}")
                    yield path.name, None, image, base
                    base += 1
            else:
                last = -1
                for f in part.frames():
                    if on_frame is not None:
                        on_frame(f"{Path(part.path).stem}/{f.name}")
                    yield f.name, f.time_s, f.image, base + f.number
                    last = f.number
                # Every frame of the recording, the ones after its last keyframe too.
                base += max(last + 1, int(getattr(part, "frames_seen", 0)))

    return total, frames()


__all__ = ["frame_stream", "iter_inputs", "read_frame"]
