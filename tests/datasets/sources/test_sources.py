"""Bags (ROS 1; ROS 2 with sqlite3 and MCAP storage) and videos as streams of frames and as traverses.

Every recording is written in the test: bags with ``rosbags`` from a few generated images (Image in
several encodings, CompressedImage, odometry and GPS topics), a video with OpenCV.
"""

from __future__ import annotations

import json
import sys
import tracemalloc
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from topoloc.cli.main import app
from topoloc.datasets.sources import Keyframes, is_stream_input, load_input, open_source, stream_traverse
from topoloc.errors import TopolocError

STORAGES = ["ros1", "sqlite3", "mcap"]
CAM, RAW, ODOM = "/camera/image_raw/compressed", "/camera/image_raw", "/odom"


def _bag_path(tmp: Path, storage: str, stem: str = "rec") -> Path:
    return tmp / (f"{stem}.bag" if storage == "ros1" else f"{stem}_{storage}")


def _cli_error(args: list[str], *needles: str) -> str:
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 2, (r.output, r.exception)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("topoloc: error:"), r.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def _cli_ok(args: list[str]) -> str:
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output + (r.stderr or "") + repr(r.exception)
    return r.stdout


# -- video ----------------------------------------------------------------------------------------
def _write_video(path: Path, frames: list[np.ndarray], fps: float = 10.0) -> Path:
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert writer.isOpened()
    for f in frames:
        writer.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
    writer.release()
    return path


def test_video_frames_times_and_every_s(tmp_path: Path, recordings: dict[str, Any]) -> None:
    frames = recordings["frames_of"](10)
    video = _write_video(tmp_path / "drive.avi", frames)
    assert is_stream_input(video)
    src = open_source(video)
    got = list(src.frames())
    assert len(got) == 10 == len(src)
    assert [f.name for f in got] == [f"drive.avi#{k}" for k in range(10)]
    np.testing.assert_allclose([f.time_s for f in got], np.arange(10) / 10.0, atol=1e-3)
    for f, ref in zip(got, frames, strict=True):
        assert f.image.shape == ref.shape and f.image.dtype == np.uint8
        assert np.abs(f.image.astype(int) - ref).mean() < 8  # MJPG is lossy
    kept = [f.name for f in open_source(video, every_s=0.25).frames()]
    assert kept == ["drive.avi#0", "drive.avi#3", "drive.avi#6", "drive.avi#9"]
    trav = stream_traverse(open_source(video, every_s=0.25))
    assert len(trav) == 4 and trav.kind == "images" and trav.times is None and trav.name == "drive.avi"
    assert load_input(video, every_s=0.25).read(1).shape == frames[0].shape
    assert open_source(video, gray=False).frames().__next__().image.shape == (*frames[0].shape, 3)


def test_bad_video_is_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "clip.mp4"
    bad.write_bytes(b"not a video at all" * 10)
    with pytest.raises(TopolocError, match=r"clip\.mp4") as exc:
        open_source(bad)
    assert "\n" not in str(exc.value)
    with pytest.raises(TopolocError, match="every_m needs positions"):
        open_source(_write_video(tmp_path / "v.avi", [np.zeros((32, 32), np.uint8)] * 2), every_m=1.0)


def _frame_chunks(data: bytes) -> list[int]:
    """Offsets of the frame chunks (``00dc`` with a JPEG after its size) of an MJPG AVI."""
    out, at = [], data.find(b"00dc")
    while at >= 0:
        if data[at + 8:at + 10] == b"\xff\xd8":
            out.append(at)
        at = data.find(b"00dc", at + 4)
    return out


@pytest.mark.parametrize("damage", ["frame", "truncated"])
def test_damaged_or_truncated_video_stops_with_file_and_frame(tmp_path: Path, recordings: dict[str, Any],
                                                              damage: str) -> None:
    # 20 frames; OpenCV ends the stream at the damaged frame 4 (or where the file is cut): a map of the
    # frames before it and a localisation that writes a few lines and exits 0 would look complete.
    video = _write_video(tmp_path / "vc.avi", recordings["frames_of"](10) + recordings["frames_of"](10, seed=1))
    data = bytearray(video.read_bytes())
    chunks = _frame_chunks(bytes(data))
    assert len(chunks) == 20
    if damage == "frame":
        data[chunks[4] + 8 + 200:chunks[4] + 8 + 600] = bytes(400)
    else:
        data = data[:chunks[12] + 50]
    video.write_bytes(bytes(data))
    with pytest.raises(TopolocError, match=r"frame \d+ of the video cannot be read.* of its 20 frames.*vc\.avi"):
        list(open_source(video).frames())
    err = _cli_error(["map", "build", "--method", "seqslam", "--map", str(video), "--out", str(tmp_path / "vc.tlm"),
                      "--quiet"], "vc.avi", "frame")
    assert not (tmp_path / "vc.tlm").exists(), err
    good = _write_video(tmp_path / "good.avi", recordings["frames_of"](6))
    _cli_ok(["map", "build", "--method", "seqslam", "--param", "ds=2", "--map", str(good), "--out",
             str(tmp_path / "g.tlm"), "--quiet"])
    _cli_error(["localize", str(tmp_path / "g.tlm"), str(video), "--out", str(tmp_path / "loc.jsonl"), "--quiet"],
               "vc.avi", "frame")


