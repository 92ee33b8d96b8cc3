"""The ROS 1 node: an image topic in, the place each frame shows out, never behind the camera.

The transport around :class:`topoloc.ros.core.NodeCore`, which it shares with
the ROS 2 node (:mod:`topoloc.ros.node2`): this module subscribes, publishes and
watches the master with ``rospy``; turning messages into frames and answers into
messages, the newest-frame buffer, the map and its reloads are the core's.
Settings: :class:`topoloc.spec.NodeSpec` (a command-line option, else the
node's private parameter, else ``--config FILE``, else the default).

Subscribed
    ``image`` (remap it, or ``--image-topic``): ``sensor_msgs/Image`` in any
    encoding of :data:`topoloc.datasets.sources.rosbag.ENCODINGS` or
    ``sensor_msgs/CompressedImage``; the type is read from each connection, so
    one node takes either (an ``image_transport`` ``.../compressed`` topic too).

Published (each answer with the image's header stamp)
    ``~answer`` (``std_msgs/String``): the answer as one JSON object, the line
    ``topoloc localize`` writes for the frame (``place``, ``score``,
    ``accepted``, ``top``, ``x``/``y`` where the map has positions, ``time``,
    and ``verified`` when the localiser verifies its answers) plus ``stamp``
    (``secs``, ``nsecs``), ``frame_id`` and ``latency_ms`` (message received
    to answer published).
    ``~position`` (``geometry_msgs/PointStamped``): the matched place's x, y in
    the map's frame (``~map_frame``, default ``map``), for accepted answers
    whose place has a position (and not ``verified: false``).
    ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``, once a second):
    frames in, answered, skipped, undecodable, milliseconds per stage, the
    last latency, the map and its reloads.

The newest frame policy: the subscriber's callback only puts the message into
a :class:`~topoloc.datasets.sources.live.Newest` buffer (``queue`` frames wait
at most; older ones are skipped and counted), and the localiser's reader thread
takes from it, decodes and describes ahead while the frame before is matched
(:meth:`topoloc.maps.localizer.Localizer.stream`, prefetch as ``localize``).

The map file is watched (its inode, size and modification time, once a
second): ``map add`` and ``map calibrate`` replace it by an atomic rename, so a
change is seen whole, and the node finishes the frames in flight, loads the new
file and goes on (SIGHUP, or the ``~reload`` service, ``std_srvs/Trigger``,
reloads at once).  A map that fails to load (or whose localiser cannot be built) is one line, and the old one stays.

SIGINT and SIGTERM stop it cleanly (one line, exit 0), as does the loss of the
ROS master (one line, exit 1): its process is checked once a second.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from topoloc.errors import ParameterError, TopolocError
from topoloc.ros import import_rospy
from topoloc.ros.core import CHECK_S, COMPRESSED, IMAGE, Messages, NodeCore, node_error
from topoloc.spec import NodeSpec

log = logging.getLogger(__name__)

PROGRAM = "topoloc ros-node"


def ros1_messages() -> Messages:
    """rospy's message classes (ROS 1 stamps: ``secs``, ``nsecs``)."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import PointStamped
    from std_msgs.msg import String

    return Messages(string=String, point_stamped=PointStamped, diagnostic_array=DiagnosticArray,
                    diagnostic_status=DiagnosticStatus, key_value=KeyValue, stamp_fields=("secs", "nsecs"))


def spec_from(given: Mapping[str, Any], params: Mapping[str, Any], config: Mapping[str, Any] | None = None,
              ) -> NodeSpec:
    """The node's specification: an option ``given`` (not None), else the ROS parameter, else ``config``'s.

    ``params`` and ``config`` are flat (:attr:`NodeSpec.PARAMS`); a parameter may
    come as text (``"5"``, ``"false"``), as a launch file's ``<param>`` writes it.
    """
    values: dict[str, Any] = {}
    for source in (config or {}, params, given):
        values.update({k: v for k, v in source.items() if v is not None})
    try:
        return NodeSpec.from_params(values, text=True)
    except ParameterError as exc:
        raise node_error(exc) from None


