"""Live sources: the newest-frame buffer, and a camera stream served on 127.0.0.1 by the test (issue 37)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from topoloc.datasets.sources.live import LiveSource, Newest, is_live_source
from topoloc.errors import TopolocError
from topoloc.synth.stream import MjpegServer

SRC = Path(__file__).resolve().parents[3] / "src"


def jpegs_of(n: int = 8) -> list[bytes]:
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.integers(0, 256, (96, 128 * 3, 3), dtype=np.uint8), (5, 5), 0)
    return [cv2.imencode(".jpg", np.ascontiguousarray(base[:, 16 * k:16 * k + 128]))[1].tobytes() for k in range(n)]


@pytest.fixture()
def server() -> Iterator[MjpegServer]:
    s = MjpegServer(jpegs_of(), fps=20.0)
    yield s
    s.close()


def test_newest_keeps_the_newest_and_counts_the_rest() -> None:
    buf: Newest[int] = Newest(1)
    for k in range(5):
        buf.put(k)
    buf.close()
    assert list(buf.items()) == [4]
    assert buf.counts() == {"received": 5, "skipped": 4, "waiting": 0}
    two: Newest[int] = Newest(2)
    for k in range(5):
        two.put(k)
    two.close()
    assert list(two.items()) == [3, 4] and two.skipped == 3


def test_newest_hands_over_as_items_arrive_and_stops() -> None:
    buf: Newest[int] = Newest(1)
    got: list[int] = []
    stop = threading.Event()
    reader = threading.Thread(target=lambda: got.extend(buf.items(stop=stop.is_set)))
    reader.start()
    for k in range(3):
        buf.put(k)
        deadline = time.monotonic() + 5
        while len(got) < k + 1 and time.monotonic() < deadline:
            time.sleep(0.01)
    stop.set()
    reader.join(timeout=5)
    assert not reader.is_alive() and got == [0, 1, 2] and buf.skipped == 0


def test_newest_raises_the_producers_error_and_refuses_a_bad_queue() -> None:
    buf: Newest[int] = Newest(1)
    buf.put(1)
    buf.close(TopolocError("camera unplugged"))
    it = buf.items()
    assert next(it) == 1
    with pytest.raises(TopolocError, match="camera unplugged"):
        next(it)
    with pytest.raises(TopolocError, match="queue must be a whole number >= 1"):
        Newest(0)


def test_newest_rate_limits_what_it_hands_over() -> None:
    buf: Newest[int] = Newest(1)
    stop = threading.Event()

    def produce() -> None:
        for k in range(60):  # 60 items over 0.6 s
            buf.put(k)
            time.sleep(0.01)
        buf.close()

    t = threading.Thread(target=produce)
    t.start()
    got = list(buf.items(stop=stop.is_set, rate=5.0))  # at most 5 a second: 3 or 4 of them
    t.join()
    assert 2 <= len(got) <= 5 and got == sorted(got)
    assert buf.received == 60 and buf.skipped == 60 - len(got)


def test_what_is_a_live_source(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert is_live_source("rtsp://camera.local/stream") and is_live_source("http://127.0.0.1:8080/video.mjpg")
    assert is_live_source("0") and is_live_source("/dev/null")  # an index; a character device
    (tmp_path / "1").mkdir()
    assert not is_live_source("1")  # a folder of that name is a folder
    assert not is_live_source("file:///tmp/x.mp4") and not is_live_source(str(tmp_path))
    assert not is_live_source("route/dusk") and not is_live_source("drive.bag")


def test_an_mjpeg_stream_is_read_as_the_same_frames_as_its_jpeg_files(server: MjpegServer, tmp_path: Path) -> None:
    """A stream's JPEGs are decoded by the one rule image files and ROS messages take: the same grey pixels."""
    from topoloc.datasets.decode import read_image

    jpegs = jpegs_of()
    files = []
    for k, data in enumerate(jpegs):
        files.append(tmp_path / f"{k}.jpg")
        files[-1].write_bytes(data)
    reference = [read_image(f) for f in files]
    source = LiveSource(server.url)
    assert source.encoded  # FFmpeg hands over the stream's own JPEGs
    got = list(source.frames())
    assert source.frames_read == len(jpegs) and source.frames_bad == 0
    assert len(got) + source.buffer.skipped == len(jpegs) and len(got) >= 2
    for name, t, image, index in got:
        k = int(name.rsplit("#", 1)[1])
        assert name.startswith(server.url) and index == k
        np.testing.assert_array_equal(image, reference[k])
        assert abs(t - time.time()) < 60  # wall-clock time of capture