# -- bags -----------------------------------------------------------------------------------------
def _route_bag(path: Path, storage: str, rec: dict[str, Any], frames: list[np.ndarray],
               encoding: str = "mono8") -> Path:
    """Frames every 0.5 s on two image topics, odometry moving 0.5 m along x every 0.5 s (stamped 0.1 s early)."""
    t0 = rec["T0"]
    msgs = []
    for k, img in enumerate(frames):
        msgs.append((ODOM, "odometry", t0 + 0.5 * k - 0.1, (0.5 * k, 2.0)))
        msgs.append((CAM, "compressed", t0 + 0.5 * k, (rec["jpeg"](img),)))
        msgs.append((RAW, "raw", t0 + 0.5 * k + 0.01, (_encode(img, encoding), encoding)))
    return rec["write_bag"](path, storage, msgs)


def _encode(gray: np.ndarray, encoding: str) -> np.ndarray:
    bgr = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    return {
        "mono8": gray, "8UC1": gray, "bgr8": bgr, "rgb8": bgr[:, :, ::-1],
        "bgra8": cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA),
        "rgba8": cv2.cvtColor(bgr, cv2.COLOR_BGR2RGBA), "mono16": gray.astype(np.uint16) * 257,
        "32FC1": gray.astype(np.float32),
    }[encoding]


@pytest.mark.usefixtures("rosbags_installed")
@pytest.mark.parametrize("storage", STORAGES)
def test_bag_image_and_compressed_topics(tmp_path: Path, recordings: dict[str, Any], storage: str) -> None:
    frames = recordings["frames_of"](6)
    bag = _route_bag(_bag_path(tmp_path, storage), storage, recordings, frames)
    assert is_stream_input(bag)
    t0 = recordings["T0"]
    raw = list(open_source(bag, topic=RAW).frames())
    assert len(raw) == 6 and all(np.array_equal(f.image, ref) for f, ref in zip(raw, frames, strict=True))
    np.testing.assert_allclose([f.time_s - t0 for f in raw], 0.5 * np.arange(6) + 0.01, atol=1e-6)
    assert raw[2].name == f"{bag.name}#2"
    assert raw[3].xy == (1.5, 2.0)  # the odometry message nearest in time (0.09 s before)
    comp = list(open_source(bag, topic=CAM).frames())
    for f, ref in zip(comp, frames, strict=True):
        assert np.array_equal(f.image, cv2.imdecode(np.frombuffer(recordings["jpeg"](ref), np.uint8),
                                                    cv2.IMREAD_GRAYSCALE))
    colour = next(open_source(bag, topic=CAM, gray=False).frames()).image
    assert colour.shape == (*frames[0].shape, 3)
    # Keyframes: every 1 m from the odometry, every 1.2 s from the stamps.
    assert [f.name for f in open_source(bag, topic=CAM, every_m=1.0).frames()] == \
        [f"{bag.name}#{k}" for k in (0, 2, 4)]
    assert [f.name for f in open_source(bag, topic=CAM, every_s=1.2).frames()] == \
        [f"{bag.name}#{k}" for k in (0, 3)]
    trav = load_input(bag, topic=CAM, every_m=1.0)
    assert len(trav) == 3 and trav.name == bag.name
    np.testing.assert_allclose(trav.xy, [[0.0, 2.0], [1.0, 2.0], [2.0, 2.0]])
    assert trav.times is not None and trav.times.dtype == np.dtype("datetime64[ms]")
    assert (trav.times - trav.times[0]).astype(np.int64).tolist() == [0, 1000, 2000]


