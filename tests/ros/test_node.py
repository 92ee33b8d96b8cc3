"""The ROS 1 node on a real roscore (loopback port), as its own process, fed by ``rosbag play`` (issue 37).

Skipped, naming what is missing, where ROS 1 (Debian's ``ros-base``, ``python3-rospy`` and the message
packages, which ``.ci/run`` installs where apt is available) is not installed.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import pytest
from tests.ros.probes import BagFrames, assert_answers_equal_localize
from tests.ros.probes import ok as _ok
from tests.ros.probes import records as _records
from tests.ros.probes import stop as _stop

from topoloc.ros.probe import LocalMaster, free_port, wait_for

SRC = Path(__file__).resolve().parents[2] / "src"
T0 = 1_700_000_000
TOPICS = {"bgr8": "/cam/bgr8", "mono8": "/cam/mono8", "compressed": "/cam/compressed"}


def _ros_missing() -> str | None:
    for tool in ("roscore", "rosbag", "rosservice", "roslaunch"):
        if shutil.which(tool) is None:
            return f"{tool} is not on PATH (apt-get install ros-base python3-rosbag)"
    probe = subprocess.run([sys.executable, "-c", "from topoloc.ros import import_rospy; import_rospy()"],
                           env={**os.environ, "PYTHONPATH": str(SRC)}, capture_output=True, text=True)
    if probe.returncode != 0:
        return (probe.stderr.strip().splitlines() or ["rospy cannot be imported"])[-1]
    return None


_MISSING = _ros_missing()
pytestmark = pytest.mark.skipif(_MISSING is not None, reason=f"ROS 1 is not installed: {_MISSING}")


class Ros(LocalMaster):
    """A roscore on a loopback port, and the processes of one test beside it."""

    def __init__(self, root: Path) -> None:
        super().__init__(root, extra_path=SRC)
        self.env["TOPOLOC_FEATURES"] = "sift"

    def start(self, args: list[str], name: str) -> subprocess.Popen[str]:
        out = (self.root / f"{name}.err").open("w")
        return subprocess.Popen([sys.executable, *args], env=self.env, stdout=subprocess.PIPE, stderr=out, text=True)

    def node(self, map_file: Path, name: str, *extra: str) -> subprocess.Popen[str]:
        proc = self.start(["-m", "topoloc", "ros-node", str(map_file), *extra, f"__name:={name}"], name)
        topic = next((extra[k + 1] for k, a in enumerate(extra) if a == "--image-topic"), None)
        if topic is not None:
            wait_for(f"{name} to subscribe to {topic}", lambda: f"/{name}" in self.subscribers(topic) or
                  proc.poll() is not None)
            assert proc.poll() is None, self.err(name)
        return proc

    def probe(self, out: Path, *args: str) -> subprocess.Popen[str]:
        proc = self.start(["-m", "topoloc.ros.probe", "--out", str(out), *args], out.stem)
        for topic in [args[k + 1] for k, a in enumerate(args) if a == "--answers"]:
            wait_for(f"the probe to subscribe to {topic}", lambda t=topic: bool(self.subscribers(t)))
        return proc

    def play(self, bag: Path, *args: str) -> None:
        subprocess.run(["rosbag", "play", "-q", "-d", "2", *args, str(bag)], env=self.env, check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=120)

    def err(self, name: str) -> str:
        return (self.root / f"{name}.err").read_text()


@pytest.fixture(scope="module")
def ros(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Ros]:
    r = Ros(tmp_path_factory.mktemp("ros"))
    yield r
    r.close()


@pytest.fixture(scope="module")
def route(tiny_route: dict[str, Any], tiny_route_map: Path, tmp_path_factory: pytest.TempPathFactory,
          ) -> dict[str, Any]:
    """The tiny route's map, and the dusk tour as a bag with bgr8, mono8 and compressed topics."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    root = tmp_path_factory.mktemp("ros_route")
    map_file = tiny_route_map
    files = sorted(tiny_route["query"].root.glob("*.jpg"))
    ts = get_typestore(Stores.ROS1_NOETIC)
    frames = BagFrames(ts, ts.serialize_ros1, seq=0)
    bag = root / "dusk.bag"
    with Writer(bag) as w:
        frames.write_tour(w, TOPICS, files, T0)
    # A camera far faster than the node matches: the frames of the mono8 topic, 400 of them at 200 Hz (played
    # faster still).
    fast = root / "fast.bag"
    with Writer(fast) as w:
        conn = w.add_connection("/cam/fast", "sensor_msgs/msg/Image", typestore=ts)
        greys = [cv2.cvtColor(cv2.imread(str(f), cv2.IMREAD_COLOR), cv2.COLOR_BGR2GRAY) for f in files]
        for k in range(400):
            sec = T0 + 0.005 * k
            w.write(conn, round(sec * 1e9), frames.raw(sec, greys[k % len(greys)], "mono8"))
    return {"root": root, "map": map_file, "bag": bag, "fast": fast, "n": len(files), "query": tiny_route["query"]}


