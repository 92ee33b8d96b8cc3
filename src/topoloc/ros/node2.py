"""The ROS 2 node: an image topic in, the place each frame shows out, never behind the camera.

The ``rclpy`` transport around :class:`topoloc.ros.core.NodeCore`, which the
ROS 1 node (:mod:`topoloc.ros.node`) shares: the buffer, messages to frames,
answers to messages, the map and its reloads are the core's; this module
declares the parameters, subscribes, publishes and serves.

Names (relative: under the node's namespace, remapped with ``--ros-args -r``)
    ``image`` (subscribed; the parameter ``image_topic``): ``sensor_msgs/msg/Image``
    in any encoding of :data:`topoloc.datasets.sources.rosbag.ENCODINGS`, or
    ``sensor_msgs/msg/CompressedImage``, with the sensor-data QoS profile (best
    effort, keep last 5: a camera's driver never waits for the node).  The type
    is the one the topic's publishers have (checked once a second; before any,
    ``CompressedImage`` for a name ending in ``compressed``, else ``Image``).
    ``answer`` (``std_msgs/msg/String``): the ``localize`` line of each frame as
    JSON, with the image's ``stamp`` (``sec``, ``nanosec``), ``frame_id`` and
    ``latency_ms``; ``position`` (``geometry_msgs/msg/PointStamped``): the place's
    x, y in ``map_frame`` for an accepted answer whose place has one.  Both
    reliable and transient local, keeping the last :data:`ANSWERS_KEPT`: a
    subscriber that joins late (``--qos-durability transient_local``) gets the
    latest answers at once.
    ``/diagnostics`` (``diagnostic_msgs/msg/DiagnosticArray``, once a second).
    ``~/reload`` (``std_srvs/srv/Trigger``): load the map file again now; the
    response says whether it was taken (a map that does not load, or whose
    localiser cannot be built, is refused, and the node keeps the map it has).

Parameters
    Those of :class:`topoloc.spec.NodeSpec` (``map``, ``image_topic``,
    ``queue``, ``rate``, ``top_k``, ``prefetch``, ``map_frame``, ``watch_map``,
    ``device``, ``sequence``, ``sequence_mode``, ``verify``,
    ``verify_candidates``, ``min_support``, ``confirm``), declared with their
    types and descriptions.  An option on the command line wins over
    ``--ros-args -p`` / ``--params-file``, which win over ``--config FILE``.
    Each can be set while the node runs (``ros2 param set``) and is checked
    first: a bad value, a map that does not load, verification asked of a map
    that cannot verify, and ``device`` (fixed for the process) are refused with
    the reason; a change is taken between two frames.

SIGINT and SIGTERM stop it cleanly (one line, exit 0); SIGHUP reloads the map.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from topoloc.errors import ParameterError, TopolocError
from topoloc.ros.core import CHECK_S, COMPRESSED, IMAGE, Messages, NodeCore, node_error, replace_spec
from topoloc.spec import NodeSpec

log = logging.getLogger(__name__)

PROGRAM = "topoloc ros2-node"

#: Answers (and positions) kept for a subscriber that joins late.
ANSWERS_KEPT = 10

#: What each parameter means, as ``ros2 param describe`` shows it.
DESCRIPTIONS = {
    "map": "The map file (topoloc map build); a new path loads that map, kept only if it loads.",
    "image_topic": "The image topic subscribed (sensor_msgs/Image or CompressedImage); remap 'image' instead.",
    "queue": "Frames that may wait to be matched (1: the newest only); older ones are skipped and counted.",
    "rate": "At most this many frames localised a second (0: as many as the cores allow).",
    "top_k": "Places listed per answer.",
    "prefetch": "Frames decoded and described ahead while one is matched (unset: one per core).",
    "map_frame": "frame_id of the positions (the map's coordinates).",
    "watch_map": "Reload the map when its file changes.",
    "device": "Where learned features are extracted: cpu, cuda or auto (unset: $TOPOLOC_DEVICE, else cpu).",
    "sequence": "Sequence matching over each frame and the N before it (0: single images; unset or < 0: as the "
                "map was calibrated).",
    "sequence_mode": "constant or acceleration (with sequence).",
    "verify": "Verify each answer geometrically (unset: as localize decides).",
    "verify_candidates": "Distinct peaks verified per frame (unset: as localize).",
    "min_support": "Support (inliers that are distinctive matches) a verified answer needs.",
    "confirm": "Temporal consistency of the answers.",
}


def ros2_messages() -> Messages:
    """rclpy's message classes (ROS 2 stamps: ``sec``, ``nanosec``)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import PointStamped
    from std_msgs.msg import String

    return Messages(string=String, point_stamped=PointStamped, diagnostic_array=DiagnosticArray,
                    diagnostic_status=DiagnosticStatus, key_value=KeyValue, stamp_fields=("sec", "nanosec"))


