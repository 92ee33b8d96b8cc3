"""Publish-to-answer latency of the ROS nodes at a camera's rate, quiet and beside busy processes (#37, #48).

    .venv/bin/python -m benchmarks.bench_ros_latency --prepare          # the map and the ROS 2 environment
    flock -x /work/notes/cpu.lock .venv/bin/python -m benchmarks.bench_ros_latency   # about 4 min on 2 cores
    .venv/bin/python -m benchmarks.bench_ros_latency --quick    # fewer frames
    .venv/bin/python -m benchmarks.bench_ros_latency --ros 2    # only ROS 2 (the ROS 1 rows kept from the last run)

Needs ``../shared/data``, and ROS 1 (Debian 12: ``apt-get install ros-base python3-rospy python3-sensor-msgs
python3-geometry-msgs python3-diagnostic-msgs python3-std-srvs``) for its rows and ROS 2 (the environment of
:mod:`topoloc.ros.environment`, built here where missing) for its rows; ``--ros`` defaults to those installed, and
the rows of a ROS not run are kept from the page's last run.  The map is gardens_point ``day_left`` (Cooc-Map, the
flagship, SIFT features as the first ROS 1 rows were measured with: the transport and the node are measured
here, the features' own speed in ``bench_camera_rate``; vocabulary trained on webcam_daynight's map tours, as
the other gardens_point results), built once into ``--work``.  For each camera rate (10 and 30 Hz) and load (0
and 3 busy processes, each a Python spin loop as in ``benchmarks/bench_load.py``), the node runs as its own process
(newest-frame policy, default prefetch: one frame per core) and a probe (``topoloc.ros.probe`` on ROS 1 through a
private ``roscore``, ``topoloc.ros.probe2`` on ROS 2 over DDS on a domain of its own) publishes ``day_right``'s
960 x 540 frames as raw ``bgr8`` ``sensor_msgs/Image`` at that rate, stamped with the wall clock when sent; each
answer's latency is its arrival at the probe less that stamp (both processes on this machine's clock).  The
frames answered, skipped (and, on ROS 2, lost before the node) are the node's own count (its last line).  ROS 2
runs with Fast DDS kept on this machine (UDP on 127.0.0.1 alone) and shared-memory segments of 16 MB, which raw
frames of 1.5 MB need with best-effort delivery; one run with Fast DDS's own 512 kB segments shows why.  The
flood runs publish at 10x the camera rate (100 and 300 Hz, quiet; as fast as the probe can where it cannot reach
that) and measure whether the answers stay current.  The load average before each run is recorded beside it:
other processes on the machine add to the busy ones.  Writes ``ros_latency.json`` and ``ros_latency.md`` in
``--out`` (default ``docs/results``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

import numpy as np

from benchmarks.bench_load import busy
from benchmarks.common import GP, REPO, RESULTS, TOPOLOC, VOCAB_FOR_GP, machine_line, require_data
from topoloc.ros.environment import FASTDDS_DEFAULT_SEGMENT, LOOPBACK_SEGMENT
from topoloc.ros.probe import LocalMaster, wait_for

RATES = (10.0, 30.0)
BUSY = (0, 3)
#: Seconds of frames published per run (``--quick``: half).
SECONDS = 20.0
#: The flood: this many times the camera's rate, for FLOOD_SECONDS.
FLOOD_X = 10
FLOOD_SECONDS = 10.0


def build_map(work: Path) -> Path:
    """gardens_point day_left as a Cooc-Map map, built once into ``work``."""
    map_file = work / "gp_day_left.tlm"
    if not map_file.exists():
        cmd = [str(TOPOLOC), "map", "build", "--method", "coocmap", "--features", "sift", "--map", str(GP / "day_left"),
               "--out", str(map_file), "-q"]
        for folder in VOCAB_FOR_GP:
            cmd += ["--vocab-train", str(folder)]
        subprocess.run(cmd, check=True)
    return map_file


def _stop(node: subprocess.Popen[str], err: IO[str]) -> None:
    """The node stopped as a user stops it (SIGTERM), its stderr file closed."""
    if node.poll() is None:
        node.send_signal(signal.SIGTERM)
    node.wait(timeout=60)
    err.close()


def _counts(err_file: Path, pattern: str) -> re.Match[str]:
    """The counts of the node's last line (the one it says when it stops)."""
    last = err_file.read_text().strip().splitlines()[-1]
    match = re.search(pattern, last)
    if match is None:
        raise RuntimeError(f"the node did not stop as it should: {last}")
    return match


