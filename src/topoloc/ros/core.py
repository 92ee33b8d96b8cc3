"""What the ROS 1 and the ROS 2 node share, with no ROS in it: messages to frames, answers to messages, the loop.

Both nodes (:mod:`topoloc.ros.node` on ``rospy``, :mod:`topoloc.ros.node2` on
``rclpy``) are a transport around one :class:`NodeCore`:

* the subscriber's callback only :meth:`NodeCore.put` s the message into a
  :class:`~topoloc.datasets.sources.live.Newest` buffer (the newest-frame
  policy: ``queue`` frames wait at most, older ones are skipped and counted);
* :meth:`NodeCore.frames`, on the localiser's reader thread, turns each message
  into a frame (:func:`frame_of`, the one place that does, for either ROS);
  a message that is no frame (an unknown encoding, a wrong step, short data, an
  empty image, compressed bytes that do not decode, a type that is no image) is
  counted, said on stderr (the first and every 100th) and never answered;
* :meth:`NodeCore.run` localises them through the map's localiser
  (:meth:`topoloc.maps.Map.localizer_for` of the node's
  :class:`~topoloc.spec.NodeSpec`) and hands each answer, made into messages by
  :meth:`NodeCore.answer` (the one place that does), to the transport to publish;
* the map and its localiser are built together (:meth:`NodeCore.build`): a
  reload (the file changed, a service call, SIGHUP, a changed parameter) whose
  map does not load or whose localiser cannot be built is one line, and the
  node keeps the map it has;
* :meth:`NodeCore.diagnostics` is the ``diagnostic_msgs/DiagnosticArray`` both publish once a second.

The message classes come from the transport (:class:`Messages`): rospy's and
rclpy's ``std_msgs/String``, ``geometry_msgs/PointStamped`` and the diagnostics
have the same fields; only a time stamp's are named differently (``secs``,
``nsecs`` in ROS 1; ``sec``, ``nanosec`` in ROS 2), and an answer's ``stamp``
is named as its ROS names it.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.datasets.sources.live import Newest
from topoloc.errors import ParameterError, TopolocError
from topoloc.spec import NodeSpec

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/Image"
COMPRESSED = "sensor_msgs/CompressedImage"

#: How often the map file is checked and diagnostics published (seconds).
CHECK_S = 1.0

#: A bad message is said on stderr the first time and then once every this many.
SAY_EVERY = 100


@dataclass(frozen=True)
class Messages:
    """The message classes of one ROS (``rospy``'s or ``rclpy``'s, whose fields are the same).

    ``stamp_fields``: the names of a time stamp's seconds and nanoseconds
    (``("secs", "nsecs")`` in ROS 1, ``("sec", "nanosec")`` in ROS 2).
    """

    string: Any
    point_stamped: Any
    diagnostic_array: Any
    diagnostic_status: Any
    key_value: Any
    stamp_fields: tuple[str, str]

    def stamp(self, header: Any) -> tuple[int, int]:
        """A header's stamp as (seconds, nanoseconds)."""
        sec, nsec = self.stamp_fields
        return int(getattr(header.stamp, sec)), int(getattr(header.stamp, nsec))


def node_error(exc: ParameterError) -> TopolocError:
    """A specification's error as the node's parameter names it (``map_file`` -> ``map``)."""
    names = {dotted: flat for flat, dotted in NodeSpec.PARAMS.items()}
    name = names.get(exc.param, exc.param)
    detail = exc.detail
    if name == "map" and detail.startswith("is needed"):
        detail += " (topoloc ros-node MAP, or the node's parameter map)"
    return TopolocError(f"{name} {detail}")