def _parameter_type(kind: type) -> Any:
    from rclpy.parameter import Parameter

    return {bool: Parameter.Type.BOOL, int: Parameter.Type.INTEGER, float: Parameter.Type.DOUBLE,
            str: Parameter.Type.STRING}[kind]


class Ros2Node:
    """The ROS 2 node (see the module) on an ``rclpy`` node: :meth:`run` until stopped, returning the exit status."""

    def __init__(self, node: Any, spec: NodeSpec) -> None:
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup

        self.node = node
        self.core = NodeCore(spec, ros2_messages(), name=node.get_fully_qualified_name(), program=PROGRAM)
        self._images_group = MutuallyExclusiveCallbackGroup()  # images keep flowing while a change is built
        self._subscription: Any = None
        self._subscribed: tuple[str, str] | None = None  # (resolved topic, type)
        self._problem: str | None = None
        self._sub_lock = threading.Lock()
        self._last_number: dict[str, int] = {}  # the last publication number of each publisher
        self.core.counts_lost = True

    # -- the image subscription -------------------------------------------------------------------------------
    def _image_type(self, topic: str) -> tuple[str | None, str | None]:
        """The image type the topic's publishers have (by its name while it has none), and a problem."""
        types = {info.topic_type.replace("/msg/", "/") for info in self.node.get_publishers_info_by_topic(topic)}
        images = types & {IMAGE, COMPRESSED}
        if len(images) == 1:
            return images.pop(), None
        if len(images) > 1:
            return None, f"topic {topic} has publishers of both {IMAGE} and {COMPRESSED}"
        if types:
            return None, f"topic {topic} carries {', '.join(sorted(types))}, not {IMAGE} or {COMPRESSED}"
        return (COMPRESSED if topic.rstrip("/").endswith("compressed") else IMAGE), None

    def subscribe(self) -> None:
        """Subscribe to the image topic with the type its publishers have (again when it changed)."""
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import CompressedImage, Image

        with self._sub_lock:
            topic = self.node.resolve_topic_name(self.core.spec.image_topic)
            kind, problem = self._image_type(topic)
            if problem != self._problem and problem is not None:
                self.core.say(problem)
            self._problem = problem
            if kind is None or self._subscribed == (topic, kind):
                return
            if self._subscription is not None:
                # The executor lets go of the old subscription's handle after its wait: the new one (whose topic
                # may have the same name and another type) is made on the next tick.
                self.node.destroy_subscription(self._subscription)
                log.warning("%s: %s carries %s, not %s: subscribing again", PROGRAM, topic, kind,
                            (self._subscribed or ("", "?"))[1])
                self._subscription, self._subscribed = None, None
                return
            msg_type = Image if kind == IMAGE else CompressedImage
            core, last = self.core, self._last_number

            def on_image(msg: Any, info: Any) -> None:
                core.put(msg, kind)
                # Frames the sensor-data QoS dropped (its reader keeps the 5 newest) or the transport lost never
                # reach the callback: gaps in each publisher's numbering count them.
                number, gid = info.get("publication_sequence_number"), info.get("publisher_gid")
                if number:
                    key = repr(gid)
                    before = last.get(key)
                    if before is not None and number > before + 1:
                        core.lost(number - before - 1)
                    last[key] = max(number, before or 0)

            try:
                self._subscription = self.node.create_subscription(
                    msg_type, topic, on_image, qos_profile_sensor_data, callback_group=self._images_group)
            except Exception as exc:  # rclpy's RCLError: the old topic not yet gone; tried again on the next tick
                log.info("%s: subscribing to %s once more (%s)", PROGRAM, topic, exc)
                return
            self._subscribed = (topic, kind)

    # -- parameters -------------------------------------------------------------------------------------------
    def on_set_parameters(self, params: list[Any]) -> Any:
        """``ros2 param set``: the change checked and built before it is taken, or refused with the reason."""
        from rcl_interfaces.msg import SetParametersResult

        changes = {p.name: p.value for p in params if p.name in NodeSpec.PARAMS}
        spec = self.core.next_spec
        try:
            new = replace_spec(spec, changes)
            if new != spec:
                self.core.change(new)
        except TopolocError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        if new.image_topic != spec.image_topic:
            threading.Thread(target=self.subscribe, daemon=True).start()  # not from inside the callback
        return SetParametersResult(successful=True)

    # -- the timer --------------------------------------------------------------------------------------------
    def _tick(self) -> None:
        """Once a second: the topic's type, the map file, diagnostics out."""
        if self.core.stopped:
            return
        self.subscribe()
        self.core.check_map_file()
        extra = {"image_topic": self._subscribed[0] if self._subscribed else self.core.spec.image_topic,
                 "image_type": self._subscribed[1] if self._subscribed else "", "problem": self._problem or ""}
        self._diag_pub.publish(self.core.diagnostics(self.node.get_clock().now().to_msg(), extra))

    def _reload(self, _request: Any, response: Any) -> Any:
        try:
            self.core.reload_now()
        except TopolocError as exc:
            response.success, response.message = False, f"map not reloaded, keeping the one loaded: {exc}"
        else:
            response.success, response.message = True, f"reloaded {self.core.spec.map_file}"
        return response

    # -- running ----------------------------------------------------------------------------------------------
    def run(self) -> int:
        """Subscribe, serve, localise and publish until stopped; the exit status."""
        from rclpy.executors import MultiThreadedExecutor
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from std_srvs.srv import Trigger

        node, msgs = self.node, self.core.messages
        answers = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=ANSWERS_KEPT,
                             reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        answer_pub = node.create_publisher(msgs.string, "answer", answers)
        position_pub = node.create_publisher(msgs.point_stamped, "position", answers)
        self._diag_pub = node.create_publisher(msgs.diagnostic_array, "/diagnostics", 10)
        node.create_service(Trigger, "~/reload", self._reload)
        node.add_on_set_parameters_callback(self.on_set_parameters)
        self.core.warm_up()
        self.subscribe()
        node.create_timer(CHECK_S, self._tick)
        executor = MultiThreadedExecutor(num_threads=2)
        executor.add_node(node)
        spinner = threading.Thread(target=executor.spin, name="topoloc-ros2-executor", daemon=True)
        spinner.start()
        log.info("%s: localizing %s against %s", PROGRAM, self._subscribed, self.core.spec.map_file)

        def publish(answer: Any, position: Any) -> None:
            answer_pub.publish(answer)
            if position is not None:
                position_pub.publish(position)

        try:
            return self.core.run(publish)
        finally:
            executor.shutdown(timeout_sec=5)
            spinner.join(timeout=5)


