"""The ROS 2 node as its own process, over DDS on this machine, fed by a probe replaying a ROS 2 bag (issue 48).

Every process (the node, the probes) runs in the ROS 2 environment (:mod:`topoloc.ros.environment`: topoloc from
this source tree with its ``ros2`` extra), built once where it is missing or out of date; where it cannot be
built or run, the tests skip with one line naming what is missing.  Each test run takes a ROS domain id no other
run on this machine holds (``PrivateDomain``: a lock per id), and discovery stays on this machine.
"""

from __future__ import annotations

import ast
import os
import shutil
import signal
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from tests.ros.probes import BagFrames, assert_answers_equal_localize
from tests.ros.probes import ok as _ok
from tests.ros.probes import records as _records
from tests.ros.probes import stop as _stop

from topoloc.ros.environment import PrivateDomain
from topoloc.ros.probe import wait_for
from topoloc.spec import NodeSpec

SRC = Path(__file__).resolve().parents[2] / "src"
T0 = 1_700_000_000
TOPICS = {"bgr8": "/cam/bgr8", "mono8": "/cam/mono8", "compressed": "/cam/image/compressed"}
ANSWER_KEYS = ("place", "score", "accepted", "top", "x", "y", "time", "verified", "inliers", "confidence")


@pytest.fixture(scope="module")
def ros2_python() -> Path:
    """The ROS 2 environment's Python ($TOPOLOC_ROS2_PYTHON, else built or found by topoloc.ros.environment)."""
    from topoloc.errors import TopolocError
    from topoloc.ros import environment

    given = os.environ.get("TOPOLOC_ROS2_PYTHON")
    if given:
        return Path(given)
    try:
        return environment.ensure()
    except TopolocError as exc:
        pytest.skip(f"ROS 2 is not installed: {exc}")


class Ros2:
    """The processes of one test on a ROS domain of their own."""

    def __init__(self, python: Path, root: Path, domain: PrivateDomain) -> None:
        self.python, self.root = python, root
        self.env = domain.env(ROS_LOG_DIR=str(root / "ros_log"), TOPOLOC_FEATURES="sift", TOPOLOC_VERIFY="0",
                              PYTHONPATH=str(SRC))
        self.procs: list[subprocess.Popen[str]] = []

    def start(self, args: list[str], name: str) -> subprocess.Popen[str]:
        err = (self.root / f"{name}.err").open("w")
        proc = subprocess.Popen([str(self.python), *args], env=self.env, stdout=err, stderr=subprocess.STDOUT,
                                text=True)
        self.procs.append(proc)
        return proc

    def node(self, map_file: Path | str, ns: str, *extra: str,
             ros_args: tuple[str, ...] = ()) -> subprocess.Popen[str]:
        """The node ``/NS/topoloc`` (its answers on ``/NS/answer``), its output in ``NS.err``."""
        return self.start(["-m", "topoloc.cli.main", "ros2-node", str(map_file), *extra, "--ros-args",
                           "-r", f"__ns:=/{ns}", *ros_args], ns)

    def probe(self, out: Path, *args: str) -> subprocess.Popen[str]:
        """A probe; one that records answers is returned once it hears the node (else it would miss answers)."""
        proc = self.start(["-m", "topoloc.ros.probe2", "--out", str(out), *args], out.stem)
        if "--answers" in args:
            wait_for(f"{out.stem} to hear the node", lambda: bool(_records(out, "ready")) or proc.poll() is not None,
                     timeout=90)
        return proc

    def client(self, node: str, *args: str) -> list[dict[str, Any]]:
        out = self.root / f"client_{len(self.procs)}.jsonl"
        proc = self.probe(out, "--node", node, *args)
        assert proc.wait(timeout=120) == 0, self.err(out.stem)
        return _records(out)

    def err(self, name: str) -> str:
        return (self.root / f"{name}.err").read_text()

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


@pytest.fixture(scope="module")
def ros2(ros2_python: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Ros2]:
    domain = PrivateDomain()
    r = Ros2(ros2_python, tmp_path_factory.mktemp("ros2"), domain)
    try:
        yield r
    finally:
        r.close()
        domain.close()