@pytest.mark.usefixtures("rosbags_installed")
@pytest.mark.parametrize("encoding", ["8UC1", "bgr8", "rgb8", "bgra8", "rgba8", "mono16"])
def test_image_encodings(tmp_path: Path, recordings: dict[str, Any], encoding: str) -> None:
    frames = recordings["frames_of"](2)
    bag = _route_bag(tmp_path / "enc.bag", "ros1", recordings, frames, encoding=encoding)
    for f, ref in zip(open_source(bag, topic=RAW).frames(), frames, strict=True):
        assert np.abs(f.image.astype(int) - ref).max() <= 1, encoding
    for f, ref in zip(open_source(bag, topic=RAW, gray=False).frames(), frames, strict=True):
        assert np.abs(f.image.astype(int) - cv2.cvtColor(ref, cv2.COLOR_GRAY2BGR)).max() <= 1, encoding


@pytest.mark.usefixtures("rosbags_installed")
def test_navsatfix_positions_in_metres(tmp_path: Path, recordings: dict[str, Any]) -> None:
    rec, frames = recordings, recordings["frames_of"](4)
    msgs = []
    for k, img in enumerate(frames):  # 0.0001 degree of latitude ~ 11.1 m north per frame
        msgs.append(("/gps/fix", "navsat", rec["T0"] + k, (51.5 + 1e-4 * k, -0.12)))
        msgs.append((CAM, "compressed", rec["T0"] + k + 0.02, (rec["jpeg"](img),)))
    bag = rec["write_bag"](tmp_path / "gps_mcap", "mcap", msgs)
    got = list(open_source(bag, every_m=20.0).frames())  # the only image topic: --topic may be left out
    assert [f.name for f in got] == [f"{bag.name}#0", f"{bag.name}#2"]
    assert got[0].xy is not None and got[1].xy is not None
    assert got[1].xy[1] - got[0].xy[1] == pytest.approx(22.2, abs=0.3)


@pytest.mark.usefixtures("rosbags_installed")
@pytest.mark.parametrize("storage", STORAGES)
def test_bag_errors_are_one_line(tmp_path: Path, recordings: dict[str, Any], storage: str) -> None:
    frames = recordings["frames_of"](2)
    bag = _route_bag(_bag_path(tmp_path, storage), storage, recordings, frames)
    with pytest.raises(TopolocError, match=rf"topic /nope is not in the bag \(image topics: {RAW}, {CAM}\): .*{bag}"):
        open_source(bag, topic="/nope")
    with pytest.raises(TopolocError, match=f"give the image topic with topic=NAME .*{RAW}, {CAM}"):
        open_source(bag)
    with pytest.raises(TopolocError, match=f"topic {ODOM} is nav_msgs/Odometry, not an image topic"):
        open_source(bag, topic=ODOM)
    odd = _route_bag(_bag_path(tmp_path, storage, "odd"), storage, recordings, frames, encoding="32FC1")
    with pytest.raises(TopolocError, match=f"topic {RAW} message 0: image encoding '32FC1' is not supported.*{odd}"):
        open_source(odd, topic=RAW)
    no_pose = recordings["write_bag"](_bag_path(tmp_path, storage, "nopose"), storage,
                                      [(CAM, "compressed", recordings["T0"], (recordings["jpeg"](frames[0]),))])
    with pytest.raises(TopolocError, match="every_m needs an odometry, pose or GPS topic"):
        open_source(no_pose, every_m=1.0)
    assert len(list(open_source(no_pose, every_s=1.0).frames())) == 1


