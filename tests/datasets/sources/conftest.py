"""Tiny recordings written in the test: ROS 1 / ROS 2 bags with ``rosbags`` and a video with OpenCV."""

from __future__ import annotations

import inspect
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

T0 = 1_700_000_000  # first stamp, seconds (Unix time)


def frames_of(n: int = 6, h: int = 96, w: int = 128, seed: int = 0) -> list[np.ndarray]:
    """``n`` textured grey images that differ from each other."""
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.integers(0, 256, (h, w * 3), dtype=np.uint8), (5, 5), 0)
    return [np.ascontiguousarray(base[:, 16 * k: 16 * k + w]) for k in range(n)]


def _messages(ts: Any, ros1: bool) -> dict[str, Callable[..., Any]]:
    t = ts.types

    def header(sec: float) -> Any:
        stamp = t["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=round((sec % 1) * 1e9))
        if ros1:
            return t["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="cam")
        return t["std_msgs/msg/Header"](stamp=stamp, frame_id="cam")

    def raw(sec: float, img: np.ndarray, encoding: str) -> Any:
        data = np.ascontiguousarray(img).reshape(-1).view(np.uint8)
        step = data.size // img.shape[0]
        return t["sensor_msgs/msg/Image"](header=header(sec), height=img.shape[0], width=img.shape[1],
                                          encoding=encoding, is_bigendian=0, step=step, data=data)

    def compressed(sec: float, jpeg: bytes) -> Any:
        return t["sensor_msgs/msg/CompressedImage"](header=header(sec), format="jpeg",
                                                    data=np.frombuffer(jpeg, np.uint8).copy())

    def odometry(sec: float, x: float, y: float) -> Any:
        point = t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0)
        quat = t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
        pose = t["geometry_msgs/msg/PoseWithCovariance"](pose=t["geometry_msgs/msg/Pose"](
            position=point, orientation=quat), covariance=np.zeros(36))
        vec = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        twist = t["geometry_msgs/msg/TwistWithCovariance"](twist=t["geometry_msgs/msg/Twist"](
            linear=vec, angular=vec), covariance=np.zeros(36))
        return t["nav_msgs/msg/Odometry"](header=header(sec), child_frame_id="base", pose=pose, twist=twist)

    def navsat(sec: float, lat: float, lon: float) -> Any:
        status = t["sensor_msgs/msg/NavSatStatus"](status=0, service=1)
        return t["sensor_msgs/msg/NavSatFix"](header=header(sec), status=status, latitude=lat, longitude=lon,
                                              altitude=0.0, position_covariance=np.zeros(9),
                                              position_covariance_type=0)

    return {"raw": raw, "compressed": compressed, "odometry": odometry, "navsat": navsat}


def write_bag(
    path: Path, storage: str, messages: Sequence[tuple[str, str, float, tuple[Any, ...]]],
) -> Path:
    """Write a bag; ``storage`` is ``ros1``, ``sqlite3`` or ``mcap``.

    ``messages`` are ``(topic, kind, time_s, args)`` with ``kind`` one of ``raw`` (args: image,
    encoding), ``compressed`` (args: jpeg bytes), ``odometry`` (x, y), ``navsat`` (lat, lon), in time order.
    """
    from rosbags.typesys import Stores, get_typestore

    msgtypes = {"raw": "sensor_msgs/msg/Image", "compressed": "sensor_msgs/msg/CompressedImage",
                "odometry": "nav_msgs/msg/Odometry", "navsat": "sensor_msgs/msg/NavSatFix"}
    ros1 = storage == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    make = _messages(ts, ros1)
    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        writer: Any = Writer1(path)
    else:
        from rosbags.rosbag2 import Writer as Writer2

        kwargs: dict[str, Any] = {}
        params = inspect.signature(Writer2).parameters
        if "version" in params:
            kwargs["version"] = 9
        if "storage_plugin" in params:
            from rosbags.rosbag2 import StoragePlugin

            kwargs["storage_plugin"] = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        elif storage == "mcap":
            pytest.skip("this rosbags cannot write MCAP")
        writer = Writer2(path, **kwargs)
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    conns: dict[str, Any] = {}
    with writer:
        for topic, kind, sec, args in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtypes[kind], typestore=ts)
            msg = make[kind](sec, *args)
            writer.write(conns[topic], round(sec * 1e9), serialize(msg, msgtypes[kind]))
    return path


def jpeg(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    return buf.tobytes()


@pytest.fixture()
def rosbags_installed() -> None:
    try:
        import rosbags  # noqa: F401
    except ImportError:
        pytest.skip("rosbags (pip install 'topoloc[ros]') is not installed")


@pytest.fixture()
def recordings() -> dict[str, Any]:
    """The helpers, for tests (conftest modules are not importable with --import-mode=importlib)."""
    return {"frames_of": frames_of, "write_bag": write_bag, "jpeg": jpeg, "T0": T0}