def _records(path: Path) -> list[dict[str, Any]]:
    """A probe's JSON lines (topoloc.ros.record)."""
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()]


def run_one(core: LocalMaster, map_file: Path, rate: float, n_busy: int, seconds: float, work: Path) -> dict[str, Any]:
    """One node and one probe at ``rate`` beside ``n_busy`` busy processes: latency, answered, skipped."""
    tag = f"{int(rate)}hz_{n_busy}busy"
    answers = work / f"{tag}.jsonl"
    err = (work / f"{tag}.node.err").open("w")
    node = subprocess.Popen([sys.executable, "-m", "topoloc", "ros-node", str(map_file), "--image-topic",
                             "/bench/image", "__name:=topoloc_bench"], env=core.env, stdout=subprocess.DEVNULL,
                            stderr=err, text=True)
    try:
        wait_for("the node", lambda: bool(core.subscribers("/bench/image")) or node.poll() is not None)
        count = round(rate * seconds)
        with busy(n_busy):
            load = os.getloadavg()[0]
            subprocess.run([sys.executable, "-m", "topoloc.ros.probe", "--out", str(answers), "--answers",
                            "/topoloc_bench/answer", "--publish", str(GP / "day_right"), "--topic", "/bench/image",
                            "--encoding", "bgr8", "--rate", str(rate), "--count", str(count), "--linger", "3"],
                           env=core.env, check=True, timeout=seconds * 4 + 120)
    finally:
        _stop(node, err)
    match = _counts(work / f"{tag}.node.err", r"(\d+) frames in, (\d+) answered, (\d+) skipped")
    records = _records(answers)
    latency = np.array([r["publish_to_answer_ms"] for r in records if r["kind"] == "answer"])
    published = next(r["published"] for r in records if r["kind"] == "summary")
    return {"rate_hz": rate, "busy": n_busy, "published": published, "frames_in": int(match.group(1)),
            "answered": int(match.group(2)), "skipped": int(match.group(3)),
            "answers_received": int(latency.size),
            "latency_ms_median": round(float(np.median(latency)), 1) if latency.size else None,
            "latency_ms_p95": round(float(np.percentile(latency, 95)), 1) if latency.size else None,
            "latency_ms_max": round(float(latency.max()), 1) if latency.size else None,
            "load_average_1min": round(load, 2)}


def _latency(records: list[dict[str, Any]]) -> dict[str, Any]:
    ms = np.array([r["publish_to_answer_ms"] for r in records if r["kind"] == "answer"])
    return {"answers_received": int(ms.size),
            "latency_ms_median": round(float(np.median(ms)), 1) if ms.size else None,
            "latency_ms_p95": round(float(np.percentile(ms, 95)), 1) if ms.size else None,
            "latency_ms_max": round(float(ms.max()), 1) if ms.size else None}


