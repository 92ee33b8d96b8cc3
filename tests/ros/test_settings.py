"""The nodes' one specification, their shared core and their imports of ROS, without a running ROS (issues 37, 48)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from topoloc.errors import TopolocError
from topoloc.ros.core import COMPRESSED, IMAGE, Messages, NodeCore, frame_of, replace_spec
from topoloc.ros.node import spec_from
from topoloc.spec import NodeSpec, SequenceSpec

SRC = Path(__file__).resolve().parents[2] / "src"


def test_an_option_given_wins_over_the_parameter_which_wins_over_the_config_file() -> None:
    s = spec_from({"map": Path("a.tlm"), "queue": None, "rate": 5.0},
                  {"map": "b.tlm", "queue": 3, "rate": 1, "image_topic": "/cam/image_raw"},
                  {"queue": 7, "top_k": 2, "map_frame": "odom"})
    assert s == NodeSpec(map_file=Path("a.tlm"), image_topic="/cam/image_raw", queue=3, rate=5.0, top_k=2,
                         map_frame="odom")
    s = spec_from({}, {"map": "b.tlm", "sequence": -1, "watch_map": "false", "prefetch": "2"})
    assert s.map_file == Path("b.tlm") and s.sequence is None and s.watch_map is False and s.prefetch == 2
    s = spec_from({"sequence": 4}, {"map": "m.tlm", "sequence_mode": "acceleration", "min_support": "30"})
    assert s.sequence == SequenceSpec(length=4, mode="acceleration") and s.verification.min_support == 30
    assert spec_from({}, {"map": "m.tlm", "sequence_mode": "acceleration"}).sequence is None  # a mode alone


def test_the_parameters_are_the_specifications_flat_names_and_round_trip() -> None:
    spec = NodeSpec.from_params({"map": "m.tlm", "queue": 2, "sequence": 3, "verify": True, "confirm": True,
                                 "device": "CPU", "rate": 2})
    values = spec.param_values()
    assert set(values) == set(NodeSpec.PARAMS) == set(NodeSpec.defaults())
    assert NodeSpec.from_params(values) == spec and spec.device == "cpu" and spec.rate == 2.0
    # A configuration file is the nested form every specification has.
    assert NodeSpec.params_of({"image_topic": "/x", "sequence": {"length": 3}, "verification": {"enabled": True}}) \
        == {"image_topic": "/x", "sequence": 3, "verify": True}
    with pytest.raises(TopolocError, match=r"unknown setting verification\.colour"):
        NodeSpec.params_of({"verification": {"colour": 1}}, source="node.toml")
    with pytest.raises(TopolocError, match="unknown node parameter 'colour'"):
        NodeSpec.from_params({"map": "m.tlm", "colour": 1})
    assert replace_spec(spec, {"top_k": 2}).top_k == 2
    with pytest.raises(TopolocError, match=r"^queue must be a whole number >= 1, got 0$"):
        replace_spec(spec, {"queue": 0})


@pytest.mark.parametrize(("given", "params", "needle"), [
    ({}, {}, "map is needed"),
    ({"map": Path("m.tlm"), "queue": 0}, {}, "queue must be a whole number >= 1"),
    ({"map": Path("m.tlm")}, {"rate": -1.0}, "rate must be a finite number"),
    ({"map": Path("m.tlm")}, {"rate": "nan"}, "rate must be a finite number"),
    ({"map": Path("m.tlm")}, {"queue": "many"}, "queue must be a whole number, got 'many'"),
    ({"map": Path("m.tlm")}, {"queue": 1.5}, "queue must be a whole number"),
    ({"map": Path("m.tlm")}, {"watch_map": "perhaps"}, "watch_map must be true or false"),
    ({"map": Path("m.tlm")}, {"top_k": [1]}, "top_k must be a whole number"),
    ({"map": Path("m.tlm")}, {"device": "tpu"}, "device must be one of cpu, cuda, auto"),
    ({"map": Path("m.tlm")}, {"image_topic": ""}, "image_topic must be a non-empty name"),
    ({"map": Path("m.tlm")}, {"verify": "maybe"}, "verify must be true or false"),
])
def test_bad_settings_are_one_line_naming_the_parameter(given: dict[str, object], params: dict[str, object],
                                                         needle: str) -> None:
    with pytest.raises(TopolocError, match=needle):
        spec_from(given, params)


def test_without_rospy_the_error_names_the_packages_to_install(tmp_path: Path) -> None:
    code = ("import topoloc.ros as r\nr.SYSTEM_DIST_PACKAGES = 'NOWHERE'\n"
            "try:\n    r.import_rospy()\n    print('imported')\nexcept r.TopolocError as e:\n    print(e)\n")
    env = {**os.environ, "PYTHONPATH": str(SRC), "TOPOLOC_ROS_PYTHONPATH": str(tmp_path)}
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    if r.stdout.strip() == "imported":
        pytest.skip("rospy is installed in this environment itself")
    assert "apt-get install ros-base python3-rospy" in r.stdout, r.stdout + r.stderr


def test_without_rclpy_ros2_node_is_one_line_naming_the_extra(tiny_route_map: Path) -> None:
    """The suite's environment has no rclpy (it lives in an environment of its own): one line, exit 2."""
    r = subprocess.run([sys.executable, "-m", "topoloc.cli.main", "ros2-node", str(tiny_route_map)],
                       env={**os.environ, "PYTHONPATH": str(SRC)}, capture_output=True, text=True, timeout=120)
    if r.returncode != 2 and "rclpy" not in r.stderr:
        pytest.skip("rclpy is installed in this environment itself")
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert "pip install 'topoloc[ros2]'" in lines[0] and "rclpy is missing" in lines[0]


