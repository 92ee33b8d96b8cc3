"""A bag whose image topic has no messages is refused in one line by localize, as by map build (issue #41)."""

from __future__ import annotations

from pathlib import Path


def test_an_image_topic_without_messages_is_one_line(tmp_path: Path, rosbags_installed: None) -> None:
    from typer.testing import CliRunner

    from topoloc.cli.main import app
    from topoloc.maps import Map
    from topoloc.synth import RouteConfig, generate_route

    bag = tmp_path / "empty.bag"
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    with Writer(bag) as w:
        w.add_connection("/cam/image", "sensor_msgs/msg/Image", typestore=ts)
    route = generate_route(tmp_path / "route", config=RouteConfig(n_places=4, width=96, height=72, seed=1),
                           tours=[("noon", 12.0)])
    tlm = tmp_path / "m.tlm"
    Map.build(method="seqslam-single", tours=[route[0]], cache_dir=tmp_path / "c").save(tlm)
    for args in (["localize", str(tlm), str(bag), "--out", str(tmp_path / "l.jsonl"), "--quiet"],
                 ["map", "build", "--method", "seqslam-single", "--map", str(bag), "--out", str(tmp_path / "b.tlm"),
                  "--quiet"]):
        r = CliRunner().invoke(app, args)
        assert r.exit_code == 2, r.output
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and "image topic /cam/image has no messages" in lines[0] and str(bag) in lines[0]
    assert not (tmp_path / "l.jsonl").exists()
