"""Live frames: the newest of a producer that does not wait (a camera, a network stream, a ROS topic).

A recording can be read as slowly as the matching goes; a camera cannot: it
keeps sending frames whether or not the last one was matched, and a reader that
takes them in turn falls further behind with every frame.  :class:`Newest` is
the buffer between such a producer and the localiser: the producer's thread
:meth:`~Newest.put` s every frame as it arrives, at most ``keep`` wait (older
ones are dropped and counted in ``skipped``), and :meth:`~Newest.items` hands the
oldest waiting one to the consumer (with ``keep=1``: always the newest), so an
answer is never about a frame older than ``keep`` frames plus the ones being
matched.  ``topoloc localize`` reads cameras and network streams through it
(:class:`LiveSource`), and the ROS node (:mod:`topoloc.ros`) its image topic.

:class:`LiveSource` opens a camera device (``/dev/video0``, or its index ``0``)
or a network stream (``rtsp://``, ``http://`` MJPEG, anything OpenCV's FFmpeg
opens) with OpenCV and reads it on its own thread while frames are matched.

A stream of JPEGs (MJPEG over HTTP or RTSP, as FFmpeg opens it) is read as its
JPEGs, each decoded by the one rule of :mod:`topoloc.datasets.decode` that image
files and ROS ``CompressedImage`` messages go through: a truncated JPEG is
refused, not filled in by the decoder, and a JPEG whose header announces too
many pixels is refused before it is decoded (issue #49).  A refused frame is
skipped and counted (``frames_bad``), as the ROS node counts its own, and the
stream goes on; before, one part of random bytes ended the stream.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import re
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np

from topoloc.datasets.decode import decode_bytes, to_gray
from topoloc.errors import TopolocError

log = logging.getLogger(__name__)

T = TypeVar("T")

#: How long a waiting consumer sleeps before it looks again whether it should stop.
_POLL_S = 0.05

#: Schemes of network streams OpenCV's FFmpeg reads (a URL with another scheme is not taken for a stream).
STREAM_SCHEMES = ("rtsp", "rtsps", "rtmp", "http", "https", "udp", "tcp", "srt")


class Newest(Generic[T]):
    """The ``keep`` newest items a producer put, handed to one consumer oldest first; older ones dropped, counted.

    Parameters
    ----------
    keep : int
        Items that may wait (>= 1): 1 is the newest-frame policy; more smooths
        out a slow frame at the cost of answers up to ``keep`` frames old.

    Attributes
    ----------
    received, skipped, taken : int
        Items put, dropped unseen (a newer one arrived while ``keep`` waited), and handed over.
    """

    def __init__(self, keep: int = 1) -> None:
        if isinstance(keep, bool) or not isinstance(keep, int) or keep < 1:
            raise TopolocError(f"queue must be a whole number >= 1, got {keep!r}")
        self.keep = keep
        self._items: collections.deque[T] = collections.deque()
        self._cond = threading.Condition()
        self._closed = False
        self._error: BaseException | None = None
        self.received = 0
        self.skipped = 0
        self.taken = 0

    def put(self, item: T) -> None:
        """Add the producer's newest item (any thread); the oldest waiting one is dropped past ``keep``."""
        with self._cond:
            self.received += 1
            self._items.append(item)
            while len(self._items) > self.keep:
                self._items.popleft()
                self.skipped += 1
            self._cond.notify()

    def resize(self, keep: int) -> None:
        """Let ``keep`` items wait from now on (a node's ``queue`` changed); the oldest beyond it are skipped."""
        if isinstance(keep, bool) or not isinstance(keep, int) or keep < 1:
            raise TopolocError(f"queue must be a whole number >= 1, got {keep!r}")
        with self._cond:
            self.keep = keep
            while len(self._items) > keep:
                self._items.popleft()
                self.skipped += 1

    def close(self, error: BaseException | None = None) -> None:
        """No more items: the consumer gets what waits, then the end (or ``error``, raised in its thread)."""
        with self._cond:
            self._closed = True
            self._error = error
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed

    def items(self, *, stop: Callable[[], bool] | None = None, rate: float = 0.0) -> Iterator[T]:
        """The items as they come, until :meth:`close` (then the producer's error, if any) or ``stop()``.

        ``rate`` > 0: at most that many items a second (the ones put meanwhile
        are dropped and counted as ``skipped``, as when matching is slow).
        """
        last = -float("inf")
        while True:
            if rate > 0:  # wait out the interval first, so that the item taken is the newest after it
                wait = last + 1.0 / rate - time.monotonic()
                while wait > 0 and not (stop is not None and stop()):
                    time.sleep(min(wait, _POLL_S))
                    wait = last + 1.0 / rate - time.monotonic()
            with self._cond:
                while not self._items and not self._closed:
                    if stop is not None and stop():
                        return
                    self._cond.wait(_POLL_S)
                if stop is not None and stop():
                    return
                if not self._items:  # closed and drained
                    if self._error is not None:
                        raise self._error
                    return
                item = self._items.popleft()
                self.taken += 1
            last = time.monotonic()
            yield item

    def counts(self) -> dict[str, int]:
        """``received``, ``skipped`` and ``waiting`` (put, not yet taken nor dropped)."""
        with self._cond:
            return {"received": self.received, "skipped": self.skipped, "waiting": len(self._items)}


