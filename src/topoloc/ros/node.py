"""The ROS 1 node: an image topic in, the place each frame shows out, never behind the camera.

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
reloads at once).  A map that fails to load is one line, and the old one stays.

SIGINT and SIGTERM stop it cleanly (one line, exit 0), as does the loss of the
ROS master (one line, exit 1): its process is checked once a second.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from topoloc._parallel import n_workers
from topoloc.datasets.sources.live import Newest
from topoloc.errors import TopolocError
from topoloc.ros import import_rospy

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/Image"
COMPRESSED = "sensor_msgs/CompressedImage"

#: How often the map file and the master are checked, and diagnostics published (seconds).
CHECK_S = 1.0


@dataclass
class NodeSettings:
    """What the node runs with: command-line options, else the node's private parameters, else these defaults.

    Parameters
    ----------
    map_file : Path
        The saved map (``~map``).
    image_topic : str
        Subscribed topic (``~image_topic``; default ``image``, to remap).
    sequence : int, optional
        Sequence matching over each frame and the N before it; None: as the
        map was calibrated (``~sequence``; 0: single images).
    sequence_mode : str, optional
        ``constant`` or ``acceleration`` (``~sequence_mode``).
    queue : int
        Frames that may wait to be matched (``~queue``; 1: the newest only).
    rate : float
        At most this many frames localised a second, 0 for as many as the
        cores allow (``~rate``); the others are skipped.
    top_k : int
        Places listed per answer (``~top_k``).
    prefetch : int, optional
        Frames decoded and described ahead (``~prefetch``; as ``localize --prefetch``).
        None: one per core, not ``localize``'s two: a frame taken from the
        topic waits behind the ones already ahead of it, so every extra one
        adds a frame's time to the latency without adding throughput once each
        core describes one.
    map_frame : str
        ``frame_id`` of ``~position`` (``~map_frame``).
    watch_map : bool
        Reload the map when its file changes (``~watch_map``).
    verify : bool, optional
        Verify each answer (``~verify``; ``--verify/--no-verify``); None: as
        ``localize`` decides (``$TOPOLOC_VERIFY``, the map's record, else
        wherever the map can).  A map that cannot verify where it was asked is
        refused at the start, and a reloaded one is not taken (the old map stays).
    """

    map_file: Path
    image_topic: str = "image"
    sequence: int | None = None
    sequence_mode: str | None = None
    queue: int = 1
    rate: float = 0.0
    top_k: int = 5
    prefetch: int | None = None
    map_frame: str = "map"
    watch_map: bool = True
    verify: bool | None = None

    def check(self) -> None:
        """One-line errors naming the setting, before the node starts."""
        if self.queue < 1:
            raise TopolocError(f"queue must be >= 1, got {self.queue}")
        if not (self.rate >= 0 and np.isfinite(self.rate)):
            raise TopolocError(f"rate must be a finite number of frames a second >= 0, got {self.rate}")
        if self.sequence is not None and self.sequence < 0:
            raise TopolocError(f"sequence must be >= 0, got {self.sequence}")


PARAMS = ("map", "image_topic", "sequence", "sequence_mode", "queue", "rate", "top_k", "prefetch",
          "map_frame", "watch_map", "verify")


def settings_from(given: dict[str, Any], params: dict[str, Any]) -> NodeSettings:
    """The settings: a value ``given`` on the command line (not None), else the ROS parameter, else the default."""
    values: dict[str, Any] = {}
    for name in PARAMS:
        value = given.get(name)
        if value is None:
            value = params.get(name)
            if name == "sequence" and isinstance(value, int) and value < 0:
                value = None  # a launch file's "not given": as the map was calibrated
        if value is not None:
            values["map_file" if name == "map" else name] = value
    if "map_file" not in values:
        raise TopolocError("the node needs a map: topoloc ros-node MAP, or the private parameter ~map")
    kinds = {"queue": int, "top_k": int, "prefetch": int, "sequence": int, "rate": float, "map_file": Path,
             "image_topic": str, "sequence_mode": str, "map_frame": str, "watch_map": bool, "verify": bool}
    for key, kind in kinds.items():
        if key in values:
            values[key] = _typed(key, kind, values[key])
    s = NodeSettings(**values)
    s.check()
    return s


def _typed(key: str, kind: type, value: Any) -> Any:
    """A setting as ``kind``: a parameter may come as text ("5", "false") or as a number; anything else refused."""
    bad = TopolocError(f"{key} must be {kind.__name__}, got {value!r}")
    if kind is bool:
        if isinstance(value, bool):
            return value
        text = str(value).strip().lower() if isinstance(value, str | int) else ""
        if text not in ("true", "false", "1", "0"):
            raise bad
        return text in ("true", "1")
    if kind in (int, float):
        if isinstance(value, bool) or not isinstance(value, int | float | str):
            raise bad
        try:
            number = float(value)
        except ValueError:
            raise bad from None
        if kind is int and not number.is_integer():
            raise bad
        return int(number) if kind is int else number
    return kind(value)


def _stamp_s(header: Any) -> float:
    return float(header.stamp.secs) + 1e-9 * float(header.stamp.nsecs)


@dataclass
class _Counts:
    bad: int = 0
    answered: int = 0
    reloads: int = 0
    latency_ms: float | None = None
    latencies: deque[float] = field(default_factory=lambda: deque(maxlen=1000))


class LocalizerNode:
    """The node (see the module); :meth:`run` until a signal or the master's loss, returning the exit status."""

    def __init__(self, settings: NodeSettings, rospy: Any, *, name: str) -> None:
        self.settings = settings
        self.rospy = rospy
        self.name = name
        self.buffer: Newest[Any] = Newest(settings.queue)
        self.counts = _Counts()
        self.stop_reason: str | None = None
        self.exit_status = 0
        self._stop = threading.Event()
        self._reload = threading.Event()
        self._in_flight: deque[tuple[Any, float]] = deque()
        self._map_stamp = self._file_stamp()
        self.map, self._localizer = self._load_map()

    # -- the map ------------------------------------------------------------------------------------
    def _file_stamp(self) -> tuple[int, int, int] | None:
        try:
            st = os.stat(self.settings.map_file)
        except OSError:
            return None
        return st.st_ino, st.st_size, st.st_mtime_ns

    def _load_map(self) -> tuple[Any, Any]:
        """The map and its localiser, built together: a map whose localiser cannot be built is not taken."""
        from topoloc.maps import Map
        from topoloc.maps.acceptance import warn_before_localizing

        s = self.settings
        m = Map.load(s.map_file)
        seq = self._sequence(m)
        warn_before_localizing(m, s.map_file, seq, s.verify)
        prefetch = n_workers(-1) if s.prefetch is None else s.prefetch
        loc = m.localizer(top_k=s.top_k, sequence=seq.length, sequence_mode=seq.mode, prefetch=prefetch,
                          verify=s.verify)
        return m, loc

    def _sequence(self, m: Any) -> Any:
        from topoloc.spec import SequenceSpec

        s = self.settings
        if s.sequence is None:  # as `localize`: match as the threshold was calibrated
            return m.calibrated_sequence
        return SequenceSpec(length=s.sequence, mode=s.sequence_mode or "constant")

    def request_reload(self) -> None:
        """Load the map file again once the frames in flight are answered (any thread, a signal handler)."""
        self._reload.set()

    def _reload_map(self) -> None:
        self._reload.clear()
        stamp = self._file_stamp()
        try:
            m, loc = self._load_map()
        except TopolocError as exc:
            print(f"topoloc ros-node: map not reloaded, keeping the one loaded: {exc}", file=sys.stderr, flush=True)
            self._map_stamp = stamp  # said once per change of the file
            return
        self.map, self._localizer = m, loc
        self._map_stamp = stamp
        self.counts.reloads += 1
        log.warning("topoloc ros-node: map reloaded: %s (%d places)", self.settings.map_file, len(m.place_ids))

    # -- stopping -----------------------------------------------------------------------------------
    def stop(self, reason: str, status: int = 0) -> None:
        """Stop after the frames in flight (any thread, a signal handler); the first reason counts."""
        if self.stop_reason is None:
            self.stop_reason = reason
            self.exit_status = status
        self._stop.set()
        self.buffer.close()

    def _stopping(self) -> bool:
        return self._stop.is_set() or self._reload.is_set()

    # -- frames in ----------------------------------------------------------------------------------
    def _on_message(self, msg: Any) -> None:
        # Runs on rospy's thread of the connection: only put it aside, so that this thread keeps up.
        self.buffer.put((msg, time.time()))

    def _frames(self) -> Iterator[tuple[str, float | None, np.ndarray]]:
        """Decoded frames of the newest messages, for :meth:`Localizer.stream` (run on its reader thread)."""
        import sensor_msgs.msg

        from topoloc.datasets.sources.rosbag import decode_image

        topic = self.settings.image_topic
        for raw, received in self.buffer.items(stop=self._stopping, rate=self.settings.rate):
            kind = raw._connection_header.get("type", "") if raw._connection_header else ""
            k = self.buffer.taken - 1
            if kind not in (IMAGE, COMPRESSED):
                self._bad(f"topic {topic} carries {kind or 'an unknown type'}, not {IMAGE} or {COMPRESSED}")
                continue
            msg = (sensor_msgs.msg.Image if kind == IMAGE else sensor_msgs.msg.CompressedImage)()
            try:
                msg.deserialize(raw._buff)
                image = decode_image(msg, kind, gray=True, where=f"topic {topic} message {k}", path=Path(topic))
            except TopolocError as exc:
                self._bad(str(exc).removesuffix(f": {topic}"))
                continue
            except Exception as exc:  # a message that does not deserialise: skipped, said, counted
                self._bad(f"topic {topic} message {k} cannot be read ({type(exc).__name__}: {exc})")
                continue
            self._in_flight.append((msg.header, received))
            stamp = _stamp_s(msg.header)
            yield f"{topic}#{k}", stamp if stamp > 0 else received, image

    def _bad(self, line: str) -> None:
        self.counts.bad += 1
        if self.counts.bad == 1 or self.counts.bad % 100 == 0:  # said, not once a frame
            print(f"topoloc ros-node: frame skipped ({self.counts.bad} so far): {line}", file=sys.stderr, flush=True)

    # -- answers out --------------------------------------------------------------------------------
    def _publish(self, line: dict[str, Any]) -> None:
        from geometry_msgs.msg import PointStamped
        from std_msgs.msg import String

        header, received = self._in_flight.popleft()
        answer = {**line, "stamp": {"secs": int(header.stamp.secs), "nsecs": int(header.stamp.nsecs)},
                  "frame_id": header.frame_id}
        latency = 1e3 * (time.time() - received)
        answer["latency_ms"] = round(latency, 2)
        self._answer_pub.publish(String(data=json.dumps(answer)))
        if line.get("accepted") and line.get("verified", True) and "x" in line:
            point = PointStamped()
            point.header.stamp = header.stamp
            point.header.frame_id = self.settings.map_frame
            point.point.x, point.point.y = float(line["x"]), float(line["y"])
            self._position_pub.publish(point)
        self.counts.answered += 1
        self.counts.latency_ms = latency
        self.counts.latencies.append(latency)

    def _diagnostics(self, loc: Any) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        counts = self.buffer.counts()
        summary = loc.summary() if loc is not None and loc.frames else {}
        lat = np.asarray(self.counts.latencies, float)
        values = {
            "frames_in": counts["received"], "frames_out": self.counts.answered,
            "frames_skipped": counts["skipped"], "frames_waiting": counts["waiting"],
            "frames_bad": self.counts.bad, "map": str(self.settings.map_file), "map_reloads": self.counts.reloads,
            "latency_ms_last": None if self.counts.latency_ms is None else round(self.counts.latency_ms, 2),
            "latency_ms_median": round(float(np.median(lat)), 2) if lat.size else None,
            **{k: v for k, v in summary.items() if k.startswith(("ms_", "fps", "threads"))},
        }
        status = DiagnosticStatus(name=f"{self.name}: localizer", hardware_id=str(self.settings.map_file))
        calibrated = self.map.threshold is not None
        status.level = DiagnosticStatus.OK if calibrated else DiagnosticStatus.WARN
        status.message = ("localizing" if calibrated else "map not calibrated: every answer is accepted")
        status.values = [KeyValue(key=k, value=json.dumps(v) if not isinstance(v, str) else v)
                         for k, v in values.items()]
        arr = DiagnosticArray(status=[status])
        arr.header.stamp = self.rospy.Time.now()
        self._diag_pub.publish(arr)

    # -- the watchers -------------------------------------------------------------------------------
    def _watch(self, holder: list[Any]) -> None:
        """Once a second: is the master there, has the map file changed; diagnostics out."""
        import rosgraph

        master = rosgraph.Master(self.rospy.get_name())
        while not self._stop.wait(CHECK_S):
            try:
                master.getPid()
            except Exception:  # refused, reset, timed out: the master is gone
                self.stop(f"the ROS master at {rosgraph.get_master_uri()} is gone", status=1)
                return
            if self.settings.watch_map and not self._reload.is_set():
                stamp = self._file_stamp()
                if stamp is not None and stamp != self._map_stamp:
                    self.request_reload()
            with contextlib.suppress(Exception):  # a publish racing the shutdown
                self._diagnostics(holder[0] if holder else None)

    # -- running ------------------------------------------------------------------------------------
    def run(self) -> int:
        """Subscribe, localise and publish until stopped; the exit status (0, or 1 when the master is gone)."""
        rospy = self.rospy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PointStamped
        from std_msgs.msg import String

        self._answer_pub = rospy.Publisher("~answer", String, queue_size=10)
        self._position_pub = rospy.Publisher("~position", PointStamped, queue_size=10)
        self._diag_pub = rospy.Publisher("/diagnostics", DiagnosticArray, queue_size=10)
        with contextlib.suppress(ImportError):  # std_srvs missing: the signal and the file watch still reload
            from std_srvs.srv import Trigger, TriggerResponse

            def reload(_: Any) -> Any:
                self.request_reload()
                return TriggerResponse(success=True, message=f"reloading {self.settings.map_file}")

            rospy.Service("~reload", Trigger, reload)
        # queue_size None: rospy hands over every message it read (with a bound it drops the older ones of a
        # batch read at once, uncounted); the callback only puts it into the buffer, which drops and counts.
        # buff_size: rospy reads a connection in chunks of it; smaller than a frame, messages queue up in the
        # socket and arrive late (a known rospy trap), so room for a few large raw frames.
        rospy.Subscriber(self.settings.image_topic, rospy.AnyMsg, self._on_message, queue_size=None,
                         buff_size=1 << 26, tcp_nodelay=True)
        holder: list[Any] = []
        watcher = threading.Thread(target=self._watch, args=(holder,), name="topoloc-watch", daemon=True)
        watcher.start()
        log.info("topoloc ros-node: localizing %s against %s", rospy.resolve_name(self.settings.image_topic),
                 self.settings.map_file)
        while not self._stop.is_set():
            if self._reload.is_set():
                self._reload_map()
            loc = self._localizer
            holder[:] = [loc]
            self._in_flight.clear()
            for line in loc.stream(self._frames()):
                self._publish(line)
        return self.exit_status