def test_a_stream_that_cannot_be_opened_is_one_line() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    url = f"http://127.0.0.1:{port}/none.mjpg"
    with pytest.raises(TopolocError, match=f"cannot open the camera or stream: {url}"):
        LiveSource(url, open_timeout_s=2)


def test_a_password_in_the_url_is_not_repeated() -> None:
    with pytest.raises(TopolocError) as info:
        LiveSource("rtsp://user:secret@127.0.0.1:1/stream", open_timeout_s=2)
    assert "secret" not in str(info.value) and "user:***@" in str(info.value)


# -- topoloc localize MAP STREAM ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def stream_map(tiny_route: dict[str, Any], tiny_route_map: Path, tmp_path_factory: pytest.TempPathFactory,
               ) -> dict[str, Any]:
    """The tiny route's map; the dusk tour's JPEGs as a stream's frames and as a file of them."""
    root = tmp_path_factory.mktemp("live_map")
    map_file = tiny_route_map
    jpegs = [p.read_bytes() for p in sorted(tiny_route["query"].root.glob("*.jpg"))]
    video = root / "dusk.mjpeg"
    video.write_bytes(b"".join(jpegs))
    return {"root": root, "map": map_file, "jpegs": jpegs, "video": video, "folder": tiny_route["query"].root}


def _ok(args: list[str]) -> str:
    from typer.testing import CliRunner

    from topoloc.cli.main import app

    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output + repr(r.exception)
    return r.stdout


def _topoloc(*args: str, **kwargs: Any) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen([sys.executable, "-m", "topoloc.cli.main", *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kwargs)


def _lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()] if path.exists() else []


KEYS = ("place", "score", "accepted", "top", "x", "y")


def test_localize_a_stream_answers_as_localize_of_its_frames(stream_map: dict[str, Any]) -> None:
    """The stream ends: the answers are those of the same frames read from a file, then one line naming it."""
    server = MjpegServer(stream_map["jpegs"], fps=10.0)
    try:
        out = stream_map["root"] / "live.jsonl"
        proc = _topoloc("localize", str(stream_map["map"]), server.url, "--out", str(out), "-q")
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        server.close()
    assert proc.returncode == 0, stderr
    ref_file = stream_map["root"] / "file.jsonl"
    # The stream's JPEGs are the folder's images: decoded by one rule, they are answered alike (issue #49).
    _ok(["localize", str(stream_map["map"]), str(stream_map["folder"]), "--out", str(ref_file), "-q"])
    reference = _lines(ref_file)
    lines = _lines(out)
    summary = json.loads(stdout.strip().splitlines()[-1])
    n = len(stream_map["jpegs"])
    assert summary["frames_read"] == n and summary["ended"] == "stream" and summary["stream"] == server.url
    assert len(lines) + summary["frames_skipped"] == n and summary["frames"] == len(lines) >= 2
    assert summary["frames_bad"] == 0
    for line in lines:
        k = int(line["image"].rsplit("#", 1)[1])
        assert line["frame"] == k  # the frame's number in the stream, skipped frames leaving gaps
        assert {key: line.get(key) for key in KEYS} == {key: reference[k].get(key) for key in KEYS}
        assert abs(line["time"] - time.time()) < 120  # the wall-clock time the frame was captured
    said = [x for x in stderr.splitlines() if x.strip() and "not calibrated" not in x]
    assert said == [f"WARNING: the stream ended after {n} frames: {server.url}"] or said == [
        f"the stream ended after {n} frames: {server.url}"], said


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_stops_a_stream_cleanly(stream_map: dict[str, Any], sig: int) -> None:
    server = MjpegServer(stream_map["jpegs"], fps=15.0, loops=1000)
    try:
        out = stream_map["root"] / f"stopped_{sig}.jsonl"
        proc = _topoloc("localize", str(stream_map["map"]), server.url, "--out", str(out), "-q")
        deadline = time.monotonic() + 60
        while len(_lines(out)) < 3 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.1)
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        server.close()
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stderr and "stream ended" not in stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["ended"] == signal.Signals(sig).name and summary["frames"] == len(_lines(out)) >= 3


def test_localize_a_stream_that_cannot_be_opened_is_one_line(stream_map: dict[str, Any]) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    url = f"http://127.0.0.1:{port}/video.mjpg"
    proc = _topoloc("localize", str(stream_map["map"]), url, "--out", str(stream_map["root"] / "none.jsonl"))
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 2 and stderr.strip() == f"topoloc: error: cannot open the camera or stream: {url}"
    proc = _topoloc("localize", str(stream_map["map"]), url, str(stream_map["video"]), "--out",
                    str(stream_map["root"] / "none.jsonl"))
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 2 and stderr.strip().startswith("topoloc: error: a camera or stream is read alone")


