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