def run_one_ros2(python: Path, domain: Any, map_file: Path, rate: float, n_busy: int, seconds: float, work: Path,
                 *, segment: int = LOOPBACK_SEGMENT, kind: str = "camera") -> dict[str, Any]:
    """One ROS 2 node and one probe at ``rate`` beside ``n_busy`` busy processes (shared-memory ``segment`` bytes)."""
    tag = f"ros2_{kind}_{int(rate)}hz_{n_busy}busy_{segment}"
    answers = work / f"{tag}.jsonl"
    env = domain.env(segment=segment, PYTHONPATH=str(REPO / "src"), ROS_LOG_DIR=str(work / "ros_log"))
    err = (work / f"{tag}.node.err").open("w")
    node = subprocess.Popen([str(python), "-m", "topoloc.cli.main", "ros2-node", str(map_file), "--image-topic",
                             "/bench/image", "--ros-args", "-r", "__ns:=/bench"], env=env, stdout=subprocess.DEVNULL,
                            stderr=err, text=True)
    try:
        count = round(rate * seconds)
        with busy(n_busy):
            load = os.getloadavg()[0]
            subprocess.run([str(python), "-m", "topoloc.ros.probe2", "--out", str(answers), "--answers",
                            "/bench/answer", "--publish", str(GP / "day_right"), "--topic", "/bench/image",
                            "--encoding", "bgr8", "--rate", str(rate), "--count", str(count), "--linger", "3"],
                           env=env, check=True, timeout=seconds * 10 + 120)
    finally:
        _stop(node, err)
    match = _counts(work / f"{tag}.node.err",
                    r"(\d+) frames in, (\d+) answered, (\d+) skipped, (\d+) unreadable, (\d+) lost")
    records = _records(answers)
    summary = next(r for r in records if r["kind"] == "summary")
    frames = [int(r["frame_id"].rsplit("_", 1)[1]) for r in records if r["kind"] == "answer"]
    first = next((r["publish_to_answer_ms"] for r in records if r["kind"] == "answer"), None)
    return {"ros": 2, "last_frame_answered": max(frames) if frames else None, "first_answer_ms": first,
            "kind": kind, "segment_bytes": segment, "rate_hz": rate, "busy": n_busy,
            "published": summary["published"], "published_hz": round(summary["published"] / summary["seconds"], 1),
            "frames_in": int(match.group(1)), "answered": int(match.group(2)), "skipped": int(match.group(3)),
            "lost": int(match.group(5)), **_latency(records), "load_average_1min": round(load, 2)}


def _table(rows: list[dict[str, Any]], *, ros2: bool) -> list[str]:
    head = ("| camera | busy processes | published | " + ("reached the node | lost before it | " if ros2 else "")
            + "answered | skipped | latency median ms | p95 ms | max ms | load before |\n")
    out = [head, "|" + " ---: |" * (head.count("|") - 1) + "\n"]
    for r in rows:
        out.append(f"| {r['rate_hz']:.0f} Hz | {r['busy']} | {r['published']} | "
                   + (f"{r['frames_in']} | {r['lost']} | " if ros2 else "")
                   + f"{r['answered']} | {r['skipped']} | {r['latency_ms_median']} | {r['latency_ms_p95']} | "
                   f"{r['latency_ms_max']} | {r['load_average_1min']:.1f} |\n")
    return out


def _sentences(rows: list[dict[str, Any]]) -> list[str]:
    quiet = {r["rate_hz"]: r for r in rows if r["busy"] == 0}
    loaded = {r["rate_hz"]: r for r in rows if r["busy"] == 3}
    out = []
    for rate in sorted(quiet):
        q, b = quiet[rate], loaded.get(rate)
        line = (f"At {rate:.0f} Hz the node answered {q['answered']} of {q['frames_in']} frames "
                f"({q['skipped']} skipped) with a median latency of {q['latency_ms_median']} ms")
        if b is not None and q["latency_ms_median"] and b["latency_ms_median"]:
            line += (f"; beside 3 busy processes {b['answered']} of {b['frames_in']} ({b['skipped']} skipped), "
                     f"median {b['latency_ms_median']} ms, {b['latency_ms_median'] / q['latency_ms_median']:.1f}x")
        out.append(line + ".\n")
    return out