ANSWER_KEYS = ("place", "score", "accepted", "top", "x", "y", "time")


def test_answers_equal_localize_on_each_encoding_of_the_bag(ros: Ros, route: dict[str, Any]) -> None:
    """bgr8, mono8 and compressed topics played by rosbag play: the answers are localize's lines, frame for frame."""
    nodes = {k: ros.node(route["map"], f"topoloc_{k}", "--image-topic", topic, "--queue", "1000")
             for k, topic in TOPICS.items()}
    out = route["root"] / "answers.jsonl"
    probe = ros.probe(out, *[a for k in TOPICS for a in ("--answers", f"/topoloc_{k}/answer")])
    ros.play(route["bag"], "-r", "2")
    n = route["n"]
    wait_for("every answer", lambda: all(sum(r["topic"] == f"/topoloc_{k}/answer" for r in _records(out, "answer"))
                                      >= n for k in TOPICS), timeout=90)

    def counted(k: str) -> bool:
        last = [d for d in _records(out, "diagnostics") if d["name"].startswith(f"/topoloc_{k}")]
        return bool(last) and int(last[-1]["values"]["frames_out"]) == n

    wait_for("diagnostics of every frame", lambda: all(counted(k) for k in TOPICS), timeout=30)
    for k in TOPICS:
        assert _stop(nodes[k]) == 0
        err = ros.err(f"topoloc_{k}")
        assert "Traceback" not in err
        # One line when it stops, with the counts: every frame in was answered, none skipped.
        assert f"stopped (SIGTERM): {n} frames in, {n} answered, 0 skipped, 0 unreadable" in err, err
    _stop(probe)
    answers = _records(out, "answer")
    # Frame for frame localize's lines, with the frame's own header: stamp and frame id.
    assert_answers_equal_localize(answers, route, TOPICS, n, ANSWER_KEYS,
                                  lambda stamp: stamp["secs"] + 1e-9 * stamp["nsecs"])
    assert all("verified" not in a or isinstance(a["verified"], bool) for a in answers)
    # The diagnostics counted the frames of each node.
    diags = _records(out, "diagnostics")
    for k in TOPICS:
        last = [d for d in diags if d["name"].startswith(f"/topoloc_{k}")]
        assert last, f"no diagnostics from /topoloc_{k}"
        values = last[-1]["values"]
        assert int(values["frames_in"]) == n and int(values["frames_skipped"]) == 0
        assert float(values["ms_extract_mean"]) > 0
        assert last[-1]["level"] == 1  # WARN: the map is not calibrated, every answer accepted


def test_a_camera_faster_than_matching_leaves_no_backlog(ros: Ros, route: dict[str, Any]) -> None:
    """400 frames at 800 Hz: skipped frames are counted, answers stay current, latency stays bounded."""
    node = ros.node(route["map"], "topoloc_fast", "--image-topic", "/cam/fast")
    out = route["root"] / "fast.jsonl"
    probe = ros.probe(out, "--answers", "/topoloc_fast/answer")
    ros.play(route["fast"], "-r", "4")  # 800 frames a second
    last_stamp = T0 + 0.005 * 399
    wait_for("the answer to the last frame",
          lambda: any(abs(a["time"] - last_stamp) < 1e-6 for a in _records(out, "answer")), timeout=30)
    assert _stop(node) == 0
    _stop(probe)
    err = ros.err("topoloc_fast")
    line = next(x for x in err.splitlines() if "stopped (SIGTERM)" in x)
    n_in, n_out, n_skipped, n_bad = (int(w) for w in
                                     [line.split(": ")[-1].split(", ")[i].split()[0] for i in range(4)])
    answers = _records(out, "answer")
    assert n_in == 400 and n_bad == 0
    assert n_out == len(answers) and n_out + n_skipped == n_in
    assert n_skipped > 0, "at 800 Hz some frames must be skipped"
    times = [a["time"] for a in answers]
    assert times == sorted(times) and len(set(times)) == len(times)
    # No backlog: each answer is about a frame received shortly before (a node matching every frame in turn
    # would answer the last of 400 frames, sent within half a second, only after matching all the others), and
    # the last frame sent is answered (waited for above).
    worst = max(a["latency_ms"] for a in answers)
    assert worst < 3000, f"latency {worst:.0f} ms with {n_skipped} frames skipped"