class LocalizerNode:
    """The ROS 1 node (see the module): :meth:`run` until a signal or the master's loss, returning the exit status."""

    def __init__(self, spec: NodeSpec, rospy: Any, *, name: str, messages: Messages | None = None) -> None:
        self.rospy = rospy
        self.core = NodeCore(spec, messages or ros1_messages(), name=name, program=PROGRAM)

    def _decode(self, raw: Any, _kind: str) -> tuple[Any, str]:
        """An ``AnyMsg`` as the message its connection says it is (an image type, else counted as bad)."""
        import sensor_msgs.msg

        kind = raw._connection_header.get("type", "") if raw._connection_header else ""
        if kind not in (IMAGE, COMPRESSED):
            raise TopolocError(f"topic {self.core.spec.image_topic} carries {kind or 'an unknown type'}, "
                               f"not {IMAGE} or {COMPRESSED}")
        msg = (sensor_msgs.msg.Image if kind == IMAGE else sensor_msgs.msg.CompressedImage)()
        msg.deserialize(raw._buff)
        return msg, kind

    def _watch(self) -> None:
        """Once a second: is the master there, has the map file changed; diagnostics out."""
        import rosgraph

        master = rosgraph.Master(self.rospy.get_name())
        while not self.core._stop.wait(CHECK_S):
            try:
                master.getPid()
            except Exception:  # refused, reset, timed out: the master is gone
                self.core.stop(f"the ROS master at {rosgraph.get_master_uri()} is gone", status=1)
                return
            self.core.check_map_file()
            with contextlib.suppress(Exception):  # a publish racing the shutdown
                self._diag_pub.publish(self.core.diagnostics(self.rospy.Time.now()))

    def run(self) -> int:
        """Subscribe, localise and publish until stopped; the exit status (0, or 1 when the master is gone)."""
        rospy, core, msgs = self.rospy, self.core, self.core.messages
        answer_pub = rospy.Publisher("~answer", msgs.string, queue_size=10)
        position_pub = rospy.Publisher("~position", msgs.point_stamped, queue_size=10)
        self._diag_pub = rospy.Publisher("/diagnostics", msgs.diagnostic_array, queue_size=10)
        with contextlib.suppress(ImportError):  # std_srvs missing: the signal and the file watch still reload
            from std_srvs.srv import Trigger, TriggerResponse

            def reload(_: Any) -> Any:
                core.request_reload()
                return TriggerResponse(success=True, message=f"reloading {core.spec.map_file}")

            rospy.Service("~reload", Trigger, reload)
        core.warm_up()
        # queue_size None: rospy hands over every message it read (with a bound it drops the older ones of a
        # batch read at once, uncounted); the callback only puts it into the buffer, which drops and counts.
        # buff_size: rospy reads a connection in chunks of it; smaller than a frame, messages queue up in the
        # socket and arrive late (a known rospy trap), so room for a few large raw frames.
        rospy.Subscriber(core.spec.image_topic, rospy.AnyMsg, lambda m: core.put(m, ""), queue_size=None,
                         buff_size=1 << 26, tcp_nodelay=True)
        threading.Thread(target=self._watch, name="topoloc-watch", daemon=True).start()
        log.info("%s: localizing %s against %s", PROGRAM, rospy.resolve_name(core.spec.image_topic),
                 core.spec.map_file)

        def publish(answer: Any, position: Any) -> None:
            answer_pub.publish(answer)
            if position is not None:
                position_pub.publish(position)

        return core.run(publish, decode=self._decode)


def serve(given: Mapping[str, Any], argv: list[str], *, config: Path | None = None) -> int:
    """Start the node (``topoloc ros-node``): check the master, read the parameters, run; the exit status.

    ``given``: the command line's options as flat parameters (None: not given);
    ``argv`` holds ROS's own arguments (``image:=/camera/image_raw``, ``__name:=...``).
    """
    config_params = _config_params(config)
    rospy = import_rospy()
    import rosgraph

    uri = rosgraph.get_master_uri()
    if not rosgraph.is_master_online(uri):  # rospy.init_node would wait for it for ever
        raise TopolocError(f"no ROS master at {uri} (start roscore, or set ROS_MASTER_URI)")
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    rospy.init_node("topoloc", argv=["topoloc", *argv], disable_signals=True, anonymous=False)
    # rospy configures logging from its own file (rosgraph.roslogging): the command line's handler is put
    # back, and topoloc's loggers, which that configuration disables, enabled again.
    root.handlers[:], root.level = handlers, level
    for name, logger in logging.Logger.manager.loggerDict.items():
        if name.startswith("topoloc") and isinstance(logger, logging.Logger):
            logger.disabled = False
    _quiet_rospy_loggers()
    params = {name: rospy.get_param(f"~{name}") for name in NodeSpec.PARAMS if rospy.has_param(f"~{name}")}
    spec = spec_from(given, params, config_params)
    use_device(spec)
    node = LocalizerNode(spec, rospy, name=rospy.get_name())
    node.core.handle_signals()
    try:
        status = node.run()
    finally:
        # Unregistering from a master that is gone would only log connection errors.
        rospy.signal_shutdown(node.core.stop_reason or "done")
    node.core.say(node.core.last_line().removeprefix(f"{PROGRAM}: "))
    return status


def _config_params(config: Path | None) -> dict[str, Any]:
    """``--config FILE``'s settings as the node's flat parameters (a file another node or command wrote too)."""
    if config is None:
        return {}
    from topoloc.spec import load_config
    from topoloc.spec.config import typed_config

    return NodeSpec.params_of(typed_config(NodeSpec, load_config(config), source=config), source=config)


def use_device(spec: NodeSpec) -> None:
    """The node's ``device``, for its life (as ``--device``: an environment variable the extraction reads)."""
    import os

    if spec.device is not None:
        os.environ["TOPOLOC_DEVICE"] = spec.device


def _quiet_rospy_loggers() -> None:
    """rospy's own log lines (a lost master, connections closing at shutdown) off the terminal: the node says them."""
    for name in ("rospy", "rosout", "rospy.core", "rospy.topics", "rospy.internal", "rospy.impl", "rosgraph"):
        logging.getLogger(name).setLevel(logging.CRITICAL)


__all__ = ["PROGRAM", "LocalizerNode", "ros1_messages", "serve", "spec_from", "use_device"]