def frame_of(msg: Any, kind: str, *, where: str) -> np.ndarray:
    """The grey pixels of an image message, decoded as ``localize`` decodes a bag's (the same pixels).

    ``kind`` is :data:`IMAGE` or :data:`COMPRESSED` (``sensor_msgs/msg/Image`` too).

    Raises
    ------
    TopolocError
        One line naming ``where`` (the topic and the message's number) for a message that is no frame:
        an unknown encoding, a step shorter than a row, data shorter than the image, an empty image,
        compressed bytes that do not decode.
    """
    from topoloc.datasets.sources.rosbag import decode_image

    kind = kind.replace("/msg/", "/")
    if kind not in (IMAGE, COMPRESSED):
        raise TopolocError(f"{where} is a {kind or 'message of unknown type'}, not {IMAGE} or {COMPRESSED}")
    try:
        return decode_image(msg, kind, gray=True, where=where, path=Path(where))
    except TopolocError as exc:
        raise TopolocError(str(exc).removesuffix(f": {where}")) from None
    except Exception as exc:  # a message whose fields are not what its type says (a foreign publisher)
        raise TopolocError(f"{where} cannot be read ({type(exc).__name__}: {exc})") from None


def file_stamp(path: Path) -> tuple[int, int, int] | None:
    """A file's inode, size and modification time (None when it cannot be read): an atomic rename changes it."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_ino, st.st_size, st.st_mtime_ns


@dataclass
class Counts:
    """What the node did, for its diagnostics and its last line."""

    bad: int = 0
    lost: int = 0
    answered: int = 0
    reloads: int = 0
    latency_ms: float | None = None
    latencies: deque[float] = field(default_factory=lambda: deque(maxlen=1000))
    last_bad: str = ""


class NodeCore:
    """The transport-free node: the buffer, the map and its localiser, frames in and answers out (see the module).

    Parameters
    ----------
    spec : NodeSpec
    messages : Messages
        The message classes of the node's ROS.
    name : str
        The node's full name (``/topoloc``): the diagnostics' status is named after it.
    program : str
        How its lines on stderr begin (``topoloc ros-node``).

    Raises
    ------
    TopolocError
        The map does not load or its localiser cannot be built (before anything is subscribed).
    """

    def __init__(self, spec: NodeSpec, messages: Messages, *, name: str, program: str) -> None:
        self.spec = spec
        self.messages = messages
        self.name = name
        self.program = program
        self.buffer: Newest[tuple[Any, str, float]] = Newest(spec.queue)
        self.counts = Counts()
        self.stop_reason: str | None = None
        self.exit_status = 0
        self._stop = threading.Event()
        self._restart = threading.Event()
        self._reload = False
        self._lock = threading.Lock()  # guards _pending and _reload
        self._pending: tuple[NodeSpec, Any, Any, bool] | None = None
        self._in_flight: deque[tuple[Any, float]] = deque()
        self._map_stamp = file_stamp(spec.map_file)  # type: ignore[arg-type]
        self.map, self.localizer = self.build(spec)
        self._current: Any = None
        #: Whether the transport counts the frames lost before the node (ROS 2: gaps in publishers' numbers).
        self.counts_lost = False

    # -- the map and its localiser ----------------------------------------------------------------------------
    def build(self, spec: NodeSpec, m: Any = None) -> tuple[Any, Any]:
        """The map (loaded unless given) and its localiser, built together: neither is taken without the other."""
        from topoloc.maps import Map
        from topoloc.maps.acceptance import warn_before_localizing

        assert spec.map_file is not None
        if m is None:
            m = Map.load(spec.map_file)
        warn_before_localizing(m, spec.map_file, spec.sequence or m.calibrated_sequence, spec.verification.enabled,
                               spec.verification.min_support)
        return m, m.localizer_for(spec)

    def warm_up(self) -> None:
        """One textured frame through the localiser before the topic is subscribed, its answer dropped.

        The first frame of a process pays for loading compiled code, creating
        detectors and the verifier's first reads (``benchmarks/bench_ros_latency.py``
        measured the first answers up to seconds late without it); a camera's
        frames would wait behind it, or be dropped unseen.
        """
        import cv2

        noise = np.random.default_rng(0).integers(0, 256, (480, 640), dtype=np.uint8)
        seconds = self.localizer.warm_up(cv2.GaussianBlur(noise, (0, 0), 2.0))
        log.info("%s: warmed up in %.2f s", self.program, seconds)

    def request_reload(self) -> None:
        """Load the map file again once the frames in flight are answered (any thread, a signal handler)."""
        with self._lock:
            self._reload = True
        self._restart.set()

    def change(self, spec: NodeSpec) -> None:
        """Run with ``spec`` from the next frame (a changed parameter), its map and localiser built now.

        Raises
        ------
        TopolocError
            Where the new map does not load or its localiser cannot be built, or a setting fixed for
            the node's life (:attr:`NodeSpec.FIXED`) would change (nothing changes then).
        """
        base, base_map, base_loc, reloaded = self._next()
        for name, reason in NodeSpec.FIXED.items():
            if spec.param_values()[name] != base.param_values()[name]:
                raise TopolocError(f"{name} cannot change while the node runs: {reason}")
        same_map = spec.map_file == base.map_file
        if same_map and all(getattr(spec, f) == getattr(base, f) for f in _LOCALIZER_FIELDS):
            m, loc = base_map, base_loc  # the answers' settings are the same: the localiser goes on
        else:
            m, loc = self.build(spec, base_map if same_map else None)
        self._take_later(spec, m, loc, reloaded=reloaded or not same_map)

    @property
    def next_spec(self) -> NodeSpec:
        """The specification the next frame is answered with (a change not yet taken included)."""
        return self._next()[0]

    def _next(self) -> tuple[NodeSpec, Any, Any, bool]:
        with self._lock:
            if self._pending is not None:
                return self._pending
        return self.spec, self.map, self.localizer, False

    def reload_now(self) -> None:
        """Load the map file again now (a service call), taken from the next frame.

        Raises
        ------
        TopolocError
            Where it does not load or its localiser cannot be built: said in one line, and the map
            loaded stays.
        """
        stamp = file_stamp(self.spec.map_file)  # type: ignore[arg-type]
        try:
            m, loc = self.build(self.spec)
        except TopolocError as exc:
            self.say(f"map not reloaded, keeping the one loaded: {exc}")
            self._map_stamp = stamp
            raise
        self._take_later(self.spec, m, loc, reloaded=True)

    def _take_later(self, spec: NodeSpec, m: Any, loc: Any, *, reloaded: bool) -> None:
        with self._lock:
            self._pending = (spec, m, loc, reloaded)
        self._restart.set()

    def _take_changes(self) -> None:
        """Between two runs of the localiser: a changed specification, then a reload due (main thread)."""
        with self._lock:
            pending, self._pending = self._pending, None
            reload, self._reload = self._reload, False
        self._restart.clear()
        if pending is not None:
            spec, m, loc, reloaded = pending
            changed = spec != self.spec
            self.spec, self.map, self.localizer = spec, m, loc
            self.buffer.resize(spec.queue)
            if reloaded:
                self._map_stamp = file_stamp(spec.map_file)  # type: ignore[arg-type]
                self.counts.reloads += 1
                log.warning("%s: map reloaded: %s (%d places)", self.program, spec.map_file, len(m.place_ids))
            if changed:
                log.warning("%s: settings changed: %s", self.program, json.dumps(spec.param_values()))
        if reload:
            self._reload_map()

    def _reload_map(self) -> None:
        stamp = file_stamp(self.spec.map_file)  # type: ignore[arg-type]
        try:
            m, loc = self.build(self.spec)
        except TopolocError as exc:
            self.say(f"map not reloaded, keeping the one loaded: {exc}")
            self._map_stamp = stamp  # said once per change of the file
            return
        self.map, self.localizer = m, loc
        self._map_stamp = stamp
        self.counts.reloads += 1
        log.warning("%s: map reloaded: %s (%d places)", self.program, self.spec.map_file, len(m.place_ids))

    def check_map_file(self) -> None:
        """Once a second (the transport's timer): a map file that changed is reloaded."""
        if self.spec.watch_map and not self._restart.is_set():
            stamp = file_stamp(self.spec.map_file)  # type: ignore[arg-type]
            if stamp is not None and stamp != self._map_stamp:
                self.request_reload()

    # -- stopping ---------------------------------------------------------------------------------------------
    def handle_signals(self) -> None:
        """SIGINT and SIGTERM stop the node (named in its last line), SIGHUP reloads the map: both nodes alike."""
        import signal

        def on_signal(signum: int, frame: object) -> None:
            if signum == signal.SIGHUP:
                self.request_reload()
            else:
                self.stop(signal.Signals(signum).name)

        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, on_signal)

    def stop(self, reason: str, status: int = 0) -> None:
        """Stop after the frames in flight (any thread, a signal handler); the first reason counts."""
        if self.stop_reason is None:
            self.stop_reason = reason
            self.exit_status = status
        self._stop.set()
        self.buffer.close()

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    def _stopping(self) -> bool:
        return self._stop.is_set() or self._restart.is_set()

    def last_line(self) -> str:
        """The line the node ends with: why, and what it did."""
        counts = self.buffer.counts()
        lost = f", {self.counts.lost} lost before the node" if self.counts_lost else ""
        return (f"{self.program}: stopped ({self.stop_reason}): {counts['received']} frames in, "
                f"{self.counts.answered} answered, {counts['skipped']} skipped, {self.counts.bad} unreadable{lost}")

    def say(self, line: str) -> None:
        """One line on stderr, as the command line's (the node's own words, not a log record's)."""
        print(f"{self.program}: {line}", file=sys.stderr, flush=True)

    # -- frames in --------------------------------------------------------------------------------------------
    def put(self, msg: Any, kind: str) -> None:
        """The subscriber's callback: the message aside, with its type and the time it arrived (nothing else)."""
        self.buffer.put((msg, kind, time.time()))

    def lost(self, n: int) -> None:
        """``n`` frames published that never reached the node (the transport dropped them), counted."""
        self.counts.lost += n

    def frames(self, decode: Callable[[Any, str], tuple[Any, str]] | None = None,
               ) -> Iterator[tuple[str, float | None, np.ndarray]]:
        """Frames of the newest messages, for :meth:`Localizer.stream` (run on its reader thread).

        ``decode(msg, kind)`` gives the message object and its type where the
        transport hands over raw bytes (ROS 1's ``AnyMsg``); it may raise for a
        message that cannot be read, which is then counted as bad.
        """
        topic = self.spec.image_topic
        for msg, kind, received in self.buffer.items(stop=self._stopping, rate=self.spec.rate):
            k = self.buffer.taken - 1
            where = f"topic {topic} message {k}"
            try:
                if decode is not None:
                    msg, kind = decode(msg, kind)
                image = frame_of(msg, kind, where=where)
            except TopolocError as exc:
                self._bad(str(exc))
                continue
            except Exception as exc:  # a message that does not deserialise: skipped, said, counted
                self._bad(f"{where} cannot be read ({type(exc).__name__}: {exc})")
                continue
            self._in_flight.append((msg.header, received))
            sec, nsec = self.messages.stamp(msg.header)
            stamp = sec + 1e-9 * nsec
            yield f"{topic}#{k}", stamp if stamp > 0 else received, image

    def _bad(self, line: str) -> None:
        self.counts.bad += 1
        self.counts.last_bad = line
        if self.counts.bad == 1 or self.counts.bad % SAY_EVERY == 0:  # said, not once a frame
            self.say(f"frame skipped ({self.counts.bad} so far): {line}")

    # -- answers out ------------------------------------------------------------------------------------------
    def answer(self, line: dict[str, Any]) -> tuple[Any, Any | None]:
        """The messages of one answer: ``std_msgs/String`` (the ``localize`` line, as JSON) and the position.

        The JSON object is the line ``topoloc localize`` writes for the frame,
        with the image header's ``stamp`` (as its ROS names the fields) and
        ``frame_id``, and ``latency_ms`` (message received to answer made).  The
        ``geometry_msgs/PointStamped`` (None where there is none) is the place's
        x, y in ``map_frame``, stamped as the image, for an accepted answer whose
        place has a position and that is not ``"verified": false``.
        """
        msgs = self.messages
        header, received = self._in_flight.popleft()
        sec, nsec = msgs.stamp(header)
        latency = 1e3 * (time.time() - received)
        answer = {**line, "stamp": dict(zip(msgs.stamp_fields, (sec, nsec), strict=True)),
                  "frame_id": header.frame_id, "latency_ms": round(latency, 2)}
        point = None
        if line.get("accepted") and line.get("verified", True) and "x" in line:
            point = msgs.point_stamped()
            point.header.stamp = header.stamp
            point.header.frame_id = self.spec.map_frame
            point.point.x, point.point.y = float(line["x"]), float(line["y"])
        self.counts.answered += 1
        self.counts.latency_ms = latency
        self.counts.latencies.append(latency)
        return msgs.string(data=json.dumps(answer)), point

    def diagnostics(self, stamp: Any, extra: dict[str, Any] | None = None) -> Any:
        """The ``diagnostic_msgs/DiagnosticArray`` of the node now (``stamp``: the header's time)."""
        msgs = self.messages
        counts = self.buffer.counts()
        loc = self._current
        summary = loc.summary() if loc is not None and loc.frames else {}
        lat = np.asarray(self.counts.latencies, float)
        values: dict[str, Any] = {
            "frames_in": counts["received"], "frames_out": self.counts.answered,
            "frames_skipped": counts["skipped"], "frames_waiting": counts["waiting"],
            "frames_bad": self.counts.bad, "last_bad": self.counts.last_bad,
            **({"frames_lost": self.counts.lost} if self.counts_lost else {}),
            "map": str(self.spec.map_file), "map_reloads": self.counts.reloads,
            "image_topic": self.spec.image_topic,
            "latency_ms_last": None if self.counts.latency_ms is None else round(self.counts.latency_ms, 2),
            "latency_ms_median": round(float(np.median(lat)), 2) if lat.size else None,
            **{k: v for k, v in summary.items() if k.startswith(("ms_", "fps", "threads"))},
            **(extra or {}),
        }
        status = msgs.diagnostic_status(name=f"{self.name}: localizer", hardware_id=str(self.spec.map_file))
        calibrated = self.map.threshold is not None
        problem = (extra or {}).get("problem")
        if problem:
            status.level, status.message = msgs.diagnostic_status.ERROR, str(problem)
        elif self.counts.bad and counts["received"] == self.counts.bad:
            status.level = msgs.diagnostic_status.ERROR
            status.message = f"no frame readable: {self.counts.last_bad}"
        elif not calibrated:
            status.level, status.message = msgs.diagnostic_status.WARN, "map not calibrated: every answer is accepted"
        elif self.counts.bad:
            status.level, status.message = msgs.diagnostic_status.WARN, f"{self.counts.bad} frames unreadable"
        else:
            status.level, status.message = msgs.diagnostic_status.OK, "localizing"
        status.values = [msgs.key_value(key=k, value=v if isinstance(v, str) else json.dumps(v))
                         for k, v in values.items()]
        arr = msgs.diagnostic_array(status=[status])
        arr.header.stamp = stamp
        return arr

    # -- running ----------------------------------------------------------------------------------------------
    def run(self, publish: Callable[[Any, Any | None], None],
            decode: Callable[[Any, str], tuple[Any, str]] | None = None) -> int:
        """Localise the frames and ``publish(answer, position)`` each answer until stopped; the exit status.

        Between two frames a changed setting or a reload due is taken (the
        frames in flight are answered first, with the map they were matched
        against; a sequence under way starts over).
        """
        while not self._stop.is_set():
            self._take_changes()
            loc = self.localizer
            self._current = loc
            self._in_flight.clear()
            for line in loc.stream(self.frames(decode)):
                publish(*self.answer(line))
        return self.exit_status


#: What the localiser is built from: a change of any of these builds a new one.
_LOCALIZER_FIELDS = ("map_file", "top_k", "prefetch", "sequence", "verification")


def replace_spec(spec: NodeSpec, changes: dict[str, Any]) -> NodeSpec:
    """``spec`` with the parameters ``changes`` (flat names) set; a bad value is a one-line error naming it."""
    values = {**spec.param_values(), **changes}
    try:
        return NodeSpec.from_params(values)
    except ParameterError as exc:
        raise node_error(exc) from None


__all__ = ["CHECK_S", "COMPRESSED", "IMAGE", "Counts", "Messages", "NodeCore", "file_stamp", "frame_of", "node_error",
           "replace_spec"]