# -- the core, with message classes of its own (the fields rospy's and rclpy's have) -----------------------------
class _Obj(SimpleNamespace):
    def __init__(self, **kw: Any) -> None:
        super().__init__(**kw)


def _header(sec: int, nsec: int, frame: str = "camera") -> _Obj:
    return _Obj(stamp=_Obj(sec=sec, nanosec=nsec), frame_id=frame)


class _Status(_Obj):
    OK, WARN, ERROR = 0, 1, 2


def _point() -> _Obj:
    return _Obj(header=_Obj(stamp=None, frame_id=""), point=_Obj(x=0.0, y=0.0, z=0.0))


def _array(status: list[Any]) -> _Obj:
    return _Obj(status=status, header=_Obj(stamp=None))


MESSAGES = Messages(string=_Obj, point_stamped=_point, diagnostic_array=_array, diagnostic_status=_Status,
                    key_value=_Obj, stamp_fields=("sec", "nanosec"))


def _image(img: np.ndarray, encoding: str = "mono8", **kw: Any) -> _Obj:
    fields = {"height": img.shape[0], "width": img.shape[1], "encoding": encoding, "is_bigendian": 0,
              "step": img.strides[0] if img.ndim else 0, "data": img.tobytes(), **kw}
    return _Obj(header=_header(1_700_000_000, 500_000_000), **fields)


def test_every_kind_of_bad_message_is_one_line_never_a_crash() -> None:
    good = np.tile(np.arange(64, dtype=np.uint8), (48, 1))
    assert np.array_equal(frame_of(_image(good), IMAGE, where="topic /c message 0"), good)
    cases = {
        "step 10": _image(good, step=10),
        "do not hold a 64x48 mono8 image": _image(good, data=good.tobytes()[:100]),
        "encoding '32FC7' is not supported": _image(good, encoding="32FC7"),
        "do not hold a 0x0": _image(np.zeros((0, 0), np.uint8)),
    }
    for needle, msg in cases.items():
        with pytest.raises(TopolocError, match=needle) as exc:
            frame_of(msg, IMAGE, where="topic /c message 3")
        assert str(exc.value).startswith("topic /c message 3") and "\n" not in str(exc.value)
    for data in (b"\xff\xd8 not a jpeg", b""):
        with pytest.raises(TopolocError, match="topic /c message 4"):
            frame_of(_Obj(format="jpeg", data=data, header=_header(1, 0)), COMPRESSED, where="topic /c message 4")
    with pytest.raises(TopolocError, match="is a sensor_msgs/PointCloud2, not"):
        frame_of(_image(good), "sensor_msgs/msg/PointCloud2", where="topic /c message 5")
    with pytest.raises(TopolocError, match="cannot be read"):
        frame_of(_Obj(encoding="mono8"), IMAGE, where="topic /c message 6")  # fields missing