def spec_from_node(node: Any, given: Mapping[str, Any], config: Mapping[str, Any]) -> NodeSpec:
    """Declare the parameters (``config``'s values as defaults, ``given`` options as overrides); the spec."""
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.exceptions import InvalidParameterTypeException, ParameterUninitializedException

    defaults = {**NodeSpec.defaults(), **{k: v for k, v in config.items() if v is not None}}
    values: dict[str, Any] = {}
    for name in NodeSpec.PARAMS:
        kind = NodeSpec.param_type(name)
        value = defaults[name]
        if value is not None and kind is float:
            value = float(value)
        # rate takes 5 as well as 5.0 (a ROS 2 double refuses an integer); its value is checked by the specification
        descriptor = ParameterDescriptor(name=name, description=DESCRIPTIONS[name], dynamic_typing=kind is float,
                                         additional_constraints=NodeSpec.FIXED.get(name, ""))
        try:
            if value is None:
                node.declare_parameter(name, _parameter_type(kind), descriptor)
            else:
                node.declare_parameter(name, value, descriptor)
        except InvalidParameterTypeException as exc:
            raise TopolocError(f"{name} must be {_WORDS[kind]} ({exc})") from None
        try:
            values[name] = node.get_parameter(name).value
        except ParameterUninitializedException:
            values[name] = None
    try:
        return NodeSpec.from_params(values)
    except ParameterError as exc:
        raise node_error(exc) from None


_WORDS = {bool: "true or false", int: "a whole number", float: "a number", str: "text"}


def serve(given: Mapping[str, Any], ros_args: list[str], *, config: Path | None = None) -> int:
    """Start the node (``topoloc ros2-node``): parameters, map, then run until a signal; the exit status.

    ``given``: the command line's options as flat parameters (None: not
    given); ``ros_args``: ROS 2's own (``--ros-args -r image:=/cam -p queue:=2``).
    """
    from topoloc.ros import import_rclpy
    from topoloc.ros.node import _config_params, use_device

    config_params = _config_params(config)
    rclpy = import_rclpy()
    from rclpy.parameter import Parameter
    from rclpy.signals import SignalHandlerOptions

    overrides = []
    for name, value in given.items():
        if value is None:
            continue
        kind = NodeSpec.param_type(name)
        overrides.append(Parameter(name, value=float(value) if kind is float else kind(value)))
    rclpy.init(args=["topoloc", *ros_args], signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = rclpy.create_node("topoloc", parameter_overrides=overrides)
        try:
            spec = spec_from_node(node, given, config_params)
            use_device(spec)
            ros2 = Ros2Node(node, spec)
            ros2.core.handle_signals()
            status = ros2.run()
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    ros2.core.say(ros2.core.last_line().removeprefix(f"{PROGRAM}: "))
    return status


__all__ = ["ANSWERS_KEPT", "DESCRIPTIONS", "PROGRAM", "Ros2Node", "ros2_messages", "serve", "spec_from_node"]
