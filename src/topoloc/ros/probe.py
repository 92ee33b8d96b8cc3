"""A probe beside the node: publish frames at a camera's rate and record the answers, with their latency.

``python -m topoloc.ros.probe --out answers.jsonl --answers /topoloc/answer``
records every answer (one JSON line each, with ``received`` wall-clock time)
and the node's diagnostics; with ``--publish FOLDER --rate HZ`` it also plays
the folder's images as a camera would (``sensor_msgs/Image``, ``bgr8`` or
``mono8``, or ``CompressedImage``), stamped with the wall clock when sent, so
that each answer's ``publish_to_answer_ms`` is the time from a frame's
publication to its answer's arrival.  The tests and ``benchmarks/bench_ros_latency.py``
run it as its own process; it stops on SIGINT/SIGTERM or ``--linger`` seconds
after its last frame.  :class:`LocalMaster` starts the private ``roscore`` they
run beside.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import time
import xmlrpc.client
from collections.abc import Callable
from pathlib import Path
from typing import Any

from topoloc.ros import import_rospy
from topoloc.ros.record import ProbeRecord, stop_on_signals


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(what: str, ok: Callable[[], bool], timeout: float = 60.0) -> None:
    """Poll ``ok()`` every 0.1 s; an ``AssertionError`` naming ``what`` after ``timeout`` seconds."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if ok():
            return
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


class LocalMaster:
    """A private ``roscore`` on a free loopback port, logs under ``root``, and the environment to reach it.

    ``env`` is this process's environment with ``ROS_MASTER_URI``, ``ROS_HOME``,
    ``ROS_LOG_DIR`` and ``ROS_IP`` set, and ``extra_path`` (a source tree) first on
    ``PYTHONPATH``: the processes started with it (the node, the probe, ``rosbag
    play``) talk to this master only.
    """

    def __init__(self, root: Path, *, extra_path: str | Path | None = None) -> None:
        self.root = root
        self.port = free_port()
        self.uri = f"http://127.0.0.1:{self.port}"
        path = [str(extra_path)] if extra_path is not None else []
        self.env = {**os.environ, "ROS_MASTER_URI": self.uri, "ROS_HOME": str(root / "ros_home"),
                    "ROS_LOG_DIR": str(root / "ros_log"), "ROS_IP": "127.0.0.1",
                    "PYTHONPATH": os.pathsep.join([*path, os.environ.get("PYTHONPATH", "")])}
        self.core = subprocess.Popen(["roscore", "-p", str(self.port)], env=self.env, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL, start_new_session=True)
        wait_for("roscore", self.online)

    def _master(self) -> Any:
        # Any: the master's XML-RPC replies are lists of lists, which xmlrpc's stubs do not describe.
        return xmlrpc.client.ServerProxy(self.uri)

    def online(self) -> bool:
        """Whether the master answers."""
        try:
            return bool(self._master().getPid("/probe")[0] == 1)
        except OSError:
            return False

    def subscribers(self, topic: str) -> list[str]:
        """The nodes subscribed to ``topic`` (none when the master does not answer)."""
        try:
            state = self._master().getSystemState("/probe")[2]
        except OSError:
            return []
        return list(next((nodes for name, nodes in state[1] if name == topic), []))

    def param(self, name: str) -> Any:
        """A parameter's value on the master."""
        return self._master().getParam("/probe", name)[2]

    def close(self) -> None:
        """Stop the roscore (SIGINT to its process group, as Ctrl-C would; SIGKILL after 15 s)."""
        if self.core.poll() is None:
            os.killpg(self.core.pid, signal.SIGINT)
            try:
                self.core.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(self.core.pid, signal.SIGKILL)
                self.core.wait()


def _image_message(path: Path, encoding: str, seq: int) -> Any:
    import numpy as np
    import sensor_msgs.msg

    from topoloc.datasets.decode import read_image, to_bgr, to_gray

    if encoding == "jpeg":
        msg = sensor_msgs.msg.CompressedImage(format="jpeg", data=path.read_bytes())
    else:
        bgr = to_bgr(read_image(path, gray=False))
        img = np.ascontiguousarray(to_gray(bgr) if encoding == "mono8" else bgr)
        msg = sensor_msgs.msg.Image(height=img.shape[0], width=img.shape[1], encoding=encoding, is_bigendian=0,
                                    step=img.strides[0], data=img.tobytes())
    msg.header.frame_id = "probe_camera"
    msg.header.seq = seq
    return msg


def main(argv: list[str] | None = None) -> None:
    """The probe (see the module)."""
    ap = argparse.ArgumentParser(prog="python -m topoloc.ros.probe", description=__doc__)
    ap.add_argument("--out", type=Path, required=True, help="JSON lines: answers, diagnostics, a summary last")
    ap.add_argument("--answers", action="append", default=[], help="answer topic to record (repeatable)")
    ap.add_argument("--publish", type=Path, help="folder of images to publish, in name order, looped")
    ap.add_argument("--topic", default="/probe/image", help="topic to publish them on")
    ap.add_argument("--encoding", default="bgr8", choices=["bgr8", "mono8", "jpeg"])
    ap.add_argument("--rate", type=float, default=10.0, help="frames a second")
    ap.add_argument("--count", type=int, default=100, help="frames to publish")
    ap.add_argument("--subscribers", type=int, default=1, help="wait for this many subscribers before publishing")
    ap.add_argument("--linger", type=float, default=3.0, help="seconds to record after the last frame")
    args, ros_args = ap.parse_known_args(argv)
    rospy = import_rospy()
    from diagnostic_msgs.msg import DiagnosticArray
    from std_msgs.msg import String

    rospy.init_node("topoloc_probe", argv=["probe", *ros_args], anonymous=True, disable_signals=True)
    stop = stop_on_signals()
    record = ProbeRecord(args.out)

    def on_answer(msg: Any, topic: str) -> None:
        record.answer(msg.data, topic, lambda stamp: stamp["secs"] + 1e-9 * stamp["nsecs"])

    def on_diagnostics(msg: Any) -> None:
        record.diagnostics(msg.status)

    for topic in args.answers:
        rospy.Subscriber(topic, String, on_answer, callback_args=topic, queue_size=1000)
    rospy.Subscriber("/diagnostics", DiagnosticArray, on_diagnostics, queue_size=100)
    published = 0
    if args.publish is not None:
        files = sorted(p for p in args.publish.iterdir() if p.suffix.lower() in {".jpg", ".jpeg", ".png"})
        messages = [_image_message(p, args.encoding, k) for k, p in enumerate(files)]
        kind = type(messages[0])
        pub = rospy.Publisher(args.topic, kind, queue_size=1, tcp_nodelay=True)
        while pub.get_num_connections() < args.subscribers and not stop.is_set():
            time.sleep(0.05)
        time.sleep(0.5)  # the subscriber's connection is set up after it is counted
        period = 1.0 / args.rate
        t0 = time.monotonic()
        for k in range(args.count):
            if stop.is_set():
                break
            wait = t0 + k * period - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            msg = messages[k % len(messages)]
            msg.header.seq = k
            msg.header.stamp = rospy.Time.from_sec(time.time())
            pub.publish(msg)
            published += 1
        stop.wait(args.linger)
    else:
        stop.wait()
    record.write({"kind": "summary", "published": published})
    rospy.signal_shutdown("probe done")
    record.close()


if __name__ == "__main__":
    main()