def test_the_core_answers_counts_and_reloads_as_both_nodes_do(tiny_route: dict[str, Any], tiny_route_map: Path,
                                                              tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                              ) -> None:
    """Frames in (bad ones counted, never answered), localize's lines out with the header, a reload kept or refused."""
    from topoloc.maps import Map

    map_file = tmp_path / "m.tlm"
    shutil.copy(tiny_route_map, map_file)
    core = NodeCore(NodeSpec(map_file=map_file, queue=100, top_k=3), MESSAGES, name="/ns/topoloc",
                    program="topoloc ros2-node")
    frames = tiny_route["query_frames"][:3]
    core.warm_up()  # a frame's first-use costs paid before subscribing: nothing of the localiser's state changes
    assert core.localizer.frames == 0 and core.localizer.ms_features == 0
    core.put(_image(np.ascontiguousarray(frames[0][..., 0])), IMAGE)
    core.put(_image(frames[0][..., 0].copy(), encoding="32FC7"), IMAGE)  # counted, not answered
    for f in frames[1:]:
        core.put(_image(np.ascontiguousarray(f), encoding="bgr8"), IMAGE)
    published: list[tuple[Any, Any]] = []

    def publish(answer: Any, position: Any) -> None:
        published.append((answer, position))
        if len(published) == 3:
            core.stop("done")

    assert core.run(publish) == 0
    answers = [json.loads(a.data) for a, _ in published]
    expected = Map.load(map_file).localize_many([frames[0][..., 0], *frames[1:]], top_k=3, sequence=0)
    for a, e in zip(answers, expected, strict=True):
        assert {k: a[k] for k in ("place", "score", "top", "accepted")} == {k: e[k] for k in ("place", "score", "top",
                                                                                            "accepted")}
        assert a["stamp"] == {"sec": 1_700_000_000, "nanosec": 500_000_000} and a["frame_id"] == "camera"
        assert a["time"] == pytest.approx(1_700_000_000.5) and a["latency_ms"] >= 0
    point = published[0][1]
    assert point.header.frame_id == "map" and (point.point.x, point.point.y) == (answers[0]["x"], answers[0]["y"])
    assert "frame skipped (1 so far): topic image message 1: image encoding '32FC7'" in capsys.readouterr().err
    diag = core.diagnostics(stamp="now").status[0]
    values = {kv.key: kv.value for kv in diag.values}
    assert values["frames_in"] == "4" and values["frames_out"] == "3" and values["frames_bad"] == "1"
    assert diag.level == _Status.WARN and diag.name == "/ns/topoloc: localizer"
    assert "stopped (done): 4 frames in, 3 answered, 0 skipped, 1 unreadable" in core.last_line()
    # A change is built before it is taken: a map that does not load is refused, the one loaded stays.
    with pytest.raises(TopolocError, match=r"none\.tlm"):
        core.change(replace_spec(core.spec, {"map": str(tmp_path / "none.tlm")}))
    with pytest.raises(TopolocError, match="device cannot change while the node runs"):
        core.change(replace_spec(core.spec, {"device": "cuda"}))
    map_file.write_bytes(b"not a map")
    with pytest.raises(TopolocError):
        core.reload_now()
    assert "map not reloaded, keeping the one loaded" in capsys.readouterr().err
    assert core.map is not None and core.counts.reloads == 0