@pytest.mark.usefixtures("rosbags_installed")
def test_not_a_bag(tmp_path: Path) -> None:
    fake = tmp_path / "fake.bag"
    fake.write_bytes(b"#ROSBAG V2.0\n" + b"\x00garbage" * 50)
    with pytest.raises(TopolocError, match="not a readable ROS 1 bag") as exc:
        open_source(fake)
    assert "\n" not in str(exc.value) and str(fake) in str(exc.value)
    text = tmp_path / "notes.bag"
    text.write_text("hello")
    with pytest.raises(TopolocError, match=f"not a readable ROS 1 bag.*{text}"):
        open_source(text)
    folder = tmp_path / "ros2"
    folder.mkdir()
    (folder / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    with pytest.raises(TopolocError, match=f"not a readable ROS 2 bag.*{folder}"):
        open_source(folder)


def test_missing_rosbags_names_the_extra(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rosbags", None)  # import rosbags now raises ImportError
    bag = tmp_path / "x.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n")
    with pytest.raises(TopolocError, match=r"pip install 'topoloc\[ros\]'") as exc:
        open_source(bag)
    assert "\n" not in str(exc.value)


def test_keyframe_options_are_checked() -> None:
    with pytest.raises(TopolocError, match="not both"):
        Keyframes(every_s=1.0, every_m=1.0)
    with pytest.raises(TopolocError, match="every_s must be a number >= 0"):
        Keyframes(every_s=-1.0)
    k = Keyframes(every_m=1.0)
    assert not k.keep(0.0, None) and k.keep(0.1, (0.0, 0.0)) and not k.keep(0.2, (0.5, 0.5))
    assert k.keep(0.3, (1.0, 0.0))


@pytest.mark.usefixtures("rosbags_installed")
@pytest.mark.parametrize("storage", ["ros1", "mcap"])
def test_memory_does_not_grow_with_length(tmp_path: Path, recordings: dict[str, Any], storage: str) -> None:
    def peak(n: int) -> int:
        img = recordings["frames_of"](1, h=120, w=160)[0]
        msgs = [(RAW, "raw", recordings["T0"] + 0.1 * k, (img, "mono8")) for k in range(n)]
        bag = recordings["write_bag"](_bag_path(tmp_path, storage, f"len{n}"), storage, msgs)
        src = open_source(bag, topic=RAW)
        tracemalloc.start()
        count = sum(1 for _ in src.frames())
        _, top = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert count == n
        return top

    short, long = peak(20), peak(400)  # 0.4 MB of pixels vs 7.7 MB
    assert long < short + 2_000_000, (short, long)


# -- command line ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def route_map(tiny_route_map: Path) -> Path:
    """The tiny route's bag-of-words map (its vocabulary file beside it)."""
    return tiny_route_map


@pytest.mark.usefixtures("rosbags_installed")
@pytest.mark.parametrize("storage", STORAGES)
def test_localize_bag_equals_localize_folder(
    tmp_path: Path, tiny_route: dict[str, Any], route_map: Path, recordings: dict[str, Any], storage: str,
) -> None:
    query = tiny_route["query"].root
    files = sorted(query.glob("*.jpg"))
    t0 = recordings["T0"]
    msgs = [(CAM, "compressed", t0 + k, (f.read_bytes(),)) for k, f in enumerate(files)]
    msgs += [(ODOM, "odometry", t0 + k + 0.3, (3.0 * k, 0.0)) for k in range(len(files))]
    bag = recordings["write_bag"](_bag_path(tmp_path, storage, "recording"), storage, msgs)
    _cli_ok(["localize", str(route_map), str(query), "--out", str(tmp_path / "folder.jsonl"), "--quiet"])
    summary = json.loads(_cli_ok(["localize", str(route_map), str(bag), "--topic", CAM,
                                  "--out", str(tmp_path / "bag.jsonl"), "--quiet"]))
    assert summary["frames"] == len(files)
    folder = [json.loads(line) for line in (tmp_path / "folder.jsonl").read_text().splitlines()]
    lines = [json.loads(line) for line in (tmp_path / "bag.jsonl").read_text().splitlines()]
    assert [r["place"] for r in lines] == [r["place"] for r in folder]
    assert [r["top"] for r in lines] == [r["top"] for r in folder]
    assert [r["time"] for r in lines] == pytest.approx([t0 + k for k in range(len(files))])
    assert lines[1]["image"] == f"{bag.name}#1" and "time" not in folder[0]
    # Keyframes every 5 m of odometry (3 m per frame): frames 0, 2, 4, ...
    _cli_ok(["localize", str(route_map), str(bag), "--topic", CAM, "--every-m", "5",
             "--out", str(tmp_path / "every.jsonl"), "--quiet"])
    every = [json.loads(line) for line in (tmp_path / "every.jsonl").read_text().splitlines()]
    assert [r["image"] for r in every] == [f"{bag.name}#{k}" for k in range(0, len(files), 2)]
    assert [r["place"] for r in every] == [r["place"] for r in folder[::2]]


@pytest.mark.usefixtures("rosbags_installed")
def test_cli_bags_and_videos_as_traverses(
    tmp_path: Path, tiny_route: dict[str, Any], route_map: Path, recordings: dict[str, Any],
) -> None:
    files = sorted(tiny_route["query"].root.glob("*.jpg"))
    t0 = recordings["T0"]
    bag = recordings["write_bag"](tmp_path / "q.bag", "ros1",
                                  [(CAM, "compressed", t0 + k, (f.read_bytes(),)) for k, f in enumerate(files)])
    voc = route_map.parent / "vocab.tlv"
    # evaluate with the bag as the query (frame k is place k), and map build from a video
    out = tmp_path / "run"
    _cli_ok(["evaluate", "--method", "bow", "--map", str(tiny_route["map"].root), "--query", str(bag),
             "--topic", CAM, "--vocab", str(voc), "--out", str(out), "--quiet"])
    metrics = json.loads((out / "metrics.json").read_text())
    folder_out = tmp_path / "run_folder"
    _cli_ok(["evaluate", "--method", "bow", "--map", str(tiny_route["map"].root), "--query",
             str(tiny_route["query"].root), "--vocab", str(voc), "--out", str(folder_out), "--quiet"])
    assert np.array_equal(np.load(out / "S.npy"), np.load(folder_out / "S.npy"))
    assert np.array_equal(np.load(out / "queries.npy"), np.arange(len(files)))  # no places.csv: frame k, place k
    assert metrics["run"]["query"] == str(bag)
    video = _write_video(tmp_path / "noon.avi", [tiny_route["map"].read(i) for i in range(len(tiny_route["map"]))],
                         fps=5.0)
    tlm = tmp_path / "video.tlm"
    built = json.loads(_cli_ok(["map", "build", "--method", "bow", "--map", str(video), "--vocab", str(voc),
                                "--out", str(tlm), "--quiet"]))
    assert built["places"] == len(tiny_route["map"]) and built["tours"] == ["noon.avi"]
    half = json.loads(_cli_ok(["map", "build", "--method", "bow", "--map", str(video), "--every-s", "0.35",
                               "--vocab", str(voc), "--out", str(tmp_path / "half.tlm"), "--quiet"]))
    assert half["places"] == (len(tiny_route["map"]) + 1) // 2
    _cli_ok(["localize", str(tlm), str(video), "--out", str(tmp_path / "v.jsonl"), "--quiet"])
    # map add and map calibrate take recordings too
    added = json.loads(_cli_ok(["map", "add", str(tlm), str(bag), "--topic", CAM, "--quiet"]))
    assert added["tours"] == ["noon.avi", "q.bag"]
    # the map's own recording would calibrate on training images: refused, naming it and the map
    _cli_error(["map", "calibrate", str(tlm), "--query", str(video), "--quiet"], "noon.avi", "own tour", "video.tlm")
    dusk = _write_video(tmp_path / "dusk.avi", [tiny_route["query"].read(i) for i in range(len(tiny_route["query"]))],
                        fps=5.0)
    calibrated = json.loads(_cli_ok(["map", "calibrate", str(tlm), "--query", str(dusk), "--quiet"]))
    assert calibrated["n_queries"] == len(tiny_route["query"])
    assert json.loads((tmp_path / "v.jsonl").read_text().splitlines()[2])["time"] == pytest.approx(0.4, abs=1e-3)


@pytest.mark.usefixtures("rosbags_installed")
def test_cli_bad_recordings_exit_2(tmp_path: Path, route_map: Path, recordings: dict[str, Any]) -> None:
    out = str(tmp_path / "r.jsonl")
    fake = tmp_path / "recording.bag"
    fake.write_bytes(b"this is not a bag")
    _cli_error(["localize", str(route_map), str(fake), "--topic", CAM, "--out", out], "not a readable ROS 1 bag",
               str(fake))
    frames = recordings["frames_of"](2)
    odd = _route_bag(tmp_path / "odd.bag", "ros1", recordings, frames, encoding="32FC1")
    _cli_error(["localize", str(route_map), str(odd), "--topic", RAW, "--out", out],
               "image encoding '32FC1' is not supported", str(odd))
    _cli_error(["localize", str(route_map), str(odd), "--topic", "/camera/left", "--out", out],
               f"topic /camera/left is not in the bag (image topics: {RAW}, {CAM})", str(odd))
    _cli_error(["map", "build", "--method", "bow", "--map", str(odd), "--topic", "/x", "--out",
                str(tmp_path / "m.tlm")], "topic /x is not in the bag")
    folder = tmp_path / "imgs"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), frames[0])
    _cli_error(["localize", str(route_map), str(folder), "--topic", CAM, "--out", out],
               "--topic applies to ROS bags and videos only, and no input is one")
    junk = tmp_path / "clip.mkv"
    junk.write_bytes(b"\x00" * 100)
    _cli_error(["localize", str(route_map), str(junk), "--out", out], "clip.mkv")