def is_live_source(text: str) -> bool:
    """Whether a command-line input names a camera or a network stream rather than a file or folder.

    A stream URL (``rtsp://``, ``http://`` ...), a character device (``/dev/video0``), or a
    bare index (``0``) that names no file here.
    """
    scheme = re.match(r"^([a-zA-Z][a-zA-Z0-9+.-]*)://", text)
    if scheme:
        return scheme.group(1).lower() in STREAM_SCHEMES
    p = Path(text)
    if text.isdigit() and not p.exists():
        return True
    with contextlib.suppress(OSError):
        import stat

        return stat.S_ISCHR(p.stat().st_mode)
    return False


#: FourCC codes of streams whose packets are whole JPEGs (FFmpeg's mjpeg codec).
_JPEG_CODECS = frozenset({"MJPG", "JPEG", "AVRN", "LJPG", "JPGL", "MJLS"})


def _own_jpegs(cap: Any) -> bool:
    """Ask OpenCV's FFmpeg for the stream's packets undecoded, where each is a JPEG; whether it gives them.

    A camera (V4L2) and a stream of another codec (H.264) keep OpenCV's decoding: their
    frames are not image files, and no other source gives the same bytes.
    """
    import cv2

    try:
        if cap.getBackendName() != "FFMPEG":
            return False
        code = int(cap.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little").decode("latin-1").upper()
    except (cv2.error, OverflowError, ValueError):
        return False
    return code in _JPEG_CODECS and bool(cap.set(cv2.CAP_PROP_FORMAT, -1))


def _redacted(url: str) -> str:
    """A stream's name as said in messages: a password in the URL is not printed."""
    return re.sub(r"//([^:/@]+):[^@/]*@", r"//\1:***@", url)


class LiveSource:
    """A camera or network stream read by OpenCV on its own thread, newest frames first (:class:`Newest`).

    Parameters
    ----------
    source : str
        ``/dev/videoN``, a camera index, or a stream URL.
    keep : int
        Frames that may wait to be matched (:class:`Newest`).
    open_timeout_s : float
        How long opening (and each read) may take before the stream counts as not
        opened (or stopped).

    Raises
    ------
    TopolocError
        One line naming the source when OpenCV cannot open it or it gives no frame.
    """

    absolute_time = True
    has_positions = False

    def __init__(self, source: str, *, keep: int = 1, open_timeout_s: float = 10.0) -> None:
        import os

        # FFmpeg's own log lines (a refused connection, a stream cut short) would come on top of the
        # one line that names the stream; set before OpenCV's FFmpeg backend is first used.
        os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
        import cv2

        self.source = source
        self._timeout_s = open_timeout_s
        self.name = _redacted(source)
        self.buffer: Newest[tuple[int, float, np.ndarray]] = Newest(keep)
        self.frames_read = 0
        #: Frames refused by the decoding rule (random bytes, a truncated or too large JPEG): skipped, counted.
        self.frames_bad = 0
        self.stopped_by: str | None = None
        target: int | str = int(source) if source.isdigit() else source
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, int(open_timeout_s * 1e3),
                  cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(open_timeout_s * 1e3)]
        cap = cv2.VideoCapture(target, cv2.CAP_ANY, params)
        if not cap.isOpened():
            cap.release()
            raise TopolocError(f"cannot open the camera or stream: {self.name}")
        #: Whether the frames are the stream's own JPEGs (decoded here, by the one rule), not FFmpeg's pixels.
        self.encoded = _own_jpegs(cap)
        ok, first = cap.read()
        if not ok or first is None or first.size == 0:
            cap.release()
            raise TopolocError(f"the camera or stream gives no frame: {self.name}")
        self._cap = cap
        self._stop = threading.Event()
        self._put(first)
        self._thread = threading.Thread(target=self._read, name="topoloc-live", daemon=True)
        self._thread.start()

    def _put(self, image: np.ndarray) -> None:
        self.buffer.put((self.frames_read, time.time(), image))
        self.frames_read += 1

    def _skip(self, name: str, exc: TopolocError) -> None:
        self.frames_bad += 1
        if self.frames_bad == 1 or self.frames_bad % 100 == 0:  # said, not once a frame
            log.warning("frame skipped (%d so far): %s", self.frames_bad, exc)

    def _read(self) -> None:
        try:
            while not self._stop.is_set():
                ok, img = self._cap.read()
                if not ok or img is None or img.size == 0:
                    self.stopped_by = "stream"
                    break
                self._put(img)
        except Exception as exc:  # OpenCV raising mid-stream is a stop, said in one line by the consumer
            self.stopped_by = f"stream ({type(exc).__name__}: {exc})"
        finally:
            self._cap.release()
            self.buffer.close()

    def frames(self, *, stop: Callable[[], bool] | None = None, rate: float = 0.0,
               ) -> Iterator[tuple[str, float, np.ndarray, int]]:
        """``(name, wall-clock time of capture, grey image, index)`` of the newest frames, until the end or ``stop()``.

        ``index`` is the frame's number in the stream (``name`` ends ``#index``): frames
        skipped to keep up, or refused, leave gaps.  Decoding (a stream's JPEGs, by
        :func:`~topoloc.datasets.decode.decode_bytes`) and the conversion to grey run here,
        on the consumer's reading thread, so that the capture thread does nothing but
        keep up with the stream; a frame the decoding refuses is skipped and counted.
        """
        try:
            for k, t, payload in self.buffer.items(stop=stop, rate=rate):
                name = f"{self.name}#{k}"
                if self.encoded:
                    try:
                        image = decode_bytes(payload, name, gray=True)
                    except TopolocError as exc:
                        self._skip(name, exc)
                        continue
                else:
                    image = to_gray(payload)
                yield name, t, image, k
        finally:
            self.stop()

    def stop(self) -> None:
        """Stop reading, from any thread or a signal handler: the frames waiting are still handed over."""
        self._stop.set()
        self.buffer.close()

    def close(self) -> None:
        """Stop reading and wait for the capture to be released (at most a read's timeout)."""
        self.stop()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=self._timeout_s + 1.0)

    def __len__(self) -> int:
        return 0  # unknown: a live stream has no length

    def __repr__(self) -> str:
        return f"LiveSource({self.name!r})"


__all__ = ["STREAM_SCHEMES", "LiveSource", "Newest", "is_live_source"]
