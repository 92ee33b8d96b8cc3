"""What both ROS nodes' tests do alike: read a probe's record, stop a process, run topoloc, compare with localize."""

from __future__ import annotations

import json
import signal
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from topoloc.cli.main import app


def records(path: Path, kind: str | None = None) -> list[dict[str, Any]]:
    """The probe's JSON lines (``topoloc.ros.record``) of ``kind`` (every kind: None); none before it wrote any."""
    if not path.exists():
        return []
    lines = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [r for r in lines if kind is None or r.get("kind") == kind]


def stop(proc: subprocess.Popen[str], sig: int = signal.SIGTERM, timeout: float = 30.0) -> int:
    """Stop ``proc`` as a user does (``sig``); its exit status."""
    if proc.poll() is None:
        proc.send_signal(sig)
    return proc.wait(timeout=timeout)


def ok(args: list[str]) -> str:
    """``topoloc ARGS``, which must succeed; its standard output."""
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output + repr(result.exception)
    return result.stdout


def assert_answers_equal_localize(answers: list[dict[str, Any]], route: dict[str, Any], topics: dict[str, str],
                                  n: int, keys: tuple[str, ...], seconds: Callable[[dict[str, Any]], float]) -> None:
    """Each node's answers (``/topoloc_K/answer`` for K of ``topics``) are ``localize``'s lines of the bag's topic,
    frame for frame: the ``keys`` equal, positions given, the frame's own stamp (``seconds(stamp)``) and frame id."""
    for k, topic in topics.items():
        lines_file = route["root"] / f"localize_{k}.jsonl"
        ok(["localize", str(route["map"]), str(route["bag"]), "--topic", topic, "--out", str(lines_file), "-q"])
        expected = [json.loads(line) for line in lines_file.read_text().splitlines()]
        got = [a for a in answers if a["topic"] == f"/topoloc_{k}/answer"]
        assert len(got) == len(expected) == n
        for a, e in zip(got, expected, strict=True):
            assert {key: a.get(key) for key in keys} == {key: e.get(key) for key in keys}
            assert "x" in a  # the map has positions
            assert seconds(a["stamp"]) == pytest.approx(e["time"], abs=1e-6)
            assert a["frame_id"] == "camera"


class BagFrames:
    """Image messages of a bag as ``rosbags`` writes them for either ROS (``serialize``: the typestore's
    ``serialize_ros1`` or ``serialize_cdr``), each stamped with its time and the frame id ``camera``."""

    def __init__(self, ts: Any, serialize: Callable[[Any, str], Any], **header_fields: Any) -> None:
        self.ts, self.serialize, self.header_fields = ts, serialize, header_fields

    def header(self, sec: float) -> Any:
        t = self.ts.types
        stamp = t["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=round((sec % 1) * 1e9))
        return t["std_msgs/msg/Header"](**self.header_fields, stamp=stamp, frame_id="camera")

    def raw(self, sec: float, img: np.ndarray, encoding: str) -> bytes:
        """A ``sensor_msgs/Image`` of ``img`` (rows of ``step`` bytes, no padding)."""
        data = np.ascontiguousarray(img).reshape(-1)
        msg = self.ts.types["sensor_msgs/msg/Image"](
            header=self.header(sec), height=img.shape[0], width=img.shape[1], encoding=encoding, is_bigendian=0,
            step=data.size // img.shape[0], data=data)
        return bytes(self.serialize(msg, "sensor_msgs/msg/Image"))

    def compressed(self, sec: float, jpeg: bytes) -> bytes:
        msg = self.ts.types["sensor_msgs/msg/CompressedImage"](header=self.header(sec), format="jpeg",
                                                                data=np.frombuffer(jpeg, np.uint8).copy())
        return bytes(self.serialize(msg, "sensor_msgs/msg/CompressedImage"))

    def write_tour(self, writer: Any, topics: dict[str, str], files: list[Path], t0: float) -> None:
        """``files`` at 4 Hz from ``t0`` on the bgr8, mono8 and compressed topics of ``topics``."""
        conns = {k: writer.add_connection(topic, "sensor_msgs/msg/CompressedImage" if k == "compressed"
                                          else "sensor_msgs/msg/Image", typestore=self.ts)
                 for k, topic in topics.items()}
        for k, f in enumerate(files):
            sec = t0 + 0.25 * k
            bgr = cv2.imread(str(f), cv2.IMREAD_COLOR)
            writer.write(conns["bgr8"], round(sec * 1e9), self.raw(sec, bgr, "bgr8"))
            writer.write(conns["mono8"], round(sec * 1e9), self.raw(sec, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY),
                                                                     "mono8"))
            writer.write(conns["compressed"], round(sec * 1e9), self.compressed(sec, f.read_bytes()))
