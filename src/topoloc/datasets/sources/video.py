"""A video file (anything OpenCV's ``VideoCapture`` opens) as a stream of frames.

A frame's time is its position in the video in seconds (``CAP_PROP_POS_MSEC``, else index / fps);
a video has no absolute clock, so its traverse has no ``times``.  Frames that are not keyframes are
grabbed but not decoded into pixels.

A damaged frame or a file cut short stops the reading with one line naming the file and the first
frame not read, rather than a map or a localisation of the frames before it that looks complete:
OpenCV ends the stream at the first frame it cannot demultiplex or decode, and containers that
record their number of frames (:data:`COUNTED_SUFFIXES`) tell that the stream ended early.  Other
containers only estimate it from their duration, so there a short stream is taken as it is.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import cv2

from topoloc.datasets.decode import to_bgr, to_gray
from topoloc.datasets.sources.base import Frame, Keyframes
from topoloc.errors import input_error

#: Containers whose header states the number of frames, so that a stream ending before it is damage.
COUNTED_SUFFIXES = frozenset({".avi", ".mp4", ".m4v", ".mov"})


class VideoSource:
    """A video read one frame at a time; opening checks that OpenCV opens it and that it has a frame."""

    absolute_time = False
    has_positions = False

    def __init__(self, path: Path, *, keyframes: Keyframes | None = None, gray: bool = True) -> None:
        self.path = path
        self.gray = gray
        self.keyframes = keyframes or Keyframes()
        self.frames_seen = 0  # frames of the video, once frames() has read them all
        if not path.is_file():
            raise input_error("video is not a file", path)
        if path.stat().st_size == 0:
            raise input_error("video file is empty", path)
        cap = self._capture()
        try:
            self.fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
            self._count = max(int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0), 0)
            ok, first = cap.read()
            if not ok or first is None or first.size == 0:
                raise input_error("video has no frame OpenCV can decode", path)
        finally:
            cap.release()

    def __len__(self) -> int:
        return self._count

    def __repr__(self) -> str:
        return f"VideoSource({str(self.path)!r})"

    def _capture(self) -> cv2.VideoCapture:
        try:
            str(self.path).encode("utf-8")
        except UnicodeEncodeError:  # OpenCV takes names as UTF-8: another encoding's bytes crashed it (issue #41)
            raise input_error("video file name is not UTF-8, which OpenCV cannot open: rename it", self.path) from None
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            cap.release()
            raise input_error("not a bag, image or video OpenCV can open", self.path)
        return cap

    def frames(self) -> Iterator[Frame]:
        """The keyframes (``every_s``), decoded one at a time."""
        keep = replace(self.keyframes)
        cap = self._capture()
        name = self.path.name
        try:
            k = 0
            while cap.grab():
                msec = float(cap.get(cv2.CAP_PROP_POS_MSEC) or 0.0)
                t = msec / 1e3 if (msec > 0 or k == 0) else (k / self.fps if self.fps > 0 else float(k))
                if keep.keep(t):
                    ok, img = cap.retrieve()
                    if not ok or img is None or img.size == 0:
                        raise input_error(f"frame {k} of the video cannot be decoded", self.path)
                    # OpenCV gives video frames as BGR; the conversion is the one image files get.
                    img = to_gray(img) if self.gray else to_bgr(img)
                    yield Frame(t, img, f"{name}#{k}", None, k)
                k += 1
            self.frames_seen = k
            if k < self._count and self.path.suffix.lower() in COUNTED_SUFFIXES:
                raise input_error(f"frame {k} of the video cannot be read (damaged, or the file ends early: "
                                  f"{k} of its {self._count} frames read)", self.path)
        finally:
            cap.release()