def _last_diag(path: Path, ns: str) -> dict[str, Any] | None:
    diags = [d for d in _records(path, "diagnostics") if d["name"] == f"/{ns}/topoloc: localizer"]
    return diags[-1] if diags else None


@pytest.fixture(scope="module")
def route(tiny_route: dict[str, Any], tiny_route_map: Path, tmp_path_factory: pytest.TempPathFactory,
          ) -> dict[str, Any]:
    """The tiny route's map, and its dusk tour as a ROS 2 bag with bgr8, mono8 and compressed topics."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    root = tmp_path_factory.mktemp("ros2_route")
    files = sorted(tiny_route["query"].root.glob("*.jpg"))
    ts = get_typestore(Stores.ROS2_HUMBLE)
    frames = BagFrames(ts, ts.serialize_cdr)
    bag = root / "dusk"
    with Writer(bag, version=9) as w:
        frames.write_tour(w, TOPICS, files, T0)
    return {"root": root, "map": tiny_route_map, "bag": bag, "n": len(files), "query": tiny_route["query"]}


def test_answers_equal_localize_on_each_encoding_of_a_ros2_bag(ros2: Ros2, route: dict[str, Any]) -> None:
    """A ROS 2 bag's bgr8, mono8 and compressed topics replayed over DDS: localize's lines, frame for frame."""
    n = route["n"]
    nodes = {k: ros2.node(route["map"], f"topoloc_{k}", "--image-topic", topic, "--queue", "1000")
             for k, topic in TOPICS.items()}
    out = route["root"] / "answers.jsonl"
    recorder = ros2.probe(out, *[a for k in TOPICS for a in ("--answers", f"/topoloc_{k}/answer")],
                          "--positions", "/topoloc_bgr8/position")
    player = ros2.probe(route["root"] / "player.jsonl", "--bag", str(route["bag"]), "--rate", "4", "--linger", "0")
    wait_for("every answer", lambda: all(sum(r["topic"] == f"/topoloc_{k}/answer" for r in _records(out, "answer"))
                                          >= n for k in TOPICS) or any(p.poll() is not None for p in nodes.values()),
             timeout=180)
    for k in TOPICS:
        assert nodes[k].poll() is None, ros2.err(f"topoloc_{k}")
    assert player.wait(timeout=60) == 0, ros2.err("player")

    def counted(k: str) -> bool:
        last = _last_diag(out, f"topoloc_{k}")
        return last is not None and int(last["values"]["frames_out"]) == n

    wait_for("diagnostics of every frame", lambda: all(counted(k) for k in TOPICS), timeout=30)
    for k in TOPICS:
        assert _stop(nodes[k]) == 0, ros2.err(f"topoloc_{k}")
        err = ros2.err(f"topoloc_{k}")
        assert "Traceback" not in err
        assert f"stopped (SIGTERM): {n} frames in, {n} answered, 0 skipped, 0 unreadable" in err, err
    _stop(recorder)
    answers = _records(out, "answer")
    assert_answers_equal_localize(answers, route, TOPICS, n, ANSWER_KEYS,
                                  lambda stamp: stamp["sec"] + 1e-9 * stamp["nanosec"])
    # A position for each accepted answer (the map is not calibrated: every one), stamped as its image.
    positions = _records(out, "position")
    bgr = [a for a in answers if a["topic"] == "/topoloc_bgr8/answer"]
    assert [p["stamp"] for p in positions] == pytest.approx([a["time"] for a in bgr])
    assert [c for p in positions for c in (p["x"], p["y"])] == pytest.approx([c for a in bgr for c in (a["x"], a["y"])])
    assert {p["frame_id"] for p in positions} == {"map"}
    for k in TOPICS:
        values = _last_diag(out, f"topoloc_{k}")["values"]  # type: ignore[index]
        assert int(values["frames_in"]) == n and int(values["frames_skipped"]) == 0
        assert int(values["frames_bad"]) == 0 and float(values["ms_extract_mean"]) > 0
    assert _last_diag(out, "topoloc_bgr8")["level"] == 1  # type: ignore[index]  # WARN: not calibrated


def test_bad_messages_are_counted_never_answered_never_fatal(ros2: Ros2, route: dict[str, Any]) -> None:
    """Wrong step, short data, unknown encoding, empty image, garbage compressed bytes: counted, said, not answered."""
    nodes = {kind: ros2.node(route["map"], f"topoloc_bad_{kind}", "--image-topic", topic, "--queue", "100")
             for kind, topic in (("image", "/bad/image"), ("compressed", "/bad/image/compressed"))}
    out = route["root"] / "bad.jsonl"
    recorder = ros2.probe(out, "--answers", "/topoloc_bad_image/answer", "--answers", "/topoloc_bad_compressed/answer")
    players = [ros2.probe(route["root"] / f"bad_{kind}.jsonl", "--bad", kind, "--topic", topic, "--rate", "5",
                          "--linger", "0")
               for kind, topic in (("image", "/bad/image"), ("compressed", "/bad/image/compressed"))]
    expect = {"image": (4, "bad_4"), "compressed": (2, "bad_2")}

    def done(kind: str) -> bool:
        last = _last_diag(out, f"topoloc_bad_{kind}")
        # The answer too: it travels apart from the diagnostics that count it, and may arrive after them.
        return last is not None and int(last["values"]["frames_in"]) == expect[kind][0] + 1 and \
            int(last["values"]["frames_out"]) == 1 and \
            any(a["topic"] == f"/topoloc_bad_{kind}/answer" for a in _records(out, "answer"))

    wait_for("the bad messages counted", lambda: all(done(k) for k in expect), timeout=90)
    for p in players:
        assert p.wait(timeout=30) == 0
    for kind, (n_bad, good) in expect.items():
        last = _last_diag(out, f"topoloc_bad_{kind}")
        assert last is not None and int(last["values"]["frames_bad"]) == n_bad
        assert last["level"] >= 1 and last["values"]["last_bad"]  # reported: WARN at least, and the last one said
        answers = [a for a in _records(out, "answer") if a["topic"] == f"/topoloc_bad_{kind}/answer"]
        assert [a["frame_id"] for a in answers] == [good]  # only the good frame answered
        assert nodes[kind].poll() is None  # never fatal
        assert _stop(nodes[kind]) == 0
        err = ros2.err(f"topoloc_bad_{kind}")
        assert "Traceback" not in err and f"{n_bad} unreadable" in err and "frame skipped (1 so far)" in err
    err = ros2.err("topoloc_bad_image")
    assert "step 10" in err  # the first one said: the wrong step
    _stop(recorder)


def test_a_flood_leaves_no_backlog(ros2: Ros2, route: dict[str, Any]) -> None:
    """400 frames at 400 Hz: skipped frames counted, answers current, latency bounded, the last frames answered."""
    node = ros2.node(route["map"], "topoloc_flood", "--image-topic", "/cam/flood")
    out = route["root"] / "flood.jsonl"
    recorder = ros2.probe(out, "--answers", "/topoloc_flood/answer")
    player = ros2.probe(route["root"] / "flood_player.jsonl", "--publish", str(route["query"].root), "--topic",
                        "/cam/flood", "--encoding", "mono8", "--rate", "400", "--count", "400", "--linger", "0")
    assert player.wait(timeout=120) == 0
    def quiet() -> bool:
        # Nothing waiting, and every answer the node counted received: a frame being matched when the diagnostics
        # said "0 waiting" is answered after them, and stopping the node then could lose that answer on the way.
        values = (_last_diag(out, "topoloc_flood") or {"values": {}})["values"]
        return values.get("frames_waiting") == "0" and int(values.get("frames_out", -1)) == len(_records(out, "answer"))

    wait_for("the node to go quiet", quiet, timeout=30)
    assert _stop(node) == 0
    _stop(recorder)
    line = next(x for x in ros2.err("topoloc_flood").splitlines() if "stopped (SIGTERM)" in x)
    n_in, n_out, n_skipped, n_bad, n_lost = (int(w.split()[0]) for w in line.split(": ")[-1].split(", "))
    answers = _records(out, "answer")
    assert n_bad == 0 and n_out == len(answers) and n_out + n_skipped == n_in
    # Frames DDS dropped before the node took them (the sensor-data QoS keeps the 5 newest) are counted too.
    assert n_in + n_lost == 400, (n_in, n_lost)
    assert int(_last_diag(out, "topoloc_flood")["values"]["frames_lost"]) == n_lost  # type: ignore[index]
    assert n_skipped + n_lost > 0, "at 400 Hz some frames must be skipped"
    frames = [int(a["frame_id"].rsplit("_", 1)[1]) for a in answers]
    assert frames == sorted(frames) and len(set(frames)) == len(frames)
    assert frames[-1] >= 380, f"the last answer is about frame {frames[-1]} of 400"
    worst = max(a["publish_to_answer_ms"] for a in answers)
    assert worst < 3000, f"latency {worst:.0f} ms with {n_skipped} frames skipped"


def test_parameters_reload_remapping_and_a_late_subscriber(ros2: Ros2, route: dict[str, Any]) -> None:
    """Parameters set at run time or refused with a reason; reloads; names under the namespace; late answers."""
    map_file = route["root"] / "reloaded.tlm"
    shutil.copy(route["map"], map_file)
    # The option wins over --ros-args -p; the names are remapped and under the namespace /robot.
    node = ros2.node(map_file, "robot", "--queue", "2", ros_args=("-r", "__node:=loc", "-r", "image:=/cam/param",
                                                                  "-p", "queue:=5", "-p", "top_k:=3"))
    full = "/robot/loc"
    got = {r["name"]: r["value"] for r in ros2.client(full, *[a for p in NodeSpec.PARAMS for a in ("--get", p)])}
    assert set(got) == set(NodeSpec.PARAMS)
    assert got["queue"] == 2 and got["top_k"] == 3 and got["map"] == str(map_file) and got["image_topic"] == "image"
    assert got["verify"] is None and got["sequence"] is None  # not set: as localize decides
    out = route["root"] / "param.jsonl"
    recorder = ros2.probe(out, "--answers", "/robot/answer")
    sets = ros2.client(full, "--set", "queue=0", "--set", "device=cuda", "--set", f"map={route['root'] / 'none.tlm'}",
                       "--set", "rate=many", "--set", "top_k=2", "--set", "rate=20")
    by = {(s["name"], str(s["value"])): s for s in sets}
    assert not by[("queue", "0")]["successful"] and "queue must be a whole number >= 1" in by[("queue", "0")]["reason"]
    assert not by[("device", "cuda")]["successful"] and "restart" in by[("device", "cuda")]["reason"]
    refused_map = by[("map", str(route["root"] / "none.tlm"))]
    assert not refused_map["successful"] and "none.tlm" in refused_map["reason"]
    assert not by[("rate", "many")]["successful"] and "rate" in by[("rate", "many")]["reason"]
    assert by[("top_k", "2")]["successful"] and by[("rate", "20")]["successful"]
    player = ros2.probe(route["root"] / "param_player.jsonl", "--publish", str(route["query"].root), "--topic",
                        "/cam/param", "--encoding", "mono8", "--rate", "4", "--linger", "0")
    assert player.wait(timeout=60) == 0
    wait_for("answers on /robot/answer", lambda: len(_records(out, "answer")) >= 5, timeout=60)
    assert all(len(a["top"]) == 2 for a in _records(out, "answer"))  # top_k changed while it ran
    # A late subscriber (transient local) gets the latest answers at once, before any new frame.
    late = route["root"] / "late.jsonl"
    late_probe = ros2.probe(late, "--answers", "/robot/answer", "--late")
    wait_for("the late subscriber's answers", lambda: len(_records(late, "answer")) >= 5, timeout=30)
    assert [a["frame"] for a in _records(late, "answer")] == [a["frame"] for a in _records(out, "answer")][-10:]
    _stop(late_probe)
    # map calibrate rewrites the file: reloaded; the reload service; SIGHUP; a broken file is refused, once.
    _ok(["map", "calibrate", str(map_file), "--query", str(route["query"].root), "--sequence", "0", "-q"])
    wait_for("the reload", lambda: "map reloaded" in ros2.err("robot"), timeout=30)
    assert ros2.client(full, "--reload")[0]["success"]
    wait_for("the second reload", lambda: ros2.err("robot").count("map reloaded") == 2, timeout=30)
    node.send_signal(signal.SIGHUP)
    wait_for("the third reload", lambda: ros2.err("robot").count("map reloaded") == 3, timeout=30)
    broken = route["root"] / "broken.tmp"
    broken.write_bytes(b"not a map")
    os.replace(broken, map_file)
    wait_for("the refusal", lambda: "map not reloaded, keeping the one loaded" in ros2.err("robot"), timeout=30)
    refused = ros2.client(full, "--reload")[0]
    assert not refused["success"] and "map not reloaded" in refused["message"]
    assert node.poll() is None
    assert _stop(node, signal.SIGINT) == 0
    _stop(recorder)
    err = ros2.err("robot")
    assert "Traceback" not in err and "stopped (SIGINT)" in err
    assert err.count("map not reloaded, keeping the one loaded") == 2  # the file once, the service call once


def test_bad_settings_are_one_line(ros2: Ros2, route: dict[str, Any], tmp_path: Path) -> None:
    cases = [([str(route["map"]), "--queue", "0"], "queue must be a whole number >= 1"),
             ([str(route["map"]), "--ros-args", "-p", "queue:=many"], "queue must be a whole number"),
             ([str(tmp_path / "none.tlm")], "none.tlm"),
             (["--ros-args", "-r", "image:=/cam"], "map is needed"),
             ([str(route["map"]), "--ros-args", "-p", "rate:=-1.0"], "rate must be a finite number")]
    for args, needle in cases:
        r = subprocess.run([str(ros2.python), "-m", "topoloc.cli.main", "ros2-node", *args], env=ros2.env,
                           capture_output=True, text=True, timeout=120)
        lines = [x for x in r.stderr.strip().splitlines() if x]
        assert r.returncode == 2 and len(lines) == 1 and needle in lines[0], r.stderr


def test_ros2_run_finds_the_shipped_executable_and_the_launch_file_names_real_parameters(
        ros2: Ros2, route: dict[str, Any]) -> None:
    """docs/ros.md's `ros2 run topoloc_ros topoloc_node`: the ament index resolves it as ros2run does; it runs."""
    import topoloc.ros

    prefix = Path(topoloc.ros.__file__).parent / "ament"
    env = {**ros2.env, "AMENT_PREFIX_PATH": str(prefix)}
    code = ("from ament_index_python.packages import get_package_prefix, get_package_share_directory\n"
            "import os\np = get_package_prefix('topoloc_ros')\n"
            "print(os.path.join(p, 'lib', 'topoloc_ros', 'topoloc_node'))\n"
            "print(get_package_share_directory('topoloc_ros'))\n")
    r = subprocess.run([str(ros2.python), "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    exe, share = r.stdout.split()
    assert os.access(exe, os.X_OK)
    # The launch file: a ROS 2 Python launch file whose parameters are the node's (launch itself is not on PyPI).
    launch = Path(share) / "launch" / "localize.launch.py"
    tree = ast.parse(launch.read_text())
    strings = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
    assert {"topoloc_ros", "topoloc_node"} <= strings
    params = {n.value for d in ast.walk(tree) if isinstance(d, ast.Dict) for n in d.keys
              if isinstance(n, ast.Constant)}
    assert params and params <= set(NodeSpec.PARAMS), params - set(NodeSpec.PARAMS)
    # ros2 run executes that file with the node's arguments: it answers.
    err = (ros2.root / "ros2run.err").open("w")
    proc = subprocess.Popen([exe, "--ros-args", "-p", f"map:={route['map']}", "-r", "image:=/cam/run",
                             "-r", "__node:=topoloc_run"], env={**env, "TOPOLOC_PYTHON": str(ros2.python)},
                            stdout=err, stderr=subprocess.STDOUT, text=True)
    ros2.procs.append(proc)
    out = ros2.root / "run.jsonl"
    recorder = ros2.probe(out, "--answers", "/answer", "--late")  # answers made before it matched too
    player = ros2.probe(ros2.root / "run_player.jsonl", "--publish", str(route["query"].root), "--topic", "/cam/run",
                        "--encoding", "jpeg", "--rate", "4", "--count", "3", "--linger", "0")
    assert player.wait(timeout=60) == 0
    wait_for("answers of the node ros2 run started", lambda: len(_records(out, "answer")) >= 1, timeout=60)
    assert _stop(proc) == 0
    _stop(recorder)
    assert "stopped (SIGTERM)" in (ros2.root / "ros2run.err").read_text()