def test_a_map_rewritten_while_it_runs_is_reloaded(ros: Ros, route: dict[str, Any]) -> None:
    """map calibrate rewrites the map file: the node loads it (watching the file), again on SIGHUP and on ~reload."""
    map_file = route["root"] / "reloaded.tlm"
    shutil.copy(route["map"], map_file)
    node = ros.node(map_file, "topoloc_reload", "--image-topic", "/cam/mono8")
    out = route["root"] / "reload.jsonl"
    probe = ros.probe(out)
    _ok(["map", "calibrate", str(map_file), "--query", str(route["query"].root), "--sequence", "0", "-q"])
    wait_for("the reload", lambda: "map reloaded" in ros.err("topoloc_reload"), timeout=30)
    wait_for("calibrated diagnostics", lambda: any(d["name"].startswith("/topoloc_reload") and d["level"] == 0
                                                for d in _records(out, "diagnostics")), timeout=30)
    node.send_signal(signal.SIGHUP)
    wait_for("the second reload", lambda: ros.err("topoloc_reload").count("map reloaded") == 2, timeout=30)
    called = subprocess.run(["rosservice", "call", "/topoloc_reload/reload"], env=ros.env, capture_output=True,
                            text=True, timeout=60)
    assert "success: True" in called.stdout, called.stdout + called.stderr
    wait_for("the third reload", lambda: ros.err("topoloc_reload").count("map reloaded") == 3, timeout=30)
    # A file that is no map put in its place (atomically): one line, and the node keeps the map it has.
    broken = route["root"] / "broken.tmp"
    broken.write_bytes(b"not a map")
    os.replace(broken, map_file)
    wait_for("the refusal", lambda: "map not reloaded, keeping the one loaded" in ros.err("topoloc_reload"), timeout=30)
    assert node.poll() is None
    assert _stop(node, signal.SIGINT) == 0
    _stop(probe)
    err = ros.err("topoloc_reload")
    assert "Traceback" not in err and "stopped (SIGINT)" in err
    reloads = [d["values"]["map_reloads"] for d in _records(out, "diagnostics") if d["name"].startswith("/topoloc_re")]
    assert reloads and int(reloads[-1]) >= 1


def test_the_shipped_launch_file_starts_the_node(ros: Ros, route: dict[str, Any]) -> None:
    """docs/ros.md's roslaunch line, with the manifest-only package on ROS_PACKAGE_PATH."""
    import topoloc.ros

    share = Path(topoloc.ros.__file__).parent / "share"
    env = {**ros.env, "ROS_PACKAGE_PATH": str(share), "TOPOLOC_PYTHON": sys.executable}
    log = (ros.root / "roslaunch.out").open("w")
    launch = subprocess.Popen(["roslaunch", "topoloc_ros", "localize.launch", f"map:={route['map']}",
                               "image:=/cam/launched", "queue:=2"], env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        wait_for("the launched node", lambda: "/topoloc" in ros.subscribers("/cam/launched") or
              launch.poll() is not None, timeout=90)
        assert launch.poll() is None, (ros.root / "roslaunch.out").read_text()
        assert ros.param("/topoloc/queue") == 2
    finally:
        assert _stop(launch, signal.SIGINT, timeout=60) == 0
        log.close()
    out = (ros.root / "roslaunch.out").read_text()
    assert "stopped (SIGINT)" in out or "stopped (SIGTERM)" in out, out
    assert "Traceback" not in out


def test_losing_the_master_is_one_line(route: dict[str, Any], tmp_path: Path) -> None:
    own = Ros(tmp_path)
    try:
        node = own.node(route["map"], "topoloc_orphan", "--image-topic", "/cam/mono8")
    finally:
        own.close()
    assert node.wait(timeout=30) == 1
    lines = [x for x in own.err("topoloc_orphan").splitlines() if x.strip() and "not calibrated" not in x]
    assert len(lines) == 1 and "the ROS master at" in lines[0] and "is gone" in lines[0], lines


def test_no_master_and_bad_settings_are_one_line(ros: Ros, route: dict[str, Any], tmp_path: Path) -> None:
    env = {**ros.env, "ROS_MASTER_URI": f"http://127.0.0.1:{free_port()}"}
    r = subprocess.run([sys.executable, "-m", "topoloc", "ros-node", str(route["map"])], env=env, capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "no ROS master at" in r.stderr, r.stderr
    r = subprocess.run([sys.executable, "-m", "topoloc", "ros-node", str(route["map"]), "--queue", "0"], env=ros.env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "queue must be" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    r = subprocess.run([sys.executable, "-m", "topoloc", "ros-node", str(tmp_path / "none.tlm")], env=ros.env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "none.tlm" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_numpy_is_this_environments_and_rospy_the_systems(ros: Ros) -> None:
    """The node's process imports rospy from the system's ROS packages without their NumPy shadowing ours."""
    code = ("import numpy, cv2\nfrom topoloc.ros import import_rospy\nrospy = import_rospy()\n"
            "import numpy as n2, genpy\nprint(n2.__file__); print(rospy.__file__); print(numpy is n2)")
    r = subprocess.run([sys.executable, "-c", code], env=ros.env, capture_output=True, text=True, timeout=60)
    numpy_file, rospy_file, same = r.stdout.split()
    assert same == "True"
    assert Path(numpy_file).resolve().is_relative_to(Path(sys.prefix).resolve()) or "site-packages" in numpy_file
    assert "site-packages" in numpy_file  # a virtual environment's (or pip's), never Debian's dist-packages
    assert "dist-packages" in rospy_file or "rospy" in sys.modules
