"""ROS 1 bags and ROS 2 bags (sqlite3 or MCAP storage) as streams of frames, without ROS.

Read with the pure-Python ``rosbags`` package (``pip install 'topoloc[ros]'``).  Image topics are
``sensor_msgs/Image`` (encodings in :data:`ENCODINGS`) or ``sensor_msgs/CompressedImage`` (JPEG,
PNG, anything ``cv2.imdecode`` reads).  A frame's time is its header stamp (the bag's record time
when the stamp is zero).  Positions come from the odometry, pose or GPS message nearest in time
(``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped``, ``geometry_msgs/PoseWithCovarianceStamped``,
``sensor_msgs/NavSatFix``; latitude/longitude projected to UTM metres in the zone of the first fix),
read by a second reader that advances with the images, so neither the images nor the poses are
held in memory.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from topoloc.datasets.decode import decode_bytes, to_bgr, to_gray
from topoloc.datasets.projection import UTMProjection
from topoloc.datasets.sources.base import Frame, Keyframes
from topoloc.errors import TopolocError, input_error

IMAGE_TYPES = ("sensor_msgs/Image", "sensor_msgs/CompressedImage")
POSE_TYPES = ("nav_msgs/Odometry", "geometry_msgs/PoseStamped", "geometry_msgs/PoseWithCovarianceStamped",
              "sensor_msgs/NavSatFix")

# encoding -> (bytes per channel, channels, cv2 code to BGR); None = already BGR, BGRA or grey.  Every
# frame is brought to BGR (or kept grey) as stored and then converted to grey by the one
# ``datasets.decode.to_gray``, as image files are, so the same frame gives the same pixels from either.
ENCODINGS: dict[str, tuple[int, int, int | None]] = {
    "mono8": (1, 1, None), "8uc1": (1, 1, None), "mono16": (2, 1, None), "16uc1": (2, 1, None),
    "bgr8": (1, 3, None), "8uc3": (1, 3, None), "bgr16": (2, 3, None), "16uc3": (2, 3, None),
    "rgb8": (1, 3, cv2.COLOR_RGB2BGR), "rgb16": (2, 3, cv2.COLOR_RGB2BGR),
    "bgra8": (1, 4, None), "8uc4": (1, 4, None), "rgba8": (1, 4, cv2.COLOR_RGBA2BGR),
    # ROS names the Bayer pattern from the top-left pixel, OpenCV from the second row (as cv_bridge maps them).
    "bayer_rggb8": (1, 1, cv2.COLOR_BayerBG2BGR), "bayer_bggr8": (1, 1, cv2.COLOR_BayerRG2BGR),
    "bayer_gbrg8": (1, 1, cv2.COLOR_BayerGR2BGR), "bayer_grbg8": (1, 1, cv2.COLOR_BayerGB2BGR),
    "uyvy": (1, 2, cv2.COLOR_YUV2BGR_UYVY), "yuv422": (1, 2, cv2.COLOR_YUV2BGR_UYVY),
    "yuyv": (1, 2, cv2.COLOR_YUV2BGR_YUYV), "yuv422_yuy2": (1, 2, cv2.COLOR_YUV2BGR_YUYV),
}
MISSING_EXTRA = "reading ROS bags needs the rosbags package: pip install 'topoloc[ros]'"


def _short(msgtype: str | None) -> str:
    """``sensor_msgs/msg/Image`` (how rosbags names ROS 1 and ROS 2 types alike) -> ``sensor_msgs/Image``."""
    return (msgtype or "").replace("/msg/", "/")


def _rosbags(path: Path) -> Any:
    try:
        from rosbags import highlevel, typesys
    except ImportError:
        raise input_error(MISSING_EXTRA, path) from None
    return highlevel, typesys


def decode_image(msg: Any, msgtype: str, *, gray: bool, where: str, path: Path) -> np.ndarray:
    """Pixels of a ``sensor_msgs/Image`` or ``CompressedImage`` message (uint8, grey or BGR).

    Raises
    ------
    TopolocError
        For an unknown encoding, a message whose data does not hold its size, or compressed data
        OpenCV cannot decode (naming ``where``, the topic and message, and the bag).
    """
    data = np.frombuffer(memoryview(msg.data), dtype=np.uint8)
    if _short(msgtype) == "sensor_msgs/CompressedImage":
        fmt = str(getattr(msg, "format", ""))
        if "compresseddepth" in fmt.lower().replace(" ", ""):
            raise input_error(f"{where}: compressedDepth images are not supported (format {fmt!r})", path)
        # The same decoding as an image file's, so a frame gives the same pixels from a folder or a bag.
        return decode_bytes(data, path, gray=gray, context=f"{where} (format {fmt!r}): compressed ")
    encoding = str(msg.encoding)
    spec = ENCODINGS.get(encoding.strip().lower())
    if spec is None:
        raise input_error(f"{where}: image encoding {encoding!r} is not supported (supported: "
                          f"{', '.join(sorted(ENCODINGS))})", path)
    size, channels, code = spec
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * channels * size
    if h <= 0 or w <= 0 or step < row or data.size < step * (h - 1) + row:
        raise input_error(f"{where}: {data.size} bytes of data do not hold a {w}x{h} {encoding} image "
                          f"(step {step})", path)
    rows = np.lib.stride_tricks.as_strided(data, shape=(h, row), strides=(step, 1))
    if size == 2:
        big = bool(getattr(msg, "is_bigendian", False))
        words = np.ascontiguousarray(rows).view(">u2" if big else "<u2")
        pixels = (words >> 8).astype(np.uint8)  # the 8 most significant bits
    else:
        pixels = np.ascontiguousarray(rows)
    pixels = pixels.reshape(h, w, channels) if channels > 1 else pixels.reshape(h, w)
    if code is None:
        return to_gray(pixels) if gray else to_bgr(pixels)
    bgr = to_bgr(pixels, code)
    return to_gray(bgr) if gray else bgr


def _stamp(msg: Any) -> float | None:
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if stamp is None:
        return None
    t = int(getattr(stamp, "sec", 0)) + 1e-9 * int(getattr(stamp, "nanosec", getattr(stamp, "nsec", 0)))
    return t if t > 0 else None


class BagSource:
    """One image topic of a ROS 1 or ROS 2 bag, streamed (see the module docstring).

    Opening lists the topics, checks ``topic`` (the bag's image topics named when it is missing),
    finds the pose or GPS topic, and decodes the first image so that an unsupported encoding stops
    before any work.
    """

    absolute_time = True

    def __init__(self, path: Path, *, topic: str | None = None, keyframes: Keyframes | None = None,
                 pose_topic: str | None = None, gray: bool = True) -> None:
        if path.is_file() and path.suffix.lower() in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
            path = path.parent  # a storage file of a rosbag2 folder: the folder
        self.frames_seen = 0  # messages of the image topic, once frames() has read them all
        self.path = path
        self.gray = gray
        self.keyframes = keyframes or Keyframes()
        self._highlevel, self._typesys = _rosbags(path)
        with self._open() as reader:
            topics = {name: (_short(info.msgtype), info.msgcount) for name, info in reader.topics.items()}
        images = sorted(t for t, (ty, _) in topics.items() if ty in IMAGE_TYPES)
        listed = f"image topics: {', '.join(images)}" if images else \
            "it has no sensor_msgs/Image or CompressedImage topic"
        if topic is None:
            if len(images) != 1:
                raise input_error(f"give the image topic with topic=NAME ({listed})", path)
            topic = images[0]
        elif topic not in topics:
            raise input_error(f"topic {topic} is not in the bag ({listed})", path)
        elif topics[topic][0] not in IMAGE_TYPES:
            raise input_error(f"topic {topic} is {topics[topic][0]}, not an image topic ({listed})", path)
        self.topic = topic
        self._count = int(topics[topic][1])
        if not self._count:  # localize gave no line and exit 0 (issue #41); map build refused later
            raise input_error(f"image topic {topic} has no messages", path)
        poses = sorted((t for t, (ty, n) in topics.items() if ty in POSE_TYPES and n),
                       key=lambda t: (POSE_TYPES.index(topics[t][0]), t))
        if pose_topic is not None:
            if pose_topic not in topics or topics[pose_topic][0] not in POSE_TYPES:
                raise input_error(f"pose topic {pose_topic} is not an odometry, pose or GPS topic of the bag "
                                  f"(those: {', '.join(poses) or 'none'})", path)
            if not topics[pose_topic][1]:
                raise input_error(f"pose topic {pose_topic} has no messages", path)
        self.pose_topic = pose_topic if pose_topic is not None else (poses[0] if poses else None)
        self.has_positions = self.pose_topic is not None
        if self.keyframes.every_m is not None and not self.has_positions:
            raise input_error("every_m needs an odometry, pose or GPS topic (nav_msgs/Odometry, "
                              "geometry_msgs/PoseStamped, sensor_msgs/NavSatFix); the bag has none", path)
        if self._count:
            next(self._raw_images(limit=1), None)  # decodes the first image: fails here, not later

    def __len__(self) -> int:
        return self._count

    def __repr__(self) -> str:
        return f"BagSource({str(self.path)!r}, topic={self.topic!r}, pose_topic={self.pose_topic!r})"

    @contextmanager
    def _open(self) -> Iterator[Any]:
        """An open ``AnyReader``; any failure of rosbags becomes one line naming the bag."""
        highlevel, typesys = self._highlevel, self._typesys
        kind = "ROS 1 bag" if self.path.suffix.lower() == ".bag" else "ROS 2 bag"
        try:
            reader = highlevel.AnyReader([self.path],
                                         default_typestore=typesys.get_typestore(typesys.Stores.ROS2_HUMBLE))
            reader.open()
        except TopolocError:
            raise
        except Exception as exc:  # rosbags raises many types for a damaged or foreign file
            raise input_error(f"not a readable {kind} ({type(exc).__name__}: {exc})", self.path) from None
        try:
            yield reader
        except (TopolocError, GeneratorExit):
            raise
        except Exception as exc:
            raise input_error(f"{kind} is damaged ({type(exc).__name__}: {exc})", self.path) from None
        finally:
            try:
                reader.close()
            except Exception:  # closing a damaged bag must not hide the first error
                pass

    def _messages(self, topic: str, limit: int | None = None) -> Iterator[tuple[int, int, Any, str]]:
        """``(index, record time ns, deserialised message, msgtype)`` of ``topic``, one at a time."""
        with self._open() as reader:
            conns = [c for c in reader.connections if c.topic == topic]
            for k, (conn, t_ns, raw) in enumerate(reader.messages(connections=conns)):
                if limit is not None and k >= limit:
                    return
                yield k, t_ns, reader.deserialize(raw, conn.msgtype), conn.msgtype

    def _raw_images(self, limit: int | None = None) -> Iterator[np.ndarray]:
        for k, _, msg, msgtype in self._messages(self.topic, limit):
            yield decode_image(msg, msgtype, gray=self.gray, where=f"topic {self.topic} message {k}", path=self.path)

    def positions(self) -> Iterator[tuple[float, tuple[float, float]]]:
        """``(time_s, (x, y) metres)`` of every usable message of the pose topic, in bag order."""
        if self.pose_topic is None:
            return
        project: Callable[[float, float], tuple[float, float]] | None = None
        for _, t_ns, msg, msgtype in self._messages(self.pose_topic):
            t = _stamp(msg) or t_ns * 1e-9
            kind = _short(msgtype)
            if kind == "sensor_msgs/NavSatFix":
                lat, lon = float(msg.latitude), float(msg.longitude)
                if int(getattr(msg.status, "status", 0)) < 0 or not (math.isfinite(lat) and math.isfinite(lon)):
                    continue  # no fix
                if project is None:
                    proj = UTMProjection.fit(np.array([lat]), np.array([lon]), source=self.path)

                    def project(a: float, b: float, proj: UTMProjection = proj) -> tuple[float, float]:
                        x, y = proj(np.array([a]), np.array([b]), source=self.path)[0]
                        return float(x), float(y)
                yield t, project(lat, lon)
            else:
                pose = msg.pose.pose if kind != "geometry_msgs/PoseStamped" else msg.pose
                yield t, (float(pose.position.x), float(pose.position.y))

    def frames(self) -> Iterator[Frame]:
        """The keyframes of the image topic (see :class:`~topoloc.datasets.sources.base.Keyframes`)."""
        keep = replace(self.keyframes)  # fresh state for each pass
        nearest = _Nearest(self.positions()) if self.has_positions else None
        name = self.path.name
        self.frames_seen = 0
        for k, t_ns, msg, msgtype in self._messages(self.topic):
            self.frames_seen = k + 1
            t = _stamp(msg) or t_ns * 1e-9
            xy = nearest.at(t) if nearest is not None else None
            if not keep.keep(t, xy):
                continue
            img = decode_image(msg, msgtype, gray=self.gray, where=f"topic {self.topic} message {k}", path=self.path)
            yield Frame(t, img, f"{name}#{k}", xy, k)


class _Nearest:
    """The position nearest in time, from a time-ordered stream read only as far as needed."""

    def __init__(self, stream: Iterator[tuple[float, tuple[float, float]]]) -> None:
        self._stream = stream
        self._prev: tuple[float, tuple[float, float]] | None = None
        self._next = next(stream, None)

    def at(self, t: float) -> tuple[float, float] | None:
        while self._next is not None and self._next[0] <= t:
            self._prev, self._next = self._next, next(self._stream, None)
        best = [p for p in (self._prev, self._next) if p is not None]
        return min(best, key=lambda p: abs(p[0] - t))[1] if best else None