def page(data: dict[str, Any]) -> str:
    """``ros_latency.md``: the tables and what they say, from the runs of each ROS."""
    out = ["# ROS nodes: publish-to-answer latency\n\n",
           "Written by `benchmarks/bench_ros_latency.py` (its docstring says how each figure is measured). "
           "Latency: the answer's arrival at the probe less the frame's header stamp, set when the probe published "
           "it; both on this machine's clock. Node with its defaults (newest frame, queue 1, prefetch one frame per "
           "core); camera: gardens_point day_right's 960 x 540 frames as raw bgr8 `sensor_msgs/Image`.\n\n"]
    one = data.get("ros1")
    if one:
        out += [f"## ROS 1 (`topoloc ros-node`, a real roscore on 127.0.0.1)\n\n`{one['command']}` on "
                f"{one['machine']}, {one['date']}. Map: gardens_point day_left ({one['places']} places, method "
                f"{one['method']}, features {one['features']}).\n\n"]
        out += [*_table(one["rows"], ros2=False), "\n", *_sentences(one["rows"])]
        lost = [r for r in one["rows"] if r["published"] > r["frames_in"]]
        if lost:
            out.append("Where fewer frames came in than were published, the publisher (the probe, a `rospy` publisher "
                       "with a queue of 1 as camera drivers keep) dropped them before they were sent: "
                       + ", ".join(f"{r['published'] - r['frames_in']} at {r['rate_hz']:.0f} Hz with {r['busy']} busy"
                                   for r in lost) + ".\n")
        out.append("\n")
    two = data.get("ros2")
    if two:
        camera = [r for r in two["rows"] if r["kind"] == "camera" and r["segment_bytes"] == LOOPBACK_SEGMENT]
        default = [r for r in two["rows"] if r["kind"] == "camera" and r["segment_bytes"] == FASTDDS_DEFAULT_SEGMENT]
        flood = [r for r in two["rows"] if r["kind"] == "flood"]
        out += [f"## ROS 2 (`topoloc ros2-node`, rclpy {two.get('rclpy', '?')}, Fast DDS, over DDS on this "
                f"machine)\n\n`{two['command']}` on {two['machine']}, {two['date']}. Map: as above "
                f"({two['places']} places, method {two['method']}, features {two['features']}). Fast DDS kept on "
                "this machine (UDP on 127.0.0.1 alone, and shared memory with 16 MB segments: "
                "`topoloc.ros.environment.loopback_profile`); the node's image subscription has the sensor-data "
                "QoS (best effort, keep last 5), the probe's publisher a camera driver's (reliable, keep last 10). "
                "*Lost before it*: frames published that never reached the node's buffer (gaps in the publisher's "
                "numbers), which the sensor-data QoS drops when its 5 places are full or the transport overwrote "
                "before the node took them. Both nodes warm up (one frame's first-use costs) before they "
                "subscribe.\n\n"]
        out += [*_table(camera, ros2=True), "\n", *_sentences(camera)]
        one_rows = {(r["rate_hz"], r["busy"]): r for r in (one or {}).get("rows", [])}
        pairs = [(r, one_rows.get((r["rate_hz"], r["busy"]))) for r in camera]
        pairs = [(a, b) for a, b in pairs if b is not None and a["latency_ms_median"] and b["latency_ms_median"]]
        if pairs:
            out.append("Beside the ROS 1 rows (measured earlier, on the same map and machine kind): median "
                       + ", ".join(f"{a['latency_ms_median']} vs {b['latency_ms_median']} ms at {a['rate_hz']:.0f} Hz "
                                   f"with {a['busy']} busy" for a, b in pairs) + " (ROS 2 vs ROS 1).\n")
        if default:
            d = default[0]
            reached = (f"{d['frames_in']} of {d['published']} reached the node, {d['answered']} answered"
                       if d["frames_in"] else f"none of {d['published']} reached the node (which counts as lost only "
                       "the gaps between frames it received)")
            out.append(f"\nWith Fast DDS's own segment size (512 kB) the same 1.5 MB frames at "
                       f"{d['rate_hz']:.0f} Hz: {reached}: a "
                       "best-effort subscription loses raw frames larger than a shared-memory segment on one machine. "
                       "Give the camera driver and the node larger segments (a Fast DDS profile, or "
                       "`FASTDDS_BUILTIN_TRANSPORTS=LARGE_DATA`), or subscribe to the compressed topic "
                       "(docs/ros.md).\n")
        if flood:
            out += ["\n### A flood at 10x the camera rate\n\n",
                    "| asked | published at | reached the node | lost before it | answered | skipped | latency median "
                    "ms | p95 ms | max ms |\n", "|" + " ---: |" * 9 + "\n"]
            for r in flood:
                out.append(f"| {r['rate_hz']:.0f} Hz | {r['published_hz']} Hz | {r['frames_in']} | {r['lost']} | "
                           f"{r['answered']} | {r['skipped']} | {r['latency_ms_median']} | {r['latency_ms_p95']} | "
                           f"{r['latency_ms_max']} |\n")
            for r in flood:
                out.append(f"\nAt {r['rate_hz']:.0f} Hz the last answer was about frame {r['last_frame_answered']} "
                           f"of the {r['published']} published (numbered from 0); the first answer came "
                           f"{r['first_answer_ms']} ms after its frame, the worst {r['latency_ms_max']} ms. ")
            out.append("The frames the node could not take were skipped or dropped before it, and counted.\n")
    out.append(f"\nThe 1-minute load average before each run is given beside it ({os.cpu_count()} cores): where it "
               "is above the busy processes started, other processes shared the machine and the latencies are higher "
               "than on an otherwise idle one. A skipped frame is one that arrived while the frames before it were "
               "being matched: the node answers the newest instead of falling behind.\n")
    return "".join(out)


