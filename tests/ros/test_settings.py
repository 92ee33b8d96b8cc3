"""The node's settings and its import of rospy, without a running ROS (issue 37)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from topoloc.errors import TopolocError
from topoloc.ros.node import NodeSettings, settings_from

SRC = Path(__file__).resolve().parents[2] / "src"


def test_an_option_given_wins_over_the_parameter_and_the_parameter_over_the_default() -> None:
    s = settings_from({"map": Path("a.tlm"), "queue": None, "rate": 5.0},
                      {"map": "b.tlm", "queue": 3, "rate": 1, "image_topic": "/cam/image_raw"})
    assert s == NodeSettings(map_file=Path("a.tlm"), image_topic="/cam/image_raw", queue=3, rate=5.0)
    s = settings_from({}, {"map": "b.tlm", "sequence": -1, "watch_map": "false", "prefetch": 2})
    assert s.map_file == Path("b.tlm") and s.sequence is None and s.watch_map is False and s.prefetch == 2


@pytest.mark.parametrize(("given", "params", "needle"), [
    ({}, {}, "the node needs a map"),
    ({"map": Path("m.tlm"), "queue": 0}, {}, "queue must be >= 1"),
    ({"map": Path("m.tlm")}, {"rate": -1.0}, "rate must be a finite number"),
    ({"map": Path("m.tlm")}, {"queue": "many"}, "queue must be int, got 'many'"),
    ({"map": Path("m.tlm")}, {"queue": 1.5}, "queue must be int"),
    ({"map": Path("m.tlm")}, {"watch_map": "perhaps"}, "watch_map must be bool"),
    ({"map": Path("m.tlm")}, {"top_k": [1]}, "top_k must be int"),
])
def test_bad_settings_are_one_line(given: dict[str, object], params: dict[str, object], needle: str) -> None:
    with pytest.raises(TopolocError, match=needle):
        settings_from(given, params)


def test_without_rospy_the_error_names_the_packages_to_install(tmp_path: Path) -> None:
    code = ("import topoloc.ros as r\nr.SYSTEM_DIST_PACKAGES = 'NOWHERE'\n"
            "try:\n    r.import_rospy()\n    print('imported')\nexcept r.TopolocError as e:\n    print(e)\n")
    env = {**os.environ, "PYTHONPATH": str(SRC), "TOPOLOC_ROS_PYTHONPATH": str(tmp_path)}
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    if r.stdout.strip() == "imported":
        pytest.skip("rospy is installed in this environment itself")
    assert "apt-get install ros-base python3-rospy" in r.stdout, r.stdout + r.stderr


def test_verification_is_a_setting_and_a_map_that_cannot_verify_is_not_taken_on_reload(
        tiny_route: dict[str, object], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``verify`` as an option or ``~verify``; a reload whose localiser cannot be built keeps the map it has."""
    import shutil

    from topoloc.datasets.traverse import load_traverse
    from topoloc.maps import Map
    from topoloc.ros.node import LocalizerNode

    assert settings_from({"map": Path("m.tlm")}, {"verify": "false"}).verify is False
    assert settings_from({"map": Path("m.tlm"), "verify": True}, {"verify": False}).verify is True
    assert settings_from({"map": Path("m.tlm")}, {}).verify is None
    with pytest.raises(TopolocError, match="verify must be bool"):
        settings_from({"map": Path("m.tlm")}, {"verify": "maybe"})
    tour = tmp_path / "tour"
    shutil.copytree(tiny_route["map"].root, tour)  # type: ignore[attr-defined]
    tlm = tmp_path / "m.tlm"
    Map.build(method="bow", tours=[load_traverse(tour)], vocabulary=tiny_route["vocabulary"],  # type: ignore[arg-type]
              cache_dir=tmp_path / "cache").save(tlm)
    node = LocalizerNode(NodeSettings(map_file=tlm, verify=True), rospy=None, name="/topoloc")
    assert node._localizer.verifier is not None
    first = node.map
    shutil.rmtree(tour)  # the map can no longer verify, as it was asked to
    Map.load(tlm).save(tlm)  # rewritten: a reload is due
    node._reload_map()
    assert node.map is first and node._localizer.verifier is not None and node.counts.reloads == 0
    err = capsys.readouterr().err
    assert "map not reloaded, keeping the one loaded" in err and "cannot verify answers" in err
    # Started against such a map, the node refuses in one line; with verify false it runs unverified.
    with pytest.raises(TopolocError, match="cannot verify answers"):
        LocalizerNode(NodeSettings(map_file=tlm, verify=True), rospy=None, name="/topoloc")
    assert LocalizerNode(NodeSettings(map_file=tlm, verify=False), rospy=None, name="/x")._localizer.verifier is None
