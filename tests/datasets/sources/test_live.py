"""Live sources: the newest-frame buffer, and a camera stream served on 127.0.0.1 by the test (issue 37)."""

from __future__ import annotations

import http.server
import json
import os
import signal
import socket
import socketserver
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

SRC = Path(__file__).resolve().parents[3] / "src"


class MjpegServer:
    """An HTTP MJPEG stream (multipart/x-mixed-replace) of ``frames`` at ``fps``, looped ``loops`` times."""

    def __init__(self, jpegs: list[bytes], *, fps: float = 20.0, loops: int = 1) -> None:
        served = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                try:
                    for _ in range(served.loops):
                        for data in jpegs:
                            if served.closed.is_set():
                                return
                            self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n"
                                             % len(data) + data + b"\r\n")
                            time.sleep(1.0 / served.fps)
                except (BrokenPipeError, ConnectionResetError):  # the client stopped reading
                    return

            def log_message(self, *args: object) -> None:
                pass

        self.fps, self.loops = fps, loops
        self.closed = threading.Event()
        self.server = socketserver.ThreadingTCPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/stream.mjpg"

    def close(self) -> None:
        self.closed.set()
        self.server.shutdown()
        self.server.server_close()


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


def test_an_mjpeg_stream_is_read_as_the_same_frames_as_its_file(server: MjpegServer, tmp_path: Path) -> None:
    """The stream's frames are FFmpeg's decoding of its JPEGs, as a file of them reads: the same grey pixels."""
    from topoloc.datasets.sources.video import VideoSource

    jpegs = jpegs_of()
    file = tmp_path / "frames.mjpeg"
    file.write_bytes(b"".join(jpegs))
    reference = [f.image for f in VideoSource(file).frames()]
    assert len(reference) == len(jpegs)
    source = LiveSource(server.url)
    got = list(source.frames())
    assert source.frames_read == len(jpegs)
    assert len(got) + source.buffer.skipped == len(jpegs) and len(got) >= 2
    for name, t, image in got:
        k = int(name.rsplit("#", 1)[1])
        assert name.startswith(server.url)
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
    return {"root": root, "map": map_file, "jpegs": jpegs, "video": video}


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
    _ok(["localize", str(stream_map["map"]), str(stream_map["video"]), "--out", str(ref_file), "-q"])
    reference = _lines(ref_file)
    lines = _lines(out)
    summary = json.loads(stdout.strip().splitlines()[-1])
    n = len(stream_map["jpegs"])
    assert summary["frames_read"] == n and summary["ended"] == "stream" and summary["stream"] == server.url
    assert len(lines) + summary["frames_skipped"] == n and summary["frames"] == len(lines) >= 2
    for line in lines:
        k = int(line["image"].rsplit("#", 1)[1])
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
