"""``slam`` reads recordings as ``localize`` does, and ``map info`` names a recording tour (issue 27).

The recordings are written in the test from the files of a folder: a lossless video (PNG codec, the
files' decoded colour pixels) and a ROS 2 bag whose compressed topic carries the files' bytes, so
each frame has the folder's pixels and the runs must agree with the folder's run exactly.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from topoloc.cli.main import app
from topoloc.datasets.decode import read_image

CAM = "/camera/image_raw/compressed"


def _ok(args: list[str]) -> str:
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output + (r.stderr or "") + repr(r.exception)
    return r.stdout


def _video(path: Path, files: list[Path]) -> Path:
    first = read_image(files[0], gray=False)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"png "), 5.0, (first.shape[1], first.shape[0]))
    if not writer.isOpened():
        pytest.skip("this OpenCV cannot write PNG-coded video")
    for f in files:
        writer.write(read_image(f, gray=False))
    writer.release()
    return path


def _closures(out: Path) -> list[tuple[int, int, str]]:
    with (out / "loop_closures.csv").open(newline="") as fh:
        return [(int(r["image"]), int(r["matched_image"]), r["probability"]) for r in csv.DictReader(fh)]


@pytest.fixture(scope="module")
def loop(tiny_route: dict[str, Any], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The noon tour driven twice (a folder), the same frames as a video, and one slam run on the folder."""
    root = tmp_path_factory.mktemp("slam_loop")
    folder = root / "loop"
    folder.mkdir()
    files = sorted(tiny_route["map"].root.glob("*.jpg")) * 2
    for k, p in enumerate(files):
        shutil.copy(p, folder / f"{k:03d}.jpg")
    common = ["--vocab-train", str(tiny_route["training"].root), "--vocab-words", "300", "--min-gap", "3",
              "--cache-dir", str(root / "cache"), "--quiet"]
    _ok(["slam", str(folder), "--out", str(root / "folder_out"), *common])
    return {"root": root, "folder": folder, "files": sorted(folder.glob("*.jpg")), "common": common}


def test_slam_on_a_video_equals_slam_on_its_folder(loop: dict[str, Any]) -> None:
    root, common = loop["root"], loop["common"]
    video = _video(root / "loop.avi", loop["files"])
    _ok(["slam", str(video), "--out", str(root / "video_out"), *common])
    np.testing.assert_array_equal(np.load(root / "video_out" / "posterior.npy"),
                                  np.load(root / "folder_out" / "posterior.npy"))
    assert _closures(root / "video_out") == _closures(root / "folder_out")
    assert _closures(root / "folder_out"), "the second pass revisits the first: some loop must close"
    params = json.loads((root / "video_out" / "slam.json").read_text())["params"]
    assert params["traverse"] == str(video.resolve())  # the recording, not a placeholder
    # Frame selection as for localize: one frame every 0.35 s of a 5 fps video is every second frame.
    _ok(["slam", str(video), "--every-s", "0.35", "--out", str(root / "half_out"), *common])
    assert np.load(root / "half_out" / "posterior.npy").shape[0] == (len(loop["files"]) + 1) // 2


@pytest.mark.usefixtures("rosbags_installed")
def test_slam_on_a_bag_equals_slam_on_its_folder(loop: dict[str, Any], recordings: dict[str, Any]) -> None:
    root, common = loop["root"], loop["common"]
    t0 = recordings["T0"]
    bag = recordings["write_bag"](root / "loop_sqlite3", "sqlite3",
                                  [(CAM, "compressed", t0 + k, (f.read_bytes(),)) for k, f in enumerate(loop["files"])])
    _ok(["slam", str(bag), "--topic", CAM, "--out", str(root / "bag_out"), *common])
    np.testing.assert_array_equal(np.load(root / "bag_out" / "posterior.npy"),
                                  np.load(root / "folder_out" / "posterior.npy"))
    assert _closures(root / "bag_out") == _closures(root / "folder_out")


def test_slam_refuses_recording_options_for_a_folder(loop: dict[str, Any]) -> None:
    r = CliRunner().invoke(app, ["slam", str(loop["folder"]), "--every-s", "1", "--out", str(loop["root"] / "x"),
                                 *loop["common"]])
    assert r.exit_code == 2 and "every" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_slam_max_side_defaults_to_auto() -> None:
    import inspect

    from topoloc.cli.main import slam

    assert inspect.signature(slam).parameters["max_side"].default == "auto"


@pytest.mark.usefixtures("rosbags_installed")
def test_map_info_names_a_recording_tour_by_file_and_frame_selection(
    tmp_path: Path, tiny_route: dict[str, Any], recordings: dict[str, Any],
) -> None:
    files = sorted(tiny_route["map"].root.glob("*.jpg"))
    video = _video(tmp_path / "noon.avi", files)
    voc = tmp_path / "vocab.tlv"
    tiny_route["vocabulary"].save(voc)
    tlm = tmp_path / "m.tlm"
    _ok(["map", "build", "--method", "bow", "--map", str(video), "--every-s", "0.35", "--vocab", str(voc),
         "--out", str(tlm), "--cache-dir", str(tmp_path / "cache"), "--quiet"])
    t0 = recordings["T0"]
    bag = recordings["write_bag"](tmp_path / "dusk.bag", "ros1",
                                  [(CAM, "compressed", t0 + k, (f.read_bytes(),))
                                   for k, f in enumerate(sorted(tiny_route["query"].root.glob("*.jpg")))])
    _ok(["map", "add", str(tlm), str(bag), "--topic", CAM, "--cache-dir", str(tmp_path / "cache"), "--quiet"])
    text = _ok(["map", "info", str(tlm)])
    assert f"({video.resolve()}, every 0.35 s)" in text, text
    assert f"({bag.resolve()}, topic {CAM})" in text, text
    assert "in memory" not in text
    tours = json.loads(_ok(["map", "info", str(tlm), "--json"]))["tours"]
    assert tours[0]["root"] == str(video.resolve())
    assert tours[0]["source"] == {"file": str(video.resolve()), "every_s": 0.35}
    assert tours[1]["source"] == {"file": str(bag.resolve()), "topic": CAM}
