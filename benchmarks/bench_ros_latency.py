"""Publish-to-answer latency of the ROS node at a camera's rate, quiet and beside busy processes (issue #37).

    .venv/bin/python -m benchmarks.bench_ros_latency            # about 3 min on 2 cores
    .venv/bin/python -m benchmarks.bench_ros_latency --quick    # fewer frames, about 1.5 min
    .venv/bin/python -m benchmarks.bench_ros_latency --out /tmp/ros   # results elsewhere

Needs ROS 1 (Debian 12: ``apt-get install ros-base python3-rospy python3-sensor-msgs python3-geometry-msgs
python3-diagnostic-msgs python3-std-srvs``) and ``../shared/data``.  A ``roscore`` is started on a free
loopback port; the map is gardens_point ``day_left`` (Cooc-Map, the flagship, with the default features;
vocabulary trained on webcam_daynight's map tours, as the other gardens_point results), built once into
``--work``.  For each camera rate (10 and 30 Hz) and load (0 and 3 busy processes, each a Python spin loop
as in ``benchmarks/bench_load.py``), the node (``python -m topoloc.ros``, newest-frame policy, default
prefetch: one frame per core) runs as its own process and the probe (``python -m topoloc.ros.probe``) publishes
``day_right``'s 960 x 540 frames as raw ``bgr8`` ``sensor_msgs/Image`` at that rate, stamped with the wall
clock when sent; each answer's latency is its arrival at the probe less that stamp (both processes on this
machine's clock).  The frames answered and skipped are the node's own count (its last line).  The load
average before each run is recorded beside it: other processes on the machine add to the busy ones.
Writes ``ros_latency.json`` and ``ros_latency.md`` in ``--out`` (default ``docs/results``).
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
from typing import Any

import numpy as np

from benchmarks.bench_load import busy
from benchmarks.common import GP, REPO, RESULTS, TOPOLOC, VOCAB_FOR_GP, machine_line, require_data
from topoloc.ros.probe import LocalMaster, wait_for

RATES = (10.0, 30.0)
BUSY = (0, 3)
#: Seconds of frames published per run (``--quick``: half).
SECONDS = 20.0


def build_map(work: Path) -> Path:
    """gardens_point day_left as a Cooc-Map map, built once into ``work``."""
    map_file = work / "gp_day_left.tlm"
    if not map_file.exists():
        cmd = [str(TOPOLOC), "map", "build", "--method", "coocmap", "--map", str(GP / "day_left"), "--out",
               str(map_file), "-q"]
        for folder in VOCAB_FOR_GP:
            cmd += ["--vocab-train", str(folder)]
        subprocess.run(cmd, check=True)
    return map_file


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
        if node.poll() is None:
            node.send_signal(signal.SIGTERM)
        node.wait(timeout=60)
        err.close()
    last = (work / f"{tag}.node.err").read_text().strip().splitlines()[-1]
    match = re.search(r"(\d+) frames in, (\d+) answered, (\d+) skipped", last)
    if match is None:
        raise RuntimeError(f"the node did not stop as it should: {last}")
    records = [json.loads(x) for x in answers.read_text().splitlines() if x.strip()]
    latency = np.array([r["publish_to_answer_ms"] for r in records if r["kind"] == "answer"])
    published = next(r["published"] for r in records if r["kind"] == "summary")
    return {"rate_hz": rate, "busy": n_busy, "published": published, "frames_in": int(match.group(1)),
            "answered": int(match.group(2)), "skipped": int(match.group(3)),
            "answers_received": int(latency.size),
            "latency_ms_median": round(float(np.median(latency)), 1) if latency.size else None,
            "latency_ms_p95": round(float(np.percentile(latency, 95)), 1) if latency.size else None,
            "latency_ms_max": round(float(latency.max()), 1) if latency.size else None,
            "load_average_1min": round(load, 2)}


def page(rows: list[dict[str, Any]], meta: dict[str, Any]) -> str:
    """``ros_latency.md``: the table and what it says, from the rows."""
    out = ["# ROS node: publish-to-answer latency\n\n",
           f"`{meta['command']}` on {meta['machine']}, {meta['date']} (`benchmarks/bench_ros_latency.py`).\n\n",
           f"Map: gardens_point day_left ({meta['places']} places, method {meta['method']}, features "
           f"{meta['features']}); camera: day_right's 960 x 540 frames as raw bgr8 `sensor_msgs/Image` through a "
           "real roscore on 127.0.0.1; node with its defaults (newest frame, `--queue 1`, prefetch one frame per "
           "core). "
           "Latency: the answer's arrival at the probe less the frame's header stamp (set when it was "
           "published).\n\n",
           "| camera | busy processes | published | answered | skipped | latency median ms | p95 ms | max ms | "
           "load before |\n", "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |\n"]
    for r in rows:
        out.append(f"| {r['rate_hz']:.0f} Hz | {r['busy']} | {r['published']} | {r['answered']} | {r['skipped']} | "
                   f"{r['latency_ms_median']} | {r['latency_ms_p95']} | {r['latency_ms_max']} | "
                   f"{r['load_average_1min']:.1f} |\n")
    quiet = {r["rate_hz"]: r for r in rows if r["busy"] == 0}
    loaded = {r["rate_hz"]: r for r in rows if r["busy"] == 3}
    out.append("\n")
    for rate in sorted(quiet):
        q, b = quiet[rate], loaded.get(rate)
        line = (f"At {rate:.0f} Hz the node answered {q['answered']} of {q['frames_in']} frames "
                f"({q['skipped']} skipped) with a median latency of {q['latency_ms_median']} ms")
        if b is not None and q["latency_ms_median"] and b["latency_ms_median"]:
            line += (f"; beside 3 busy processes {b['answered']} of {b['frames_in']} ({b['skipped']} skipped), "
                     f"median {b['latency_ms_median']} ms, {b['latency_ms_median'] / q['latency_ms_median']:.1f}x")
        out.append(line + ".\n")
    out.append(f"\nThe 1-minute load average before each run is given beside it ({os.cpu_count()} cores): "
               "where it is above the busy processes started, other processes shared the machine and the "
               "latencies are higher than on an otherwise idle one. A skipped frame is one that arrived while "
               "the frames before it were being matched: the node answers the newest instead of falling behind.")
    lost = [r for r in rows if r["published"] > r["frames_in"]]
    if lost:
        out.append(" Where fewer frames came in than were published, the publisher (the probe, a `rospy` publisher "
                   "with a queue of 1 as camera drivers keep) dropped them before they were sent, because its "
                   "own sending thread was not scheduled in time: "
                   + ", ".join(f"{r['published'] - r['frames_in']} at {r['rate_hz']:.0f} Hz with {r['busy']} busy"
                               for r in lost) + ".")
    out.append("\n")
    return "".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="half the frames per run")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "topoloc_bench_ros")
    args = ap.parse_args()
    require_data()
    args.work.mkdir(parents=True, exist_ok=True)
    map_file = build_map(args.work)
    # Once before the clock: the first use of compiled code (numba's cache of this checkout's Cooc-Map matcher)
    # and of the feature cache would otherwise fall on the first run's frames.
    subprocess.run([str(TOPOLOC), "localize", str(map_file), str(sorted((GP / "day_right").iterdir())[0]),
                    "--out", str(args.work / "warm.jsonl"), "-q"], check=True, capture_output=True)
    info = json.loads(subprocess.run([str(TOPOLOC), "map", "info", str(map_file), "--json"], check=True,
                                     capture_output=True, text=True).stdout)
    seconds = SECONDS / 2 if args.quick else SECONDS
    core = LocalMaster(args.work, extra_path=REPO / "src")
    rows = []
    try:
        for rate in RATES:
            for n_busy in BUSY:
                rows.append(run_one(core, map_file, rate, n_busy, seconds, args.work))
                print(json.dumps(rows[-1]), flush=True)
    finally:
        core.close()
    command = "python -m benchmarks.bench_ros_latency" + (" --quick" if args.quick else "")
    meta = {"command": command, "machine": machine_line(), "date": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
            "places": info.get("places"), "method": info.get("method"),
            "features": (info.get("features") or {}).get("method"), "seconds_per_run": seconds}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ros_latency.json").write_text(json.dumps({**meta, "rows": rows}, indent=1) + "\n")
    (args.out / "ros_latency.md").write_text(page(rows, meta))
    print(f"wrote {args.out / 'ros_latency.md'}")


if __name__ == "__main__":
    main()