def _installed(version: int) -> bool:
    if version == 1:
        from topoloc.errors import TopolocError
        from topoloc.ros import import_rospy

        try:
            import_rospy()
        except TopolocError:
            return False
        return True
    return True  # ROS 2: its environment is built where missing


def _previous(path: Path) -> dict[str, Any]:
    """The last run's page data (a page of the first version, ROS 1 alone, as its ros1 part)."""
    if not path.exists():
        return {}
    data = json.loads(path.read_text())
    return data if "ros1" in data or "ros2" in data else {"ros1": data}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="half the frames per run")
    ap.add_argument("--ros", choices=["1", "2", "both"], help="which nodes (default: those installed)")
    ap.add_argument("--prepare", action="store_true", help="build the map and the ROS 2 environment, then stop")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "topoloc_bench_ros")
    args = ap.parse_args()
    require_data()
    args.work.mkdir(parents=True, exist_ok=True)
    map_file = build_map(args.work)
    from topoloc.ros import environment

    versions = [1, 2] if args.ros in (None, "both") else [int(args.ros)]
    if args.ros is None:
        versions = [v for v in versions if _installed(v)]
    python = environment.ensure() if 2 in versions else None
    if args.prepare:
        print(f"map {map_file}; ROS 2 environment {python}")
        return
    # Once before the clock: the first use of compiled code (numba's cache of this checkout's Cooc-Map matcher)
    # and of the feature cache would otherwise fall on the first run's frames.
    subprocess.run([str(TOPOLOC), "localize", str(map_file), str(sorted((GP / "day_right").iterdir())[0]),
                    "--out", str(args.work / "warm.jsonl"), "-q"], check=True, capture_output=True)
    info = json.loads(subprocess.run([str(TOPOLOC), "map", "info", str(map_file), "--json"], check=True,
                                     capture_output=True, text=True).stdout)
    seconds = SECONDS / 2 if args.quick else SECONDS
    command = "python -m benchmarks.bench_ros_latency" + (" --quick" if args.quick else "") + \
        (f" --ros {args.ros}" if args.ros else "")
    meta = {"command": command, "machine": machine_line(), "date": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
            "places": info.get("places"), "method": info.get("method"),
            "features": (info.get("features") or {}).get("method"), "seconds_per_run": seconds}
    data = _previous(args.out / "ros_latency.json")
    if 1 in versions:
        core = LocalMaster(args.work, extra_path=REPO / "src")
        rows = []
        try:
            for rate in RATES:
                for n_busy in BUSY:
                    rows.append(run_one(core, map_file, rate, n_busy, seconds, args.work))
                    print(json.dumps(rows[-1]), flush=True)
        finally:
            core.close()
        data["ros1"] = {**meta, "rows": rows}
    if 2 in versions:
        assert python is not None
        domain = environment.PrivateDomain()
        rows = []
        try:
            runs = [dict(rate=rate, n_busy=n_busy, seconds=seconds) for rate in RATES for n_busy in BUSY]
            runs.append(dict(rate=RATES[0], n_busy=0, seconds=seconds, segment=FASTDDS_DEFAULT_SEGMENT))
            runs += [dict(rate=FLOOD_X * rate, n_busy=0, seconds=FLOOD_SECONDS / (2 if args.quick else 1),
                          kind="flood") for rate in RATES]
            for run in runs:
                rows.append(run_one_ros2(python, domain, map_file, work=args.work, **run))  # type: ignore[arg-type]
                print(json.dumps(rows[-1]), flush=True)
        finally:
            domain.close()
        version = subprocess.run([str(python), "-c", "from importlib.metadata import version; "
                                  "print(version('ros-rclpy'))"], capture_output=True, text=True,
                                 env=environment.clean_env()).stdout.strip()
        data["ros2"] = {**meta, "rclpy": version, "rows": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ros_latency.json").write_text(json.dumps(data, indent=1) + "\n")
    (args.out / "ros_latency.md").write_text(page(data))
    print(f"wrote {args.out / 'ros_latency.md'}")


if __name__ == "__main__":
    main()