# -- a bad frame in a live stream (issue #49) --------------------------------------------------------------
def _bad_parts(good: bytes) -> dict[str, bytes]:
    """Parts a stream may carry between good frames, each refused by the one decoding rule."""
    import struct

    rng = np.random.default_rng(5)
    enormous = bytearray(good)
    at = enormous.find(b"\xff\xc0")  # the baseline frame header: height and width after length and precision
    enormous[at + 5:at + 9] = struct.pack(">HH", 60000, 60000)  # 3.6 billion pixels announced
    return {"random bytes": rng.integers(0, 256, 5000, dtype=np.uint8).tobytes(),
            "truncated JPEG": good[: len(good) // 2],
            "enormous JPEG": bytes(enormous)}


@pytest.mark.parametrize("kind", ["random bytes", "truncated JPEG", "enormous JPEG"])
def test_one_rule_refuses_a_bad_frame_from_every_source(kind: str, tmp_path: Path) -> None:
    """A file, a ROS CompressedImage and a stream's part with the same bytes: all refused, by one rule."""
    from types import SimpleNamespace

    from topoloc.datasets.decode import read_image
    from topoloc.datasets.sources.rosbag import decode_image

    good = jpegs_of(1)[0]
    bad = _bad_parts(good)[kind]
    f = tmp_path / "bad.jpg"
    f.write_bytes(bad)
    with pytest.raises(TopolocError):
        read_image(f)
    msg = SimpleNamespace(data=bad, format="jpeg")
    with pytest.raises(TopolocError):
        decode_image(msg, "sensor_msgs/msg/CompressedImage", gray=True, where="topic /cam message 0",
                     path=Path("/cam"))
    server = MjpegServer([good, bad, good], fps=5.0)
    try:
        source = LiveSource(server.url)
        got = list(source.frames())
    finally:
        server.close()
    assert source.frames_read == 3 and source.frames_bad + source.buffer.skipped >= 1
    assert {index for _, _, _, index in got} <= {0, 2}  # the bad part (1) is never handed over


def test_localize_goes_on_past_a_bad_part_of_a_stream(stream_map: dict[str, Any]) -> None:
    """One part of random bytes between good frames stopped localize with 'the stream ended' (issue #49)."""
    jpegs = stream_map["jpegs"]
    parts = [*jpegs[:3], _bad_parts(jpegs[0])["random bytes"], *jpegs[3:6], _bad_parts(jpegs[0])["truncated JPEG"],
             *jpegs[6:]]
    server = MjpegServer(parts, fps=4.0)
    try:
        out = stream_map["root"] / "bad_part.jsonl"
        proc = _topoloc("localize", str(stream_map["map"]), server.url, "--out", str(out), "-q", "--prefetch", "0")
        stdout, stderr = proc.communicate(timeout=180)
    finally:
        server.close()
    assert proc.returncode == 0, stderr
    summary = json.loads(stdout.strip().splitlines()[-1])
    lines = _lines(out)
    assert summary["frames_read"] == len(parts) and summary["ended"] == "stream"
    assert summary["frames_bad"] + summary["frames_skipped"] + len(lines) == len(parts)
    assert summary["frames_bad"] >= 1 and [x for x in stderr.splitlines() if "frame skipped (1 so far)" in x]
    answered = [line["frame"] for line in lines]
    assert 3 not in answered and 7 not in answered  # the bad parts are never answered
    assert max(answered) > 7  # the good frames after them are
    for line in lines:
        assert line["frame"] == int(line["image"].rsplit("#", 1)[1])


def test_frame_is_the_frames_index_in_its_input_for_every_input_kind(stream_map: dict[str, Any],
                                                                    tmp_path: Path) -> None:
    """Files: their position; a video read every few frames: the video frame's number; two inputs: in order."""
    folder, video = stream_map["folder"], stream_map["video"]
    n = len(stream_map["jpegs"])
    out = tmp_path / "a.jsonl"
    _ok(["localize", str(stream_map["map"]), str(folder), "--out", str(out), "-q"])
    assert [x["frame"] for x in _lines(out)] == list(range(n))
    _ok(["localize", str(stream_map["map"]), str(video), "--every-s", "0.2", "--out", str(out), "-q"])
    kept = _lines(out)
    assert len(kept) < n and [x["frame"] for x in kept] == [int(x["image"].rsplit("#", 1)[1]) for x in kept]
    _ok(["localize", str(stream_map["map"]), str(video), str(folder), "--every-s", "0.2", "--out", str(out), "-q"])
    both = _lines(out)
    frames = [x["frame"] for x in both]
    assert frames == sorted(frames) and len(set(frames)) == len(frames)
    assert frames[len(kept):] == list(range(n, 2 * n))  # the folder's images after the video's n frames
