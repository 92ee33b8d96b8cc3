"""A ROS 2 probe beside the node: publish frames as a camera would, or replay a bag, and record the answers.

``python -m topoloc.ros.probe2 --out answers.jsonl --answers /topoloc/answer``
records every answer (one JSON line each, with its ``received`` wall-clock
time), the node's ``/diagnostics`` and, with ``--positions TOPIC``, its
positions.  It also publishes, on ``--topic``:

* ``--publish FOLDER --rate HZ``: the folder's images as a camera would
  (``sensor_msgs/msg/Image``, ``bgr8`` or ``mono8``, or ``CompressedImage``
  JPEG), stamped with the wall clock when sent, so that an answer's
  ``publish_to_answer_ms`` is the time from a frame's publication to its answer's
  arrival (both processes on this machine's clock);
* ``--bag BAG --rate HZ``: the image messages of a ROS 2 bag as they were
  recorded (their serialised bytes, stamps and all, as ``ros2 bag play`` sends
  them), each topic (or those of ``--bag-topic``) on its own name, HZ frames a
  second of each;
* ``--bad image|compressed``: messages that are no frame (a step shorter than a
  row, data shorter than the image, an unknown encoding, an empty image; or
  compressed bytes that decode to nothing), then one good frame.

With ``--node NAME`` it is a client of the node instead, as ``ros2 param`` and
``ros2 service call`` are: ``--get NAME`` and ``--set NAME=VALUE`` (each on its
own, in order; the result and the node's reason recorded) and ``--reload``
(the ``~/reload`` service's response), then it exits.

Published with the QoS a camera driver's publisher has (reliable, keep last
``--depth``), which the node's best-effort subscription takes.  The tests and
``benchmarks/bench_ros_latency.py`` run it as its own process with the ROS 2
environment's Python (:mod:`topoloc.ros.environment`); it stops on SIGINT or
SIGTERM, or ``--linger`` seconds after its last frame.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.ros.record import ProbeRecord, stop_on_signals


def _image(img: np.ndarray, encoding: str) -> Any:
    from sensor_msgs.msg import Image

    img = np.ascontiguousarray(img)
    return Image(height=img.shape[0], width=img.shape[1], encoding=encoding, is_bigendian=0, step=img.strides[0],
                 data=img.tobytes())


def folder_messages(folder: Path, encoding: str) -> list[Any]:
    """The images of a folder (name order) as camera messages of ``encoding`` (``bgr8``, ``mono8``, ``jpeg``)."""
    from sensor_msgs.msg import CompressedImage

    from topoloc.datasets.decode import read_image, to_bgr, to_gray

    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in {".jpg", ".jpeg", ".png"})
    out = []
    for path in files:
        if encoding == "jpeg":
            msg = CompressedImage(format="jpeg", data=path.read_bytes())
        else:
            bgr = to_bgr(read_image(path, gray=False))
            msg = _image(to_gray(bgr) if encoding == "mono8" else bgr, encoding)
        msg.header.frame_id = "probe_camera"
        out.append(msg)
    return out


def bag_messages(bag: Path, topics: list[str]) -> tuple[dict[str, type], list[tuple[str, bytes]]]:
    """The serialised messages of image topics of a ROS 2 bag (all where ``topics`` is empty), in bag order."""
    from rosbags.highlevel import AnyReader
    from sensor_msgs.msg import CompressedImage, Image

    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if (c.topic in topics if topics else
                                                    c.msgtype.endswith(("/Image", "/CompressedImage")))]
        missing = sorted(set(topics) - {c.topic for c in conns})
        if missing:
            raise SystemExit(f"probe: topic {missing[0]} is not in {bag}")
        kinds = {c.topic: CompressedImage if c.msgtype.endswith("CompressedImage") else Image for c in conns}
        raw = [(conn.topic, bytes(data)) for conn, _, data in reader.messages(connections=conns)]
    return kinds, raw


def bad_messages(kind: str) -> list[Any]:
    """Messages that are no frame, then one good frame (the probe's ``--bad``)."""
    from sensor_msgs.msg import CompressedImage

    good = np.tile(np.arange(64, dtype=np.uint8), (48, 1))
    if kind == "compressed":
        import cv2

        ok, jpeg = cv2.imencode(".jpg", good)
        assert ok
        msgs = [CompressedImage(format="jpeg", data=b"\xff\xd8 not a jpeg at all " * 10),
                CompressedImage(format="png", data=b""),
                CompressedImage(format="jpeg", data=jpeg.tobytes())]
    else:
        wrong_step = _image(good, "mono8")
        wrong_step.step = 10  # shorter than a row of 64 pixels
        short = _image(good, "mono8")
        short.data = good.tobytes()[: good.size // 2]
        unknown = _image(good, "mono8")
        unknown.encoding = "32FC7"
        empty = _image(np.zeros((0, 0), np.uint8), "mono8")
        msgs = [wrong_step, short, unknown, empty, _image(good, "mono8")]
    for k, m in enumerate(msgs):
        m.header.frame_id = f"bad_{k}"
        m.header.stamp.sec = 1_700_000_000 + k
    return msgs


def _value(text: str) -> Any:
    """A parameter's value from the command line: a number, true/false, else text (as ``ros2 param set``)."""
    try:
        return json.loads(text)
    except ValueError:
        return text


def client(args: argparse.Namespace) -> None:
    """``--node``: read and set the node's parameters and call its reload service; each result one JSON line."""
    import rclpy
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient
    from std_srvs.srv import Trigger

    rclpy.init()
    node = rclpy.create_node(f"topoloc_client_{threading.get_native_id()}")
    records = []
    try:
        params = AsyncParameterClient(node, args.node)
        if not params.wait_for_services(timeout_sec=30):
            raise SystemExit(f"probe: no parameter services of {args.node}")

        def done(future: Any) -> Any:
            rclpy.spin_until_future_complete(node, future, timeout_sec=60)
            if not future.done():
                raise SystemExit(f"probe: {args.node} did not answer")
            return future.result()

        for name in args.get:
            values = done(params.get_parameters([name])).values
            value = Parameter.from_parameter_msg(_msg(name, values[0])).value if values else None
            records.append({"kind": "get", "name": name, "value": value})
        for item in args.set:
            name, _, text = item.partition("=")
            result = done(params.set_parameters([Parameter(name, value=_value(text))])).results[0]
            records.append({"kind": "set", "name": name, "value": _value(text), "successful": result.successful,
                            "reason": result.reason})
        if args.reload:
            cli = node.create_client(Trigger, f"{args.node}/reload")
            if not cli.wait_for_service(timeout_sec=30):
                raise SystemExit(f"probe: no reload service of {args.node}")
            response = done(cli.call_async(Trigger.Request()))
            records.append({"kind": "reload", "success": response.success, "message": response.message})
    finally:
        args.out.write_text("".join(json.dumps(r) + "\n" for r in records))
        node.destroy_node()
        rclpy.try_shutdown()


def _msg(name: str, value: Any) -> Any:
    from rcl_interfaces.msg import Parameter as ParameterMsg

    return ParameterMsg(name=name, value=value)


def main(argv: list[str] | None = None) -> None:
    """The probe (see the module)."""
    ap = argparse.ArgumentParser(prog="python -m topoloc.ros.probe2", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="JSON lines: answers, diagnostics, a summary last")
    ap.add_argument("--answers", action="append", default=[], help="answer topic to record (repeatable)")
    ap.add_argument("--positions", action="append", default=[], help="position topic to record (repeatable)")
    ap.add_argument("--late", action="store_true", help="record answers as a late subscriber (transient local)")
    ap.add_argument("--publish", type=Path, help="folder of images to publish, in name order, looped")
    ap.add_argument("--bag", type=Path, help="ROS 2 bag whose image messages to publish (--bag-topic)")
    ap.add_argument("--bag-topic", action="append", default=[], help="the bag's image topic (repeatable; default all)")
    ap.add_argument("--bad", choices=["image", "compressed"], help="publish messages that are no frame, then a good")
    ap.add_argument("--topic", default="/probe/image", help="topic to publish on")
    ap.add_argument("--encoding", default="bgr8", choices=["bgr8", "mono8", "jpeg"])
    ap.add_argument("--rate", type=float, default=10.0, help="frames a second")
    ap.add_argument("--count", type=int, default=0, help="frames to publish (0: each once)")
    ap.add_argument("--depth", type=int, default=10, help="the publisher's queue (keep last)")
    ap.add_argument("--subscribers", type=int, default=1, help="wait for this many subscribers before publishing")
    ap.add_argument("--linger", type=float, default=3.0, help="seconds to record after the last frame")
    ap.add_argument("--node", help="client of this node (--get, --set, --reload), then exit")
    ap.add_argument("--get", action="append", default=[], help="parameter to read (repeatable)")
    ap.add_argument("--set", action="append", default=[], help="NAME=VALUE to set, each on its own (repeatable)")
    ap.add_argument("--reload", action="store_true", help="call the node's reload service")
    args = ap.parse_args(argv)
    if args.node is not None:
        client(args)
        return

    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PointStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import String

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"topoloc_probe_{threading.get_native_id()}")
    stop = stop_on_signals()
    record = ProbeRecord(args.out)

    def on_answer(msg: Any, topic: str) -> None:
        record.answer(msg.data, topic, lambda stamp: stamp["sec"] + 1e-9 * stamp["nanosec"])

    def on_position(msg: Any, topic: str) -> None:
        record.write({"kind": "position", "topic": topic, "received": time.time(), "frame_id": msg.header.frame_id,
                      "stamp": msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec, "x": msg.point.x,
                      "y": msg.point.y})

    def on_diagnostics(msg: Any) -> None:
        # rclpy gives a diagnostics level (a byte) as bytes.
        record.diagnostics(msg.status, lambda level: int.from_bytes(level, "little") if isinstance(level, bytes)
                           else int(level))

    answers_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL if args.late else DurabilityPolicy.VOLATILE)
    for topic in args.answers:
        node.create_subscription(String, topic, lambda m, t=topic: on_answer(m, t), answers_qos)
    for topic in args.positions:
        node.create_subscription(PointStamped, topic, lambda m, t=topic: on_position(m, t), answers_qos)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 100)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    if args.answers:
        # Answers published before this probe's subscription matches the node's publisher are never seen (only a
        # late subscriber gets the latest): wait for the node on every answer topic, then say so ("ready").
        deadline = time.monotonic() + 60.0
        while not stop.is_set() and time.monotonic() < deadline and \
                any(node.count_publishers(topic) < 1 for topic in args.answers):
            time.sleep(0.05)
        matched = all(node.count_publishers(topic) >= 1 for topic in args.answers)
        time.sleep(0.5)  # discovery: the match is made a little after the graph shows the publisher
        record.write({"kind": "ready", "matched": matched})

    published, stamps, seconds = 0, False, 0.0
    messages: list[tuple[str, Any]] = []
    kinds: dict[str, type] = {}
    if args.publish is not None:
        messages, stamps = [(args.topic, m) for m in folder_messages(args.publish, args.encoding)], True
    elif args.bag is not None:
        kinds, messages = bag_messages(args.bag, args.bag_topic)
    elif args.bad is not None:
        messages = [(args.topic, m) for m in bad_messages(args.bad)]
    if messages:
        camera = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=args.depth, reliability=ReliabilityPolicy.RELIABLE)
        pubs = {topic: node.create_publisher(kinds.get(topic) or type(m), topic, camera) for topic, m in messages}
        while any(p.get_subscription_count() < args.subscribers for p in pubs.values()) and not stop.is_set():
            time.sleep(0.05)
        time.sleep(0.5)  # discovery: the subscriber's side sees this publisher a little after it is counted
        count = args.count or len(messages)
        period = 1.0 / (args.rate * len(pubs))
        t0 = first = time.monotonic()
        for k in range(count):
            if stop.is_set():
                break
            wait = t0 + k * period - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            topic, msg = messages[k % len(messages)]
            if stamps:
                now = time.time()
                msg.header.stamp.sec, msg.header.stamp.nanosec = int(now), round((now % 1) * 1e9) % 1_000_000_000
                msg.header.frame_id = f"probe_camera_{k}"
            pubs[topic].publish(msg)
            published += 1
        seconds = time.monotonic() - first
        stop.wait(args.linger)
    else:
        stop.wait()
    record.write({"kind": "summary", "published": published, "seconds": round(seconds, 3)})
    executor.shutdown(timeout_sec=5)
    spinner.join(timeout=5)
    node.destroy_node()
    rclpy.try_shutdown()
    record.close()


if __name__ == "__main__":
    main()