def test_verification_is_a_setting_and_a_map_that_cannot_verify_is_not_taken_on_reload(
        tiny_route: dict[str, object], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``verify`` as an option or a parameter; a reload whose localiser cannot be built keeps the map it has."""
    from topoloc.datasets.traverse import load_traverse
    from topoloc.maps import Map

    assert spec_from({"map": Path("m.tlm")}, {"verify": "false"}).verification.enabled is False
    assert spec_from({"map": Path("m.tlm"), "verify": True}, {"verify": False}).verification.enabled is True
    assert spec_from({"map": Path("m.tlm")}, {}).verification.enabled is None
    tour = tmp_path / "tour"
    shutil.copytree(tiny_route["map"].root, tour)  # type: ignore[attr-defined]
    tlm = tmp_path / "m.tlm"
    Map.build(method="bow", tours=[load_traverse(tour)], vocabulary=tiny_route["vocabulary"],  # type: ignore[arg-type]
              cache_dir=tmp_path / "cache").save(tlm)
    verified = spec_from({"map": tlm, "verify": True}, {})
    core = NodeCore(verified, MESSAGES, name="/topoloc", program="topoloc ros-node")
    assert core.localizer.verifier is not None
    first = core.map
    shutil.rmtree(tour)  # the map can no longer verify, as it was asked to
    time.sleep(0.01)
    Map.load(tlm).save(tlm)  # rewritten: a reload is due
    core.check_map_file()
    core._take_changes()
    assert core.map is first and core.localizer.verifier is not None and core.counts.reloads == 0
    err = capsys.readouterr().err
    assert "map not reloaded, keeping the one loaded" in err and "cannot verify answers" in err
    # Started against such a map, the node refuses in one line; with verify false it runs unverified.
    with pytest.raises(TopolocError, match="cannot verify answers"):
        NodeCore(verified, MESSAGES, name="/topoloc", program="topoloc ros-node")
    unverified = spec_from({"map": tlm, "verify": False}, {})
    assert NodeCore(unverified, MESSAGES, name="/x", program="p").localizer.verifier is None


def test_ros2_arguments_are_passed_whole_however_the_command_line_splits_them() -> None:
    from topoloc.cli.ros import _ros2_arguments

    args = ["--ros-args", "-r", "image:=/cam"]
    assert _ros2_arguments("m.tlm", list(args)) == ("m.tlm", args)
    # No MAP: the command line took a ROS 2 argument's value for it.
    assert _ros2_arguments("image:=/cam", ["--ros-args", "-r"]) == (None, ["--ros-args", "-r", "image:=/cam"])
    assert _ros2_arguments("x:=1", ["--ros-args", "-r", "image:=/cam", "-p"]) == (
        None, ["--ros-args", "-r", "image:=/cam", "-p", "x:=1"])
    with pytest.raises(TopolocError, match="ROS 2's arguments follow --ros-args"):
        _ros2_arguments("m.tlm", ["image:=/cam"])


def test_a_config_file_gives_the_nodes_settings_nested_as_every_specification(tmp_path: Path) -> None:
    from topoloc.ros.node import _config_params

    cfg = tmp_path / "node.toml"
    cfg.write_text('image_topic = "/camera/image_raw"\nqueue = 3\n[sequence]\nlength = 4\n[verification]\n'
                   'enabled = false\n')
    spec = spec_from({"queue": 2}, {"map": "m.tlm"}, _config_params(cfg))
    assert spec.image_topic == "/camera/image_raw" and spec.queue == 2  # the option wins over the file
    assert spec.sequence == SequenceSpec(length=4) and spec.verification.enabled is False
    cfg.write_text('[verification]\ncolour = "red"\n')
    with pytest.raises(TopolocError, match=r"unknown setting verification\.colour"):
        _config_params(cfg)
    cfg.write_text('queue = "many"\n')
    with pytest.raises(TopolocError, match="queue must be a whole number"):
        _config_params(cfg)