def serve(settings_given: dict[str, Any], argv: list[str]) -> int:
    """Start the node (``topoloc ros-node``): check the master, read the parameters, run; the exit status.

    ``argv`` holds ROS's own arguments (``image:=/camera/image_raw``, ``__name:=...``).
    """
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
    params = {name: rospy.get_param(f"~{name}") for name in PARAMS if rospy.has_param(f"~{name}")}
    settings = settings_from(settings_given, params)
    node = LocalizerNode(settings, rospy, name=rospy.get_name())

    def on_signal(signum: int, frame: object) -> None:
        if signum == signal.SIGHUP:
            node.request_reload()
        else:
            node.stop(signal.Signals(signum).name)

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, on_signal)
    try:
        status = node.run()
    finally:
        # Unregistering from a master that is gone would only log connection errors.
        rospy.signal_shutdown(node.stop_reason or "done")
    counts = node.buffer.counts()
    print(f"topoloc ros-node: stopped ({node.stop_reason}): {counts['received']} frames in, "
          f"{node.counts.answered} answered, {counts['skipped']} skipped, {node.counts.bad} unreadable",
          file=sys.stderr, flush=True)
    return status


def _quiet_rospy_loggers() -> None:
    """rospy's own log lines (a lost master, connections closing at shutdown) off the terminal: the node says them."""
    for name in ("rospy", "rosout", "rospy.core", "rospy.topics", "rospy.internal", "rospy.impl", "rosgraph"):
        logging.getLogger(name).setLevel(logging.CRITICAL)


__all__ = ["COMPRESSED", "IMAGE", "PARAMS", "LocalizerNode", "NodeSettings", "serve", "settings_from"]
