"""What the ROS probes record (:mod:`topoloc.ros.probe`, :mod:`topoloc.ros.probe2`): one JSON object per line.

Answers with their publish-to-answer latency, diagnostics statuses, positions and
a summary last, written whole by any subscriber thread; the tests and
``benchmarks/bench_ros_latency.py`` read them back.  No ROS in it: each probe
says how its transport writes a stamp and a diagnostics level.
"""

from __future__ import annotations

import json
import signal
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any


class ProbeRecord:
    """A probe's JSON-lines file, each record flushed as it comes (the tests read it while the probe runs)."""

    def __init__(self, path: Path) -> None:
        self._fh = path.open("w")
        self._lock = threading.Lock()

    def write(self, record: dict[str, Any]) -> None:
        with self._lock:
            self._fh.write(json.dumps(record) + "\n")
            self._fh.flush()

    def answer(self, data: str, topic: str, seconds: Callable[[dict[str, Any]], float]) -> None:
        """An answer (the node's JSON line ``data``) and its latency: now less its stamp, ``seconds(stamp)``."""
        now = time.time()
        answer = json.loads(data)
        self.write({"kind": "answer", "topic": topic, "received": now,
                    "publish_to_answer_ms": round(1e3 * (now - seconds(answer["stamp"])), 3), **answer})

    def diagnostics(self, statuses: Iterable[Any], level: Callable[[Any], int] = int) -> None:
        """Each status of a ``diagnostic_msgs/DiagnosticArray``, its level read by ``level``."""
        for status in statuses:
            self.write({"kind": "diagnostics", "received": time.time(), "name": status.name,
                        "level": level(status.level), "message": status.message,
                        "values": {kv.key: kv.value for kv in status.values}})

    def close(self) -> None:
        self._fh.close()


def stop_on_signals() -> threading.Event:
    """An event that SIGINT and SIGTERM set: the probe stops publishing and writes its summary."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


__all__ = ["ProbeRecord", "stop_on_signals"]
