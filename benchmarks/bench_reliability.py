"""Regenerate docs/results/reliability.md: bad input and faults by family, and runs killed at random moments.

    .venv/bin/python -m benchmarks.bench_reliability          # every case (about 10 minutes on 2 cores)
    .venv/bin/python -m benchmarks.bench_reliability --fast   # the families only (a few minutes)

The families of issue #26 (:data:`FAMILIES`: data loss, silent wrong, hangs,
bombs, tracebacks, names) are cases run as a user would, each a ``topoloc``
process with a time limit (and a memory limit for the bombs): a case *holds*
when the command does what the family promises (one line and exit 2 for bad
input, a user's file intact, one warning line, a page whose names are text).

On a generated route (no shared data needed), each command is first run to
completion (the reference) and timed; then, for a seeded set of kill times
spread over that duration, the command is started on the outputs of the
previous attempt, killed with SIGKILL at that moment, every file it left is
checked to be whole and valid (metrics.json parses, every .npy loads, a map
file loads and checks its CRC, CSV lines are complete), and the command is run
again to completion and compared with the reference (S.npy equal, map scores
equal, loop closures equal).  A case *survives* when both hold.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import re
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import RESULTS, TOPOLOC

KILLS_PER_COMMAND = 8
SEED = 20261123


def _commands(route: Path, vocab: Path, out: Path) -> dict[str, list[str]]:
    noon, dusk, morning = route / "noon", route / "dusk", route / "morning"
    return {
        "evaluate": [str(TOPOLOC), "evaluate", "--method", "coocmap", "--map", str(noon), "--query", str(dusk),
                     "--vocab", str(vocab), "--tolerance", "0:2", "--out", str(out / "run"), "--quiet"],
        "map build": [str(TOPOLOC), "map", "build", "--method", "fabmap2", "--map", str(noon), "--map",
                      str(morning), "--vocab-train", str(morning), "--vocab-words", "300", "--out",
                      str(out / "route.tlm"), "--quiet"],
        "slam": [str(TOPOLOC), "slam", str(route / "loop"), "--vocab-train", str(morning), "--vocab-words", "300",
                 "--out", str(out / "slam"), "--min-gap", "5", "--quiet"],
    }


def _check_files(out: Path) -> list[str]:
    """Problems with the files a killed run left (empty list: all whole and valid)."""
    from topoloc.errors import TopolocError
    from topoloc.maps import Map

    problems = []
    for f in out.rglob("*"):
        if not f.is_file() or any(part.startswith(".") for part in f.relative_to(out).parts):
            continue  # hidden staging or temporary files are never results
        try:
            if f.suffix == ".json":
                json.loads(f.read_text())
            elif f.suffix == ".npy":
                np.load(f, allow_pickle=False)
            elif f.suffix == ".tlm":
                Map.load(f)
            elif f.suffix == ".csv":
                text = f.read_text()
                rows = list(csv.reader(text.splitlines()))
                if (text and not text.endswith("\n")) or any(len(r) != len(rows[0]) for r in rows):
                    raise ValueError("incomplete line")
        except (ValueError, OSError, TopolocError) as exc:
            problems.append(f"{f.name}: {exc}")
    return problems


def _result(name: str, out: Path, route: Path) -> Any:
    """What a finished run produced, to compare with the reference."""
    if name == "evaluate":
        return np.load(out / "run" / "S.npy")
    if name == "map build":
        from topoloc.maps import Map

        return Map.load(out / "route.tlm").similarity(route / "dusk")
    return (out / "slam" / "loop_closures.csv").read_text()


def _same(a: Any, b: Any) -> bool:
    return bool(np.array_equal(a, b)) if isinstance(a, np.ndarray) else a == b


# -- the families of issue #26: bad input and faults, each case run as a user would --------------------------
FAMILIES = {
    "data loss": "a user's files are never destroyed, a map update is never lost",
    "silent wrong": "no result that looks right but is not: refused, or said in one warning line",
    "hangs": "nothing waits forever: a bad input or an unreachable scheduler ends in one line",
    "bombs": "an input that would take all memory is refused before it is decoded",
    "tracebacks": "bad input is one line `topoloc: error: ...`, exit 2, never a traceback",
    "names": "file and folder names of any characters work, and are text in the HTML page",
    "security": "a link or file planted in a shared folder is never followed; names in places.csv stay inside "
                "their folder; a private map stays private",
    "determinism": "the same inputs give byte-identical lines and S, whatever else runs on the machine",
    "configuration": "a configuration file is untrusted input: bounded, typed, one line naming the setting and "
                     "the file; flags always win",
    "misleading": "the message names what is wrong and where, before the work; what a user asked for is done",
    "live inputs": "a bad frame of a camera or stream is skipped and counted and the stream goes on; every source "
                   "decodes a frame by one rule; `frame` is the frame's number in its input",
    "conventions": "-h/--help, -V, -q/-v before and after the command, usage naming what is needed, one error "
                   "style (`topoloc: error: ...`, exit 2) for every error, flags of the command typed",
}
CASE_TIMEOUT_S = 120
ODD = "a b ü 'q\" <script>alert(1) <!--<script> &amp;\nline"


def _run(args: list[str], env: dict[str, str], timeout: float = CASE_TIMEOUT_S,
         memory_bytes: int | None = None) -> tuple[int | None, str, str, float]:
    """(exit status or None if it ran past ``timeout``, stdout, stderr, seconds) of ``topoloc ARGS``."""

    def limit() -> None:  # pragma: no cover - runs in the child
        if memory_bytes is not None:
            import resource

            resource.setrlimit(resource.RLIMIT_AS, (memory_bytes, memory_bytes))

    t0 = time.perf_counter()
    try:
        r = subprocess.run([str(TOPOLOC), *args], capture_output=True, text=True, env=env, timeout=timeout,
                           preexec_fn=limit if memory_bytes else None)
    except subprocess.TimeoutExpired:
        return None, "", "", time.perf_counter() - t0
    return r.returncode, r.stdout, r.stderr, time.perf_counter() - t0


def _one_line_error(rc: int | None, err: str, *needles: str) -> str:
    """"" when the run refused with one error line holding ``needles``; else what went wrong."""
    if rc is None:
        return f"still running after {CASE_TIMEOUT_S} s"
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    if rc != 2 or "Traceback" in err or not lines or not lines[-1].startswith("topoloc: error:"):
        return f"exit {rc}: {(lines or ['(no message)'])[-1][:160]}"
    missing = [n for n in needles if n not in lines[-1]]
    return f"message lacks {missing}: {lines[-1][:160]}" if missing else ""


def _warnings(err: str, needle: str) -> list[str]:
    return [ln for ln in err.splitlines() if needle in ln]


def _copy_tour(src: Path, dst: Path, rename: Callable[[int, str], str] = lambda k, n: n) -> Path:
    dst.mkdir(parents=True)
    rows = list(csv.DictReader((src / "places.csv").open(newline="")))
    for k, row in enumerate(rows):
        new = rename(k, row["image"])
        shutil.copy(src / row["image"], dst / new)
        row["image"] = new
    with (dst / "places.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return dst


def _video(path: Path, tour: Path, damage: str = "") -> Path:
    import cv2

    imgs = [cv2.imread(str(p)) for p in sorted(tour.glob("*.jpg"))]
    h, w = imgs[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (w, h))
    for img in imgs * 2:
        writer.write(img)
    writer.release()
    if damage:
        data = bytearray(path.read_bytes())
        chunks, at = [], data.find(b"00dc")
        while at >= 0:
            if data[at + 8:at + 10] == b"\xff\xd8":
                chunks.append(at)
            at = data.find(b"00dc", at + 4)
        if damage == "frame":
            data[chunks[4] + 208:chunks[4] + 608] = bytes(400)
        else:
            data = data[:chunks[len(chunks) // 2] + 50]
        path.write_bytes(bytes(data))
    return path


def _png_bomb(path: Path, side: int) -> Path:
    """A PNG whose header declares ``side`` x ``side`` grey pixels, with one compressed row of data."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(bytes(side + 1)))
                     + chunk(b"IEND", b""))
    return path


def family_cases(work: Path, route: Path, env: dict[str, str]) -> list[dict[str, Any]]:
    """Run each case of :data:`FAMILIES`; a row per case: family, case, held, seconds, detail."""
    rows: list[dict[str, Any]] = []
    noon, dusk = route / "noon", route / "dusk"
    seq = ["--method", "seqslam", "--param", "ds=3", "--quiet"]

    def case(family: str, name: str, check: Callable[[], str]) -> None:
        t0 = time.perf_counter()
        try:
            detail = check()
        except Exception as exc:  # a case that cannot even be set up did not hold
            detail = f"{type(exc).__name__}: {exc}"
        rows.append({"family": family, "case": name, "held": not detail, "seconds": round(time.perf_counter() - t0, 1),
                     "detail": detail})
        print(json.dumps(rows[-1]), flush=True)

    tlm = work / "fam.tlm"
    rc, _, err, _ = _run(["map", "build", "--map", str(noon), "--out", str(tlm), *seq], env)
    if rc != 0:
        raise SystemExit(f"map build for the family cases failed: {err}")

    # -- data loss --
    def out_folder_with_user_files() -> str:
        out = work / "dl_eval"
        out.mkdir()
        (out / "thesis.tex").write_text("years of work")
        rc, _, err, _ = _run(["evaluate", "--map", str(noon), "--query", str(dusk), "--out", str(out), *seq], env)
        if not (out / "thesis.tex").is_file():
            return f"exit {rc}: the user's file in --out is gone"
        return "" if rc in (0, 2) and "Traceback" not in err else f"exit {rc}"

    def map_out_over_a_user_file() -> str:
        notes = work / "notes.tlm"
        notes.write_text("my notes")
        rc, _, err, _ = _run(["map", "build", "--map", str(noon), "--out", str(notes), *seq], env)
        if notes.read_text(errors="replace") != "my notes":
            return f"exit {rc}: a file that is not a map was overwritten"
        return _one_line_error(rc, err, str(notes))

    def report_out_with_user_files() -> str:
        run = work / "dl_run"
        rc, _, _, _ = _run(["evaluate", "--map", str(noon), "--query", str(dusk), "--out", str(run), *seq], env)
        out = work / "dl_report"
        out.mkdir()
        (out / "report.md").write_text("my own report")
        rc, _, err, _ = _run(["report", str(run), "--out", str(out)], env)
        if (out / "report.md").read_text() != "my own report":
            return f"exit {rc}: the user's report.md in --out was overwritten"
        return "" if "Traceback" not in err else "a traceback"

    def concurrent_map_adds() -> str:
        m = work / "dl_concurrent.tlm"
        shutil.copy(tlm, m)
        tours = [_copy_tour(dusk, work / "dl_tour_a"), _copy_tour(route / "morning", work / "dl_tour_b")]
        procs = [subprocess.Popen([str(TOPOLOC), "map", "add", str(m), str(t), "--quiet"], env=env,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True) for t in tours]
        codes = [p.wait(timeout=CASE_TIMEOUT_S) for p in procs]
        from topoloc.maps import Map

        names = [t["name"] for t in Map.load(m).tours]
        added = sum(c == 0 for c in codes)
        if len(names) - 1 != added:
            return f"{added} of 2 adds reported success but the map holds {names}: an update was lost"
        return ""

    case("data loss", "evaluate --out on a folder holding a user's file keeps it", out_folder_with_user_files)
    case("data loss", "map build --out on a file that is not a map refuses", map_out_over_a_user_file)
    case("data loss", "report --out on a folder holding a user's report.md keeps it", report_out_with_user_files)
    case("data loss", "two map adds at once: both tours kept, or one refused", concurrent_map_adds)

    # -- silent wrong --
    def calibrate_on_own_tour() -> str:
        m = work / "sw_own.tlm"
        shutil.copy(tlm, m)
        rc, _, err, _ = _run(["map", "calibrate", str(m), "--query", str(noon), "--quiet"], env)
        return _one_line_error(rc, err, "own tour", str(m))

    def calibrate_no_threshold() -> str:
        m = work / "sw_none.tlm"
        shutil.copy(tlm, m)
        n = len(list(dusk.glob("*.jpg")))
        wrong = _copy_tour(dusk, work / "sw_wrong")
        rows_ = list(csv.DictReader((wrong / "places.csv").open(newline="")))
        (wrong / "places.csv").write_text("image,place\n" + "".join(
            f"{r['image']},{(int(r['place']) + n // 2) % n}\n" for r in rows_))
        rc, out, err, _ = _run(["map", "calibrate", str(m), "--query", str(wrong), "--tolerance", "0:0",
                                "--precision", "1", "--quiet"], env)
        if rc != 0:
            return f"exit {rc}: {err.strip()[-160:]}"
        try:
            cal = json.loads(out, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
        except ValueError as exc:
            return f"output is not JSON ({exc})"
        if len(_warnings(err, "accepts no localisation")) != 1:
            return "no single warning line"
        return "" if cal["threshold"] is None else f"threshold {cal['threshold']}"

    def damaged_video(kind: str) -> Callable[[], str]:
        def check() -> str:
            video = _video(work / f"sw_{kind}.avi", noon, damage=kind)
            rc, _, err, _ = _run(["map", "build", "--map", str(video), "--out", str(work / f"sw_{kind}.tlm"),
                                  *seq], env)
            return _one_line_error(rc, err, video.name, "frame")
        return check

    def places_csv_drops_images() -> str:
        q = _copy_tour(dusk, work / "sw_partial")
        lines = (q / "places.csv").read_text().splitlines()
        (q / "places.csv").write_text("\n".join(lines[:6]) + "\n")
        rc, _, err, _ = _run(["evaluate", "--map", str(noon), "--query", str(q), "--out", str(work / "sw_pe"),
                              *seq[:-1]], env)
        found = _warnings(err, "not in places.csv")
        return "" if rc == 0 and len(found) == 1 else f"exit {rc}, {len(found)} warning lines"

    def query_is_map_tour() -> str:
        rc, _, err, _ = _run(["evaluate", "--map", str(noon), "--query", str(noon), "--out", str(work / "sw_self"),
                              *seq[:-1]], env)
        found = _warnings(err, "own images")
        return "" if rc == 0 and len(found) == 1 else f"exit {rc}, {len(found)} warning lines"

    case("silent wrong", "map calibrate on the map's own tour refuses", calibrate_on_own_tour)
    case("silent wrong", "map calibrate reaching no threshold prints JSON null and warns", calibrate_no_threshold)
    case("silent wrong", "MJPG video with a damaged frame: map build stops naming file and frame",
         damaged_video("frame"))
    case("silent wrong", "truncated video: map build stops naming file and frame", damaged_video("truncated"))
    case("silent wrong", "places.csv leaving images out: one warning line", places_csv_drops_images)
    case("silent wrong", "evaluate with the query equal to a map tour: one warning line", query_is_map_tour)

    # -- hangs --
    def fifo_video() -> str:
        fifo = work / "hang.avi"
        os.mkfifo(fifo)
        rc, _, err, _ = _run(["map", "build", "--map", str(fifo), "--out", str(work / "hang.tlm"), *seq], env,
                             timeout=60)
        return _one_line_error(rc, err, "hang.avi")

    def fifo_places_csv() -> str:
        q = _copy_tour(dusk, work / "hang_csv")
        (q / "places.csv").unlink()
        os.mkfifo(q / "places.csv")
        rc, _, err, _ = _run(["evaluate", "--map", str(noon), "--query", str(q), "--out", str(work / "hang_o"),
                              *seq], env, timeout=60)
        if rc is None:
            return "still running after 60 s"
        # A sidecar that is not a regular file may be ignored (exit 0) or refused (one line): never waited on.
        return "" if rc == 0 and "Traceback" not in err else _one_line_error(rc, err, "places.csv")

    def unreachable_scheduler() -> str:
        rc, _, err, secs = _run(["evaluate", "--map", str(noon), "--query", str(dusk), "--out", str(work / "hang_s"),
                                 "--scheduler", "tcp://127.0.0.1:9", "--scheduler-timeout", "3", *seq], env,
                                timeout=60)
        problem = _one_line_error(rc, err, "127.0.0.1:9")
        return problem or ("" if secs < 30 else f"took {secs:.0f} s for a 3 s timeout")

    case("hangs", "a named pipe as the video: one line, no wait", fifo_video)
    case("hangs", "a named pipe as places.csv: one line, no wait", fifo_places_csv)
    case("hangs", "unreachable --scheduler with --scheduler-timeout 3: one line within 30 s", unreachable_scheduler)

    # -- bombs --
    def png_bomb(side: int) -> Callable[[], str]:
        def check() -> str:
            q = _copy_tour(dusk, work / f"bomb_{side}")
            first = sorted(q.glob("*.jpg"))[0]
            bomb = _png_bomb(first.with_suffix(".png"), side)
            first.unlink()
            (q / "places.csv").write_text((q / "places.csv").read_text().replace(first.name, bomb.name))
            rc, _, err, _ = _run(["evaluate", "--map", str(noon), "--query", str(q), "--out",
                                  str(work / f"bomb_o{side}"), *seq], env, memory_bytes=3 * 2**30)
            return _one_line_error(rc, err, bomb.name)
        return check

    case("bombs", "PNG declaring 30000 x 30000 pixels (0.9 GB decoded) in a query folder", png_bomb(30000))
    case("bombs", "PNG declaring 100000 x 100000 pixels in a query folder", png_bomb(100000))

    # -- tracebacks --
    def numbers() -> str:
        bad = []
        for args, needle in (
                (["cache", "clean", "--cache-dir", str(work / "c"), "--older-than", "nan"], "--older-than"),
                (["cache", "clean", "--cache-dir", str(work / "c"), "--max-size", "inf"], "size"),
                (["synth", str(work / "s"), "--hours", "nan"], "--hours"),
                (["map", "calibrate", str(tlm), "--query", str(dusk), "--precision", "nan"], "--precision"),
                (["map", "calibrate", str(tlm), "--query", str(dusk), "--tolerance", "0:nan"], "--tolerance"),
                (["slam", str(noon), "--out", str(work / "sl"), "--threshold", "inf"], "--threshold"),
                (["show-match", str(next(dusk.glob("*.jpg"))), "--map", str(noon), "--method", "seqslam", "--out",
                  str(work / "sm.png"), "--tolerance", "-1"], "--tolerance"),
                (["bench", "coocmap", "--locations", "0"], "--locations"),
                (["bench", "coocmap", "--tours", "-1"], "--tours"),
                (["bench", "fabmap2", "--words", "0"], "--words"),
                (["evaluate", "--map", str(noon), "--query", str(dusk), "--out", str(work / "n"), "--every-s", "inf",
                  *seq], "--every-s"),
        ):
            rc, _, err, _ = _run(args, env, timeout=60)
            problem = _one_line_error(rc, err, needle)
            if problem:
                bad.append(f"{' '.join(args[:2])} {args[-2:]}: {problem}")
        return "; ".join(bad)

    def report_other_shape() -> str:
        run = work / "tb_run"
        run.mkdir()
        (run / "metrics.json").write_text('{"method": "bow", "auc": "high"}')
        (run / "pr.csv").write_text("precision,recall\n1,0\n")
        rc, _, err, _ = _run(["report", str(run), "--out", str(work / "tb_rep")], env)
        return _one_line_error(rc, err, "metrics.json")

    case("tracebacks", "nan, inf, -1, 0 to 11 numeric options: one line each", numbers)
    case("tracebacks", "report of a metrics.json of another shape: one line naming it", report_other_shape)

    # -- names --
    def odd_names() -> str:
        maps = _copy_tour(noon, work / f"map {ODD}", lambda k, n: f"{k:02d} {ODD}.jpg")
        query = _copy_tour(dusk, work / f"query {ODD}", lambda k, n: f"{k:02d} {ODD}.jpg")
        page = work / f"page {ODD}.html"
        rc, _, err, _ = _run(["evaluate", "--map", str(maps), "--query", str(query), "--out", str(work / f"o {ODD}"),
                              "--html", str(page), *seq], env)
        if rc != 0:
            return f"evaluate exit {rc}: {err.strip()[-160:]}"
        text = page.read_text()
        if "<script>alert" in text or "<!--" in text or text.count("<script") != text.count("</script>"):
            return "a name reached the HTML page as markup"
        m = work / f"m {ODD}.tlm"
        rc, _, err, _ = _run(["map", "build", "--map", str(maps), "--out", str(m), *seq], env)
        if rc != 0:
            return f"map build exit {rc}: {err.strip()[-160:]}"
        rc, _, err, _ = _run(["localize", str(m), str(query), "--out", str(work / f"l {ODD}.jsonl"), "--quiet"], env)
        return "" if rc == 0 else f"localize exit {rc}: {err.strip()[-160:]}"

    case("names", "folder and image names with spaces, unicode, quotes, <script>, a newline: evaluate, "
                  "--html, map build, localize", odd_names)
    campaign3_cases(work, route, env, case, tlm)
    campaign4_cases(work, route, env, case, tlm)
    return rows


# -- the families of issue #41: security, determinism, configuration files, misleading messages ------------
ALIAS_BOMB = "".join(f"{x}: &{x} [{', '.join([f'*{p}'] * 9) if p else ', '.join(['x'] * 9)}]\n"
                     for p, x in zip(["", *"abcdefgh"], "abcdefghi", strict=True))


def _busy(n: int) -> list[subprocess.Popen[bytes]]:
    """``n`` processes spinning on the cores (ended by the caller, by their ids)."""
    import sys

    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def _stop(procs: list[subprocess.Popen[bytes]]) -> None:
    for p in procs:
        p.kill()
        p.wait()


def plain_copy(src: Path, dst: Path, rename: dict[int, str] | None = None) -> list[Path]:
    """The images of ``src`` in ``dst`` without places.csv (natural order), the ``k``-th renamed ``rename[k]``.

    Also what tests/cli/test_cli_campaign3.py builds its folders with.
    """
    dst.mkdir(parents=True)
    out = []
    for k, p in enumerate(sorted(src.glob("*.jpg"))):
        out.append(dst / (rename or {}).get(k, p.name))
        shutil.copy(p, out[-1])
    return out


def campaign3_cases(work: Path, route: Path, env: dict[str, str], case: Callable[[str, str, Callable[[], str]], None],
                    tlm: Path) -> None:
    """The cases of issue #41 (and more of each family), run as a user would."""
    noon, dusk, morning = route / "noon", route / "dusk", route / "morning"
    seq = ["--method", "seqslam", "--param", "ds=3", "--quiet"]
    vocab = work / "c3_vocab.tlv"
    rc, _, err, _ = _run(["vocab", "train", str(morning), "--words", "200", "--out", str(vocab), "--quiet"], env)
    if rc != 0:
        raise SystemExit(f"vocab train for the campaign cases failed: {err}")
    cooc = work / "c3_cooc.tlm"
    _run(["map", "build", "--method", "coocmap", "--map", str(noon), "--vocab", str(vocab), "--out", str(cooc),
          "--quiet"], env)
    _run(["map", "calibrate", str(cooc), "--query", str(morning), "--sequence", "3", "--precision", "0.5",
          "--quiet"], env)

    def victim(name: str) -> Path:
        v = work / f"victim_{name}"
        v.mkdir()
        (v / "thesis.tex").write_text("years of work")
        return v

    # -- security --
    def planted_store_link(target: str) -> Callable[[], str]:
        def check() -> str:
            v = victim(f"store_{target}")
            shared = work / f"shared_cache_{target}"
            shared.mkdir()
            shared.chmod(0o1777)  # a cache folder every user may write to
            (shared / "features" / "sift-x").mkdir(parents=True)
            link = shared / "features" / "sift-x" / "store"
            link.symlink_to(v if target == "folder" else v.parent)
            if target == "vocab":
                (shared / "vocab").mkdir()
                (shared / "vocab" / "v.tlv").symlink_to(v / "thesis.tex")
            rc, _, err, _ = _run(["cache", "clean", "--all", "--cache-dir", str(shared)], env)
            if not (v / "thesis.tex").is_file():
                return f"exit {rc}: the victim's folder outside the cache is gone"
            return "" if rc == 0 else f"exit {rc}: {err.strip()[-160:]}"
        return check

    def planted_user_folder() -> str:
        v = victim("userdir")
        shared = work / "shared_cache_user"
        shared.mkdir()
        shared.chmod(0o777)
        (shared / f"user-{os.geteuid()}").symlink_to(v)
        rc, _, err, _ = _run(["evaluate", "--map", str(noon), "--query", str(dusk), "--out", str(work / "sec_u"),
                              "--cache-dir", str(shared), "--method", "bow", "--vocab", str(vocab), "--quiet"], env)
        if sorted(p.name for p in v.iterdir()) != ["thesis.tex"]:
            return "the cache was written through the planted link"
        return _one_line_error(rc, err, f"user-{os.geteuid()}")

    def places_outside(name: str) -> Callable[[], str]:
        def check() -> str:
            secret = work / "secret.jpg"
            shutil.copy(sorted(dusk.glob("*.jpg"))[0], secret)
            q = _copy_tour(dusk, work / f"sec_q_{len(list(work.iterdir()))}")
            bad = str(secret) if name == "absolute" else "../secret.jpg"
            rows = list(csv.DictReader((q / "places.csv").open(newline="")))
            (q / "places.csv").write_text("image,place\n" + "".join(f"{r['image']},{r['place']}\n" for r in rows[1:])
                                          + f"{bad},0\n")
            page = work / f"sec_{name}.html"
            rc, _, err, _ = _run(["evaluate", "--map", str(noon), "--query", str(q), "--out", str(work / f"sec_{name}"),
                                  "--html", str(page), *seq], env)
            if page.exists():
                return f"exit {rc}: a page was written with the image from outside the query folder"
            return _one_line_error(rc, err, "outside the traverse's folder")
        return check

    def private_map(mode: int, command: str) -> Callable[[], str]:
        def check() -> str:
            m = work / f"sec_{mode:o}_{command}.tlm"
            shutil.copy(cooc, m)
            m.chmod(mode)
            args = (["map", "add", str(m), str(dusk), "--quiet"] if command == "add" else
                    ["map", "calibrate", str(m), "--query", str(dusk), "--quiet"])
            rc, _, err, _ = _run(args, env)
            now = m.stat().st_mode & 0o777
            if rc != 0:
                return f"exit {rc}: {err.strip()[-160:]}"
            return "" if now == mode else f"mode {mode:o} became {now:o}"
        return check

    case("security", "a link planted as features/<key>/store in a shared cache: cache clean --all keeps what "
                     "it points at", planted_store_link("folder"))
    case("security", "links planted as a store and as a cached vocabulary: cache clean --all keeps their targets",
         planted_store_link("vocab"))
    case("security", "the per-user folder of a shared cache planted as a link: one line, nothing written through it",
         planted_user_folder)
    case("security", "places.csv naming ../secret.jpg: evaluate --html refuses in one line, no page",
         places_outside("parent"))
    case("security", "places.csv naming an absolute path: refused in one line, no page", places_outside("absolute"))
    case("security", "map add on a 0600 map keeps it 0600", private_map(0o600, "add"))
    case("security", "map calibrate on a 0640 map keeps it 0640", private_map(0o640, "calibrate"))

    # -- determinism --
    def same_lines(args: list[str], n_runs: int, beside: int) -> str:
        ref = work / f"det_ref_{len(list(work.iterdir()))}.jsonl"
        rc, _, err, _ = _run([*args, "--out", str(ref)], env)
        if rc != 0:
            return f"exit {rc}: {err.strip()[-160:]}"
        want = ref.read_bytes()
        differ = 0
        for k in range(n_runs):
            busy = _busy(beside)
            outs = [ref.with_name(f"{ref.stem}_{k}_{j}.jsonl") for j in range(2)]
            try:
                procs = [subprocess.Popen([str(TOPOLOC), *args, "--out", str(o)], env=env, stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL) for o in outs]
                codes = [p.wait(timeout=CASE_TIMEOUT_S) for p in procs]
            finally:
                _stop(busy)
            if any(codes):
                return f"exit {codes} in run {k}"
            differ += sum(o.read_bytes() != want for o in outs)
        return "" if not differ else f"{differ} of {2 * n_runs} runs beside busy processes gave other lines"

    def same_S(args: list[str], n_runs: int) -> str:
        outs = [work / f"det_S_{len(list(work.iterdir()))}_{j}" for j in range(2 * n_runs + 1)]
        rc, _, err, _ = _run([*args, "--out", str(outs[0])], env)
        if rc != 0:
            return f"exit {rc}: {err.strip()[-160:]}"
        for k in range(n_runs):
            busy = _busy(1)
            try:
                procs = [subprocess.Popen([str(TOPOLOC), *args, "--out", str(o)], env=env, stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL) for o in outs[1 + 2 * k:3 + 2 * k]]
                for p in procs:
                    p.wait(timeout=CASE_TIMEOUT_S)
            finally:
                _stop(busy)
        ref = np.load(outs[0] / "S.npy")
        bad = sum(not np.array_equal(np.load(o / "S.npy"), ref) for o in outs[1:])
        return "" if not bad else f"S differed in {bad} of {2 * n_runs} runs"

    case("determinism", "Cooc-Map, calibrated map, --sequence 3: localize lines of 6 runs, two at a time beside a "
                        "busy process", lambda: same_lines(["localize", str(cooc), str(dusk), "--quiet"], 3, 1))
    case("determinism", "Cooc-Map --sequence 0 --top-k 12 (every place's score): 4 runs beside two busy processes",
         lambda: same_lines(["localize", str(cooc), str(dusk), "--sequence", "0", "--top-k", "12", "--quiet"], 2, 2))
    case("determinism", "Cooc-Map --prefetch 0 and the default give the same lines",
         lambda: same_lines(["localize", str(cooc), str(dusk), "--prefetch", "0", "--quiet"], 1, 1))
    case("determinism", "evaluate Cooc-Map --sequence 3: S.npy of 4 runs, two at a time beside a busy process",
         lambda: same_S(["evaluate", "--map", str(noon), "--query", str(dusk), "--method", "coocmap", "--vocab",
                         str(vocab), "--sequence", "3", "--quiet"], 2))
    case("determinism", "evaluate bag of words --sequence 3: S.npy of 4 runs beside a busy process",
         lambda: same_S(["evaluate", "--map", str(noon), "--query", str(dusk), "--method", "bow", "--vocab",
                         str(vocab), "--sequence", "3", "--quiet"], 2))

    # -- configuration files --
    def config_error(name: str, text: str, *needles: str, seconds: float = 10) -> Callable[[], str]:
        def check() -> str:
            f = work / name
            f.write_text(text)
            rc, _, err, secs = _run(["evaluate", "--config", str(f)], env, memory_bytes=2 * 2**30)
            if len(err) > 2000:
                return f"an error of {len(err):,} characters"
            problem = _one_line_error(rc, err, str(f), *needles)
            return problem or ("" if secs < seconds else f"took {secs:.0f} s")
        return check

    base = f"method = 'bow'\nmaps = ['{noon}']\nquery = '{dusk}'\nout = '{work / 'cfg_out'}'\n"
    for k, (label, text, needle) in enumerate((
            ("maps = 5", "maps = 5", "--map must be a list"),
            ("features = \"sift\"", "features = 'sift'", "features must be a table"),
            ("params = [1, 2]", "params = [1, 2]", "--param must be a table"),
            ("method = [...]", "method = ['bow', 'seqslam']", "--method must be text"),
            ("recall_at = 5", "recall_at = 5", "--recall-at must be text"),
            ("cache_dir = 7", "[execution]\ncache_dir = 7", "--cache-dir must be a path"),
            ("sequence.length = 'ten'", "[sequence]\nlength = 'ten'", "--sequence must be a whole number"),
            ("top_k = true", "top_k = true", "--top-k must be a whole number"),
            ("vocabulary.train = [1]", "[vocabulary]\ntrain = [1]", "--vocab-train must be a path"))):
        case("configuration", f"TOML {label}: one line naming the flag and the file",
             config_error(f"cfg_{k}.toml", text + "\n", needle))
    n = 50_000
    case("configuration", "JSON nested 50,000 deep: one line", config_error("deep.json", "[" * n + "]" * n, "nested"))
    case("configuration", "TOML nested 50,000 deep: one line", config_error("deep.toml", "a = " + "[" * n + "]" * n,
                                                                            "nested"))
    case("configuration", "YAML nested 50,000 deep: one line", config_error("deep.yaml", "a: " + "[" * n + "]" * n,
                                                                            "nested"))
    case("configuration", "YAML alias bomb under maps (10^9 values): one line within 10 s",
         config_error("bomb_maps.yaml", ALIAS_BOMB + "maps: *i\n", "aliases"))
    case("configuration", "YAML with two documents: one line", config_error("two.yaml", "method: bow\n---\nx: 1\n",
                                                                            "several YAML documents"))
    case("configuration", "a 2 MiB JSON configuration: one line",
         config_error("big.json", json.dumps({"params": {"x": "y" * (2 << 20)}}), "larger than"))

    def tolerance_flag_wins() -> str:
        f = work / "tol.toml"
        f.write_text(base.replace("'bow'", "'seqslam'") + "params = {ds = 3}\n[ground_truth]\ntolerance_m = '0:25'\n")
        rc, _, err, _ = _run(["evaluate", "--config", str(f), "--tolerance", "0:0", "--out", str(work / "tol_a"),
                              "--quiet"], env)
        rc2, _, err2, _ = _run(["evaluate", "--map", str(noon), "--query", str(dusk), "--tolerance", "0:0", "--out",
                                str(work / "tol_b"), *seq], env)
        if rc or rc2:
            return f"exit {rc}/{rc2}: {(err or err2).strip()[-160:]}"
        a = json.loads((work / "tol_a" / "metrics.json").read_text())
        b = json.loads((work / "tol_b" / "metrics.json").read_text())
        return "" if a["run"]["ground_truth"] == b["run"]["ground_truth"] else \
            f"ground truth {a['run']['ground_truth']!r}, flag alone {b['run']['ground_truth']!r}"

    def metrics_json_outputs() -> str:
        run = work / "runs" / "bow"
        rc, _, err, _ = _run(["evaluate", "--map", str(noon), "--query", str(dusk), "--out", str(run), *seq], env)
        before = (run / "S.npy").read_bytes()
        rc, _, err, _ = _run(["evaluate", "--config", str(run / "metrics.json"), "--tolerance", "0:3"], env)
        if not (run / "S.npy").is_file() or (run / "S.npy").read_bytes() != before:
            return f"exit {rc}: the run the configuration was read from was replaced"
        return _one_line_error(rc, err, "--out is needed")

    def alternative_flag(flag: list[str], setting: str) -> Callable[[], str]:
        def check() -> str:
            f = work / f"alt_{setting.replace('.', '_')}.toml"
            body = {"vocabulary.file": f"[vocabulary]\nfile = '{vocab}'\n", "maps": ""}[setting]
            f.write_text(base + body)
            rc, _, err, _ = _run(["evaluate", "--config", str(f), *flag, "--out", str(work / f"alt_o_{setting}"),
                                  "--quiet"], env)
            return "" if rc == 0 else f"exit {rc}: {err.strip()[-160:]}"
        return check

    case("configuration", "--tolerance 0:0 over a file's ground_truth.tolerance_m: the flag's ground truth",
         tolerance_flag_wins)
    case("configuration", "evaluate --config RUN/metrics.json --tolerance 0:3 without --out: refused, RUN kept",
         metrics_json_outputs)
    case("configuration", "--vocab-train over a file's vocabulary.file: runs, no error about flags not given",
         alternative_flag(["--vocab-train", str(morning), "--vocab-words", "100"], "vocabulary.file"))
    case("configuration", "--map-file over a file's maps: runs, no error about flags not given",
         alternative_flag(["--map-file", str(cooc)], "maps"))

    # -- data loss, hangs, tracebacks: more cases of the same kinds --
    def config_out_holds_config() -> str:
        run = work / "dl_runs" / "seq"
        rc, _, err, _ = _run(["evaluate", "--map", str(noon), "--query", str(dusk), "--out", str(run), *seq], env)
        before = (run / "S.npy").read_bytes()
        rc, _, err, _ = _run(["evaluate", "--config", str(run / "metrics.json"), "--out", str(run.parent),
                              "--tolerance", "0:3"], env)
        if not (run / "S.npy").is_file() or (run / "S.npy").read_bytes() != before:
            return f"exit {rc}: the run holding the configuration was replaced"
        return _one_line_error(rc, err, "--out would replace the configuration file")

    def fifo_config() -> str:
        fifo = work / "hang_config.yaml"
        os.mkfifo(fifo)
        rc, _, err, _ = _run(["evaluate", "--config", str(fifo)], env, timeout=60)
        return _one_line_error(rc, err, str(fifo), "not a regular file")

    def dash_outputs() -> str:
        bad = []
        for args, needle in ((["localize", str(tlm), str(dusk), "--out", "-", "--top-k", "2", "--pairs-out", "-"],
                              "standard output"),
                             (["map", "build", "--map", str(noon), "--out", "-", *seq], "standard output"),
                             (["evaluate", "--config", str(work / "absent.toml")], "not found")):
            rc, _, err, _ = _run(args, env)
            problem = _one_line_error(rc, err, needle)
            if problem:
                bad.append(f"{args[0]}: {problem}")
        return "; ".join(bad)

    case("data loss", "evaluate --config RUN/metrics.json --out RUN's parent: refused, RUN kept",
         config_out_holds_config)
    case("hangs", "a named pipe as --config: one line, no wait", fifo_config)
    case("tracebacks", "'-' as a pairs file or a map, a missing --config: one line each", dash_outputs)

    # -- bombs, silent wrong, names: more cases of issue #41 --
    case("bombs", "441-byte YAML alias bomb in params.grid_x: one short line within 10 s (2 GiB limit)",
         config_error("bomb.yaml", ALIAS_BOMB + "params:\n  grid_x: *i\n", "aliases"))

    def special_image(kind: str) -> Callable[[], str]:
        def check() -> str:
            q = work / f"sw_special_{kind}"
            plain_copy(dusk, q)
            bad = q / "Image005.jpg"
            if kind == "fifo":
                os.mkfifo(bad)
            elif kind == "zero":
                bad.symlink_to("/dev/zero")
            else:
                bad.symlink_to(work / "nothing_here.jpg")
            rc, _, err, _ = _run(["localize", str(tlm), str(q), "--out", str(work / f"sw_{kind}.jsonl"), "--quiet"],
                                 env, timeout=60)
            return _one_line_error(rc, err, str(bad), "not a regular file")
        return check

    case("silent wrong", "a named pipe called Image005.jpg in a localize folder: refused, not skipped",
         special_image("fifo"))
    case("silent wrong", "a link to /dev/zero called Image005.jpg: refused, not skipped", special_image("zero"))
    case("silent wrong", "a dangling link called Image005.jpg: refused, not skipped", special_image("dangling"))

    def not_utf8() -> str:
        q = work / "names_latin1"
        plain_copy(dusk, q, {3: os.fsdecode(b"latin1 \xe9t\xe9 3.jpg")})
        problems = []
        for args in (["localize", str(tlm), str(q), "--out", str(work / "n8.jsonl"), "--quiet"],
                     ["evaluate", "--map", str(noon), "--query", str(q), "--out", str(work / "n8run"), "--html",
                      str(work / "n8.html"), "--tolerance", "0:20", *seq],
                     ["map", "build", "--map", str(q), "--out", str(work / "n8.tlm"), *seq]):
            rc, _, err, _ = _run(args, env)
            if rc != 0:
                problems.append(f"{args[0]} exit {rc}: {err.strip()[-100:]}")
        return "; ".join(problems)

    case("names", "an image name that is not UTF-8 (latin-1 bytes): localize, evaluate --html, map build",
         not_utf8)

    # -- misleading --
    def add_through_link() -> str:
        real = work / "mis_maps" / "real.tlm"
        real.parent.mkdir()
        shutil.copy(tlm, real)
        link = work / "mis_current.tlm"
        link.symlink_to(real)
        rc, _, err, _ = _run(["map", "add", str(link), str(morning), "--quiet"], env)
        if rc != 0:
            return f"exit {rc}: {err.strip()[-160:]}"
        if not link.is_symlink():
            return "the link was replaced by a file"
        rc, out, _, _ = _run(["map", "info", str(real), "--json"], env)
        return "" if len(json.loads(out)["tours"]) == 2 else "the linked map was not updated"

    def add_from_elsewhere() -> str:
        here = work / "mis_rel"
        here.mkdir()
        shutil.copytree(noon, here / "noon")
        r = subprocess.run([str(TOPOLOC), "map", "build", "--map", "noon", "--out", "m.tlm", *seq], cwd=here,
                           env=env, capture_output=True, text=True)
        if r.returncode:
            return f"map build exit {r.returncode}"
        rc, _, err, _ = _run(["map", "add", str(here / "m.tlm"), str(morning), "--quiet"], env)
        return "" if rc == 0 else f"exit {rc}: {err.strip()[-160:]}"

    def pairs_before_work() -> str:
        q = work / "mis_pairs"
        plain_copy(dusk, q, {4: "with space.jpg"})
        out = work / "mis_pairs.jsonl"
        rc, _, err, _ = _run(["localize", str(tlm), str(q), "--out", str(out), "--top-k", "2", "--pairs-out",
                              str(work / "mis_pairs.txt"), "--quiet"], env)
        if out.exists():
            return "refused only after frames were localised (lines written)"
        return _one_line_error(rc, err, "with space.jpg")

    def gt_shape_before_fit() -> str:
        gt = work / "mis_gt.npy"
        np.save(gt, np.ones((3, 3), bool))
        rc, _, err, _ = _run(["evaluate", "--map", str(noon), "--query", str(dusk), "--method", "seqslam",
                              "--ground-truth", str(gt), "--out", str(work / "mis_gt")], env)
        lines = [ln for ln in err.splitlines() if ln.strip()]
        if len(lines) > 1:
            return f"{len(lines)} lines on standard error before the refusal (the fit ran)"
        return _one_line_error(rc, err, str(gt), "shape")

    def report_unknown() -> str:
        run = work / "mis_old_run"
        _run(["evaluate", "--map", str(noon), "--query", str(dusk), "--out", str(run), "--method", "bow", "--vocab",
              str(vocab), "--quiet"], env)
        m = json.loads((run / "metrics.json").read_text())
        for key in ("features", "vocabulary", "spec"):
            m["run"].pop(key, None)
        (run / "metrics.json").write_text(json.dumps(m))
        rc, _, err, _ = _run(["report", str(run), "--out", str(work / "mis_rep")], env)
        if rc != 0:
            return f"exit {rc}: {err.strip()[-160:]}"
        text = "".join(p.read_text() for p in (work / "mis_rep").glob("*.md"))
        wrong = [w for w in ("full size", "preprocessing none", "| none |") if w in text]
        return f"shows {wrong} for settings the run did not record" if wrong or "unknown" not in text else ""

    def out_dash() -> str:
        rc, out, err, _ = _run(["localize", str(tlm), str(dusk), "--out", "-", "--quiet"], env)
        if rc != 0:
            return f"exit {rc}: {err.strip()[-160:]}"
        try:
            lines = [json.loads(x) for x in out.splitlines()]
        except ValueError:
            return "standard output holds more than the lines"
        return "" if len(lines) == len(list(dusk.glob("*.jpg"))) else f"{len(lines)} lines"

    def gif_rule() -> str:
        import cv2

        q = work / "mis_gif"
        files = plain_copy(dusk, q)
        gif = files[2].with_suffix(".gif")
        from PIL import Image

        Image.fromarray(cv2.cvtColor(cv2.imread(str(files[2])), cv2.COLOR_BGR2RGB)).save(gif)
        files[2].unlink()
        rc, _, _, _ = _run(["localize", str(tlm), str(q), "--out", str(work / "gif_a.jsonl"), "--quiet"], env)
        rc2, _, _, _ = _run(["localize", str(tlm), str(gif), "--out", str(work / "gif_b.jsonl"), "--quiet"], env)
        return "" if rc == rc2 == 0 else f"folder exit {rc}, named exit {rc2}"

    def empty_topic() -> str:
        try:
            from rosbags.rosbag1 import Writer
            from rosbags.typesys import Stores, get_typestore
        except ImportError:
            return "rosbags is not installed (pip install 'topoloc[ros]')"
        bag = work / "mis_empty.bag"
        with Writer(bag) as w:
            w.add_connection("/cam/image", "sensor_msgs/msg/Image", typestore=get_typestore(Stores.ROS1_NOETIC))
        rc, _, err, _ = _run(["localize", str(tlm), str(bag), "--out", str(work / "mis_empty.jsonl"), "--quiet"], env)
        return _one_line_error(rc, err, "/cam/image", "no messages", str(bag))

    case("misleading", "map add through a link to the map: the linked map updated, the link kept", add_through_link)
    case("misleading", "map add from another folder than map build's (tour named relative)", add_from_elsewhere)
    case("misleading", "localize --pairs-out with an image name holding a space: refused before the first frame",
         pairs_before_work)
    case("misleading", "a ground truth of the wrong shape: refused before the method's fit", gt_shape_before_fit)
    case("misleading", "report of a run without recorded settings says unknown", report_unknown)
    case("misleading", "localize --out -: the lines on standard output, nothing else", out_dash)
    case("misleading", "a GIF read in a folder as when named", gif_rule)
    case("misleading", "localize on a bag whose image topic has no messages: one line", empty_topic)


# -- the cases of issue #49: outputs, live streams, classes of campaign 3, conventions ------------------------
def _other_byte_order(src: Path, dst: Path) -> Path:
    """A topoloc container written again with its arrays in the other byte order (a big-endian machine's file)."""
    import struct
    import sys

    from topoloc.io.container import read_container, write_container

    data = src.read_bytes()
    header = json.loads(data[24:24 + struct.unpack_from("<Q", data, 12)[0]])
    meta, arrays = read_container(src, header["kind"])
    order = ">" if sys.byteorder == "little" else "<"
    swapped = {k: a.astype(a.dtype.newbyteorder(order)) if a.dtype.itemsize > 1 else a for k, a in arrays.items()}
    write_container(dst, header["kind"], header["kind_version"], swapped, meta)
    return dst


def campaign4_cases(work: Path, route: Path, env: dict[str, str], case: Callable[[str, str, Callable[[], str]], None],
                    tlm: Path) -> None:
    """The cases of issue #49 (and their neighbours), run as a user would."""
    import stat

    noon, dusk, morning = route / "noon", route / "dusk", route / "morning"
    seq = ["--method", "seqslam", "--param", "ds=3", "--quiet"]
    mine = b"years of work\n"
    vocab = work / "c4_vocab.tlv"
    rc, _, err, _ = _run(["vocab", "train", str(morning), "--words", "100", "--out", str(vocab), "--quiet"], env)
    if rc != 0:
        raise SystemExit(f"vocab train for the campaign-4 cases failed: {err}")
    run = work / "c4_run"
    _run(["evaluate", "--map", str(noon), "--query", str(dusk), "--out", str(run), *seq], env)

    def user_file(name: str) -> Path:
        f = work / "c4_user" / name
        f.parent.mkdir(exist_ok=True)
        f.write_bytes(mine)
        return f

    # -- data loss --
    def html_over(args_of: Callable[[Path], list[str]], name: str) -> Callable[[], str]:
        def check() -> str:
            f = user_file(name)
            rc, _, err, _ = _run(args_of(f), env)
            if f.read_bytes() != mine:
                return f"exit {rc}: the user's {name} was replaced"
            return _one_line_error(rc, err, str(f), "not an earlier output")
        return check

    def config_html() -> str:
        f = user_file(".bashrc")
        cfg = work / "c4_html.yaml"
        cfg.write_text(f"method: seqslam\nparams: {{ds: 3}}\nmaps: ['{noon}']\nquery: '{dusk}'\n"
                       f"out: '{work / 'c4_cfg_run'}'\nhtml: '{f}'\n")
        rc, _, err, _ = _run(["evaluate", "--config", str(cfg), "--quiet"], env)
        if f.read_bytes() != mine:
            return f"exit {rc}: the user's .bashrc was replaced by a page"
        return _one_line_error(rc, err, str(f), "not an earlier output")

    def out_link_to_a_run() -> str:
        target = work / "c4_runs" / "monday"
        target.parent.mkdir()
        _run(["evaluate", "--map", str(noon), "--query", str(dusk), "--out", str(target), *seq], env)
        link = work / "c4_current"
        link.symlink_to(target)
        rc, _, err, _ = _run(["evaluate", "--map", str(noon), "--query", str(dusk), "--out", str(link),
                              "--tolerance", "0:3", *seq], env)
        if rc != 0:
            return f"exit {rc}: {err.strip()[-160:]}"
        if not link.is_symlink():
            return "the link was replaced by a folder"
        debris = [p.name for p in (*work.iterdir(), *target.parent.iterdir()) if ".staging-" in p.name]
        if debris:
            return f"staging left behind: {debris}"
        ground = json.loads((target / "metrics.json").read_text())["run"]["ground_truth"]
        return "" if "0:3" in ground else "the run the link names was not updated"

    def links_to_a_users_file() -> str:
        bad = []
        for name, args_of in (
                ("localize --out", lambda o: ["localize", str(tlm), str(dusk), "--out", str(o), "--quiet"]),
                ("map build --out", lambda o: ["map", "build", "--map", str(noon), "--out", str(o), *seq]),
                ("vocab train --out", lambda o: ["vocab", "train", str(morning), "--words", "20", "--out", str(o),
                                                 "--quiet"]),
                ("evaluate --pairs-out", lambda o: ["evaluate", "--map", str(noon), "--query", str(dusk), "--out",
                                                    str(work / "c4_pairs_run"), "--top-k", "2", "--pairs-out",
                                                    str(o), *seq]),
                ("slam --html", lambda o: ["slam", str(noon), "--vocab", str(vocab), "--out", str(work / "c4_slam"),
                                           "--html", str(o), "--quiet"])):
            f = user_file(f"{name.replace(' ', '_')}.txt")
            link = work / f"c4_link_{name.replace(' ', '_')}"
            link.symlink_to(f)
            rc, _, err, _ = _run(args_of(link), env)
            problem = _one_line_error(rc, err, str(link))
            if f.read_bytes() != mine or not link.is_symlink():
                problem = "the user's file or the link was replaced"
            if problem:
                bad.append(f"{name}: {problem}")
        return "; ".join(bad)

    def dev_null() -> str:
        bad = []
        for args in (["localize", str(tlm), str(dusk), "--out", os.devnull, "--quiet"],
                     ["evaluate", "--map", str(noon), "--query", str(dusk), "--out", os.devnull, "--html", os.devnull,
                      *seq],
                     ["map", "build", "--map", str(noon), "--out", os.devnull, *seq],
                     ["vocab", "train", str(morning), "--words", "20", "--out", os.devnull, "--quiet"],
                     ["report", str(run), "--out", os.devnull]):
            rc, _, err, _ = _run(args, env)
            if rc != 0:
                bad.append(f"{' '.join(args[:2])}: exit {rc}: {err.strip()[-100:]}")
        if not stat.S_ISCHR(os.stat(os.devnull).st_mode):
            bad.append("/dev/null is no longer the null device")
        return "; ".join(bad)

    case("data loss", "evaluate --html notes.txt: refused, the file kept",
         html_over(lambda f: ["evaluate", "--map", str(noon), "--query", str(dusk), "--out", str(work / "c4_h"),
                              "--html", str(f), *seq], "notes.txt"))
    case("data loss", "html: ~/.bashrc in a --config file: refused, the file kept", config_html)
    case("data loss", "report --html draft.txt: refused, the file kept",
         html_over(lambda f: ["report", str(run), "--out", str(work / "c4_rep"), "--html", str(f)], "draft.txt"))
    case("data loss", "show-match --out on a user's PNG: refused, the photo kept",
         html_over(lambda f: ["show-match", str(next(dusk.glob("*.jpg"))), "--map", str(noon), "--out", str(f), *seq],
                   "photo.png"))
    case("data loss", "evaluate --out LINK to an earlier run: the linked run updated, the link kept, no staging left",
         out_link_to_a_run)
    case("data loss", "five outputs given as a link to a user's file: refused, file and link kept",
         links_to_a_users_file)
    case("data loss", "--out /dev/null (localize, evaluate with --html, map build, vocab train, report): "
                      "discarded, the device kept", dev_null)

    # -- live inputs --
    import cv2

    jpegs = [p.read_bytes() for p in sorted(dusk.glob("*.jpg"))]
    rng = np.random.default_rng(SEED)
    enormous = bytearray(jpegs[0])
    at = enormous.find(b"\xff\xc0")
    enormous[at + 5:at + 9] = bytes([0xEA, 0x60, 0xEA, 0x60])  # 60000 x 60000 announced
    bad_parts = {"random bytes": rng.integers(0, 256, 5000, dtype=np.uint8).tobytes(),
                 "an enormous JPEG": bytes(enormous), "a truncated JPEG": jpegs[1][: len(jpegs[1]) // 2]}

    def stream_with(kind: str) -> Callable[[], str]:
        def check() -> str:
            from topoloc.synth.stream import MjpegServer

            parts = [*jpegs[:3], bad_parts[kind], *jpegs[3:]]
            server = MjpegServer(parts, fps=4.0)
            out = work / f"c4_live_{kind.replace(' ', '_')}.jsonl"
            try:
                rc, stdout, err, _ = _run(["localize", str(tlm), server.url, "--out", str(out), "--quiet",
                                           "--prefetch", "0"], env)
            finally:
                server.close()
            if rc != 0:
                return f"exit {rc}: {err.strip()[-160:]}"
            summary = json.loads(stdout.strip().splitlines()[-1])
            lines = [json.loads(x) for x in out.read_text().splitlines()]
            frames = [x["frame"] for x in lines]
            if summary["frames_read"] != len(parts):
                return f"the stream stopped after {summary['frames_read']} of {len(parts)} frames"
            if 3 in frames:
                return "the bad part was answered as a frame"
            if not frames or max(frames) <= 3:
                return "no frame after the bad part was answered"
            if any(x["frame"] != int(x["image"].rsplit("#", 1)[1]) for x in lines):
                return "frame is not the frame's number in the stream"
            return "" if summary["frames_bad"] + summary["frames_skipped"] >= 1 else "the bad part was not counted"
        return check

    def one_rule() -> str:
        from topoloc.datasets.decode import read_image
        from topoloc.errors import TopolocError

        f = work / "c4_truncated.jpg"
        f.write_bytes(bad_parts["a truncated JPEG"])
        try:
            read_image(f)
        except TopolocError:
            pass
        else:
            return "a truncated JPEG file was decoded"
        ok, _ = cv2.imencode(".jpg", np.zeros((8, 8), np.uint8))
        return "" if ok else "no JPEG encoder"

    for kind in bad_parts:
        case("live inputs", f"an MJPEG stream with {kind} between good frames: localize goes on, the part skipped "
                            "and counted, frame = the frame's number", stream_with(kind))
    case("live inputs", "a truncated JPEG refused from a file as from a stream (one decoding rule)", one_rule)

    # -- classes of campaign 3 --
    def own_flags() -> str:
        bad = []
        for args, want in ((["localize", "--out", str(work / "l.jsonl")], "MAP_FILE"),
                           (["vocab", "train", str(morning), "--out", str(work / "v.tlv"), "--words", "0"], "--words"),
                           (["synth", str(work / "c4_s"), "--places", "0"], "--places"),
                           (["evaluate", "--map", str(noon), "--query", str(dusk), "--out", str(work / "c4_x"),
                             "--max-features", "0", *seq], "--max-features"),
                           (["evaluate"], "--map-file")):
            rc, _, err, _ = _run(args, env)
            problem = _one_line_error(rc, err, want)
            if not problem and re.search(r"\b[a-z]+_[a-z_]+\b", err.split(":", 2)[-1].replace(str(work), "")):
                problem = f"a field name in {err.strip()!r}"
            if not problem and args[0] == "localize" and "--map-file" in err:
                problem = "names --map-file, which localize does not take"
            if problem:
                bad.append(f"{' '.join(args[:2])}: {problem}")
        return "; ".join(bad)

    def special_inputs() -> str:
        fifo = work / "c4_fifo"
        os.mkfifo(fifo)
        bad = []
        for args, what in ((["evaluate", "--map", str(fifo), "--query", str(dusk), "--out", str(work / "c4_f"), *seq],
                            "named pipe"),
                           (["map", "info", str(fifo)], "named pipe"),
                           (["map", "info", "/dev/zero"], "character device"),
                           (["evaluate", "--map-file", str(tlm), "--query", str(dusk), "--out", str(work / "c4_f"),
                             "--cache-dir", str(fifo), "--quiet"], "named pipe"),
                           (["vocab", "train", str(fifo), "--out", str(work / "c4_v.tlv")], "named pipe"),
                           (["report", str(fifo), "--out", str(work / "c4_r")], "named pipe")):
            rc, _, err, _ = _run(args, env, timeout=60)
            problem = _one_line_error(rc, err, what)
            if problem or "does not exist" in err:
                bad.append(f"{' '.join(args[:2])}: {problem or err.strip()}")
        return "; ".join(bad)

    def duplicates() -> str:
        link = work / "c4_noon_link"
        link.symlink_to(noon)
        bad = []
        for args in (["map", "build", "--map", str(noon), "--map", str(link), "--out", str(work / "c4_d.tlm"), *seq],
                     ["evaluate", "--map", str(noon), "--map", str(noon), "--query", str(dusk), "--out",
                      str(work / "c4_d"), *seq],
                     ["show-match", str(next(dusk.glob("*.jpg"))), "--map", str(noon), "--map", str(noon), "--out",
                      str(work / "c4_d.png"), *seq],
                     ["vocab", "train", str(morning), str(morning), "--out", str(work / "c4_d.tlv")],
                     ["report", str(run), str(run), "--out", str(work / "c4_drep")]):
            rc, _, err, _ = _run(args, env)
            problem = _one_line_error(rc, err, "twice")
            if problem:
                bad.append(f"{' '.join(args[:2])}: {problem}")
        return "; ".join(bad)

    def byte_order() -> str:
        native = work / "c4_cooc.tlm"
        rc, _, err, _ = _run(["map", "build", "--method", "coocmap", "--map", str(noon), "--vocab", str(vocab),
                              "--out", str(native), "--quiet"], env)
        if rc != 0:
            return f"map build exit {rc}"
        other = _other_byte_order(native, work / "c4_cooc_other.tlm")
        outs = []
        for m in (native, other):
            out = work / f"{m.stem}.jsonl"
            rc, _, err, _ = _run(["localize", str(m), str(dusk), "--out", str(out), "--quiet"], env)
            if rc != 0:
                return f"exit {rc}: {err.strip()[-160:]}"
            outs.append(out.read_text())
        return "" if outs[0] == outs[1] else "the lines differ from the map in this machine's order"

    case("names", "errors name the flags of the command typed (MAP_FILE, --words, --places, --max-features, "
                  "--map-file), never another command's flag or a field name", own_flags)
    case("misleading", "a named pipe, a device as a tour, map file, cache folder, training folder or run: "
                       "said as what it is, never 'does not exist'", special_inputs)
    case("misleading", "a tour, training folder or run given twice (map build, evaluate, show-match, vocab train, "
                       "report): one line each, as map add refuses", duplicates)
    case("tracebacks", "a Cooc-Map map in the other byte order: localize answers as from the native map", byte_order)

    # -- conventions --
    def usage_errors() -> str:
        bad = []
        for args in (["map", "calibrate", str(tlm)], ["evaluate", "--bogus"], ["localize", str(tlm), str(dusk),
                                                                             "--out", "x", "--top-k", "x"],
                     ["report"], ["map", "nosuch"]):
            rc, _, err, _ = _run(args, env)
            problem = _one_line_error(rc, err)
            if problem or "Usage:" in err or len(err.strip().splitlines()) != 1:
                bad.append(f"{' '.join(args[:2])}: {problem or err.strip()[:120]}")
        return "; ".join(bad)

    def help_and_flags() -> str:
        bad = []
        for args in (["-h"], ["-V"], ["--version"], ["evaluate", "-h"], ["map", "build", "-h"],
                     ["-q", "localize", "-h"], ["localize", "-q", "-h"], ["-v", "map", "info", "-h"],
                     ["map", "info", "-v", "-h"], ["cache", "clean", "-h"]):
            rc, out, err, _ = _run(args, env)
            if rc != 0 or not out.strip():
                bad.append(f"{' '.join(args)}: exit {rc}: {err.strip()[:100]}")
        rc, out, _, _ = _run(["localize", "-h"], env)
        if "MAP_FILE INPUTS... --out" not in " ".join(out.split()):
            bad.append("localize's usage does not show MAP_FILE INPUTS... --out")
        return "; ".join(bad)

    def not_a_map() -> str:
        f = work / "c4_eight.tlm"
        f.write_text("hello!\n")
        rc, _, err, _ = _run(["map", "info", str(f)], env)
        return _one_line_error(rc, err, "not a topoloc map", str(f))

    def ros_entry() -> str:
        import sys

        code = ("import sys, topoloc.ros.__main__; "
                "print(sorted(m for m in sys.modules if m.startswith('topoloc.cli')))")
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
        if r.returncode or r.stdout.strip() != "[]":
            return f"python -m topoloc.ros imports the command line: {r.stdout.strip() or r.stderr.strip()[-120:]}"
        r = subprocess.run([sys.executable, "-m", "topoloc", "--version"], capture_output=True, text=True, env=env)
        return "" if r.returncode == 0 else "python -m topoloc does not run the command line"

    def add_says_it_rebuilds() -> str:
        m = work / "c4_own.tlm"
        _run(["map", "build", "--method", "coocmap", "--map", str(noon), "--vocab-words", "100", "--out", str(m),
              "--quiet"], env)
        rc, _, err, _ = _run(["map", "add", str(m), str(morning), "--quiet"], env)
        if rc != 0:
            return f"exit {rc}: {err.strip()[-160:]}"
        said = _warnings(err, "building it again")
        return "" if len(said) == 1 and "trained on its own tours" in said[0] else f"{len(said)} lines said"

    case("conventions", "click's usage errors (a missing option, an unknown flag, a value of the wrong type, a "
                        "missing argument, an unknown command): one line topoloc: error: ..., exit 2", usage_errors)
    case("conventions", "-h, -V/--version, -q and -v before and after the command; usage shows what is needed",
         help_and_flags)
    case("misleading", "map info on an 8-byte text file: not a topoloc map (not 'truncated')", not_a_map)
    case("conventions", "python -m topoloc.ros imports nothing of the command line; python -m topoloc runs it",
         ros_entry)
    case("misleading", "map add on a map whose vocabulary was trained on its own tours says it builds the map "
                       "again, in one line", add_says_it_rebuilds)


def _kill_cases(work: Path, route: Path, rng: np.random.Generator) -> list[dict[str, Any]]:
    """Each command killed with SIGKILL at seeded moments, its files checked and the rerun compared."""
    rows: list[dict[str, Any]] = []
    vocab = work / "vocab.tlv"
    env = {**os.environ, "TOPOLOC_CACHE_DIR": str(work / "cache")}
    subprocess.run([str(TOPOLOC), "vocab", "train", str(route / "morning"), "--words", "300", "--out",
                    str(vocab)], check=True, capture_output=True, env=env)
    for name in ("evaluate", "map build", "slam"):
        ref_dir = work / f"ref_{name.replace(' ', '_')}"
        # Warm the caches once, then time an uninterrupted run.
        subprocess.run(_commands(route, vocab, ref_dir)[name], check=True, capture_output=True, env=env)
        t0 = time.perf_counter()
        subprocess.run(_commands(route, vocab, ref_dir)[name], check=True, capture_output=True, env=env)
        duration = time.perf_counter() - t0
        reference = _result(name, ref_dir, route)
        out = work / f"kill_{name.replace(' ', '_')}"
        subprocess.run(_commands(route, vocab, out)[name], check=True, capture_output=True, env=env)
        for when in np.sort(rng.uniform(0.05, 1.0, KILLS_PER_COMMAND) * duration):
            proc = subprocess.Popen(_commands(route, vocab, out)[name], stdout=subprocess.DEVNULL,
                                    stderr=subprocess.DEVNULL, env=env)
            time.sleep(float(when))
            finished_before = proc.poll() is not None
            if not finished_before:
                proc.send_signal(signal.SIGKILL)
            proc.wait()
            problems = _check_files(out)
            rerun = subprocess.run(_commands(route, vocab, out)[name], capture_output=True, env=env)
            same = rerun.returncode == 0 and _same(_result(name, out, route), reference)
            rows.append({"command": name, "kill_after_s": round(float(when), 2),
                         "run_s": round(duration, 2), "killed": not finished_before,
                         "files_whole": not problems, "problems": problems, "rerun_same": same})
            print(json.dumps(rows[-1]), flush=True)
    return rows


def _page(summary: dict[str, Any]) -> str:
    """docs/results/reliability.md from the summary written to reliability.json."""
    cases, kills = summary["family_cases"], summary["cases"]
    held = sum(c["held"] for c in cases)
    text = [
        "# Reliability: bad input, faults, and runs killed at random moments\n\n",
        "Generated by `.venv/bin/python -m benchmarks.bench_reliability"
        f"{' --fast' if summary['fast'] else ''}`; do not edit by hand "
        f"({summary['machine']}, {summary['date']}, seed {SEED}). Raw: [reliability.json](reliability.json).\n\n",
        "## Bad input and faults, by family\n\n",
        "Each case runs `topoloc` as a user would, on a generated 12-place route, as its own process with a "
        f"time limit ({CASE_TIMEOUT_S} s; 60 s for the hangs) and, for the bombs, a 3 GiB address-space limit "
        "(`COLUMNS=1000`, so that the log handler does not wrap a warning line). "
        "A case *holds* when the command keeps the family's promise.\n\n",
        f"**{held} of {len(cases)} cases held.**\n\n",
        "| family | what must hold | tried | held |\n| --- | --- | --- | --- |\n",
    ]
    for fam, promise in FAMILIES.items():
        mine = [c for c in cases if c["family"] == fam]
        text.append(f"| {fam} | {promise} | {len(mine)} | {sum(c['held'] for c in mine)} |\n")
    text.append("\n| family | case | held | s | what went wrong |\n| --- | --- | --- | --- | --- |\n")
    for c in cases:
        detail = c["detail"].replace("|", "/").replace("\n", " ")
        text.append(f"| {c['family']} | {c['case'].replace('|', '/')} | {c['held']} | {c['seconds']} | {detail} |\n")
    text.append("\n## Runs killed at random moments\n\n")
    if not kills:
        text.append("Not run in this regeneration (`--fast`: the families only, to stay within a few minutes); "
                    "run the benchmark without `--fast` for them.\n")
        return "".join(text)
    survived = sum(r["files_whole"] and r["rerun_same"] for r in kills)
    text += [
        "Each command runs on a generated 16-place route; it is killed with SIGKILL at a seeded moment "
        "within its uninterrupted duration, the files it left are checked (JSON parses, `.npy` loads, the map "
        "file loads with its checksums, CSV lines are complete; hidden staging files are ignored), then it is "
        "run again and its result compared with an uninterrupted run's.\n\n",
        f"**{survived} of {len(kills)} cases survived** (files whole and rerun identical).\n\n",
        "| command | killed after s | uninterrupted run s | killed before it finished | files whole "
        "| rerun identical |\n",
        "| --- | --- | --- | --- | --- | --- |\n",
    ]
    for r in kills:
        text.append(f"| {r['command']} | {r['kill_after_s']} | {r['run_s']} | {r['killed']} | {r['files_whole']} "
                    f"| {r['rerun_same']} |\n")
    bad = [r for r in kills if r["problems"]]
    if bad:
        text.append("\nProblems found:\n\n"
                    + "".join(f"- {r['command']}: {'; '.join(r['problems'])}\n" for r in bad))
    return "".join(text)


def main(argv: list[str] | None = None) -> None:
    from topoloc.synth import RouteConfig, generate_route

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fast", action="store_true", help="The families only, not the runs killed at random.")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(SEED)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        small = work / "small"
        generate_route(small, config=RouteConfig(n_places=12, width=160, height=120, seed=2),
                       tours=[("noon", 12.0), ("dusk", 18.0), ("morning", 9.0)])
        fam_work = work / "families"
        fam_work.mkdir()
        # Wide columns: the log handler wraps a warning at the terminal's width, and a case looks for it whole.
        cases = family_cases(fam_work, small, {**os.environ, "TOPOLOC_CACHE_DIR": str(work / "fcache"),
                                               "COLUMNS": "1000"})
        kills: list[dict[str, Any]] = []
        if not args.fast:
            route = work / "route"
            generate_route(route, config=RouteConfig(n_places=16, width=256, height=192, seed=2),
                           tours=[("noon", 12.0), ("dusk", 18.0), ("morning", 9.0)])
            loop = route / "loop"
            loop.mkdir()
            for k, p in enumerate(sorted((route / "noon").glob("*.jpg")) * 2):
                os.link(p, loop / f"{k:05d}.jpg")  # the route driven twice: loop closures in the second lap
            kills = _kill_cases(work, route, rng)
    summary = {"machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
               "date": datetime.now(UTC).isoformat(timespec="seconds"), "seed": SEED, "fast": args.fast,
               "family_cases": cases, "families_tried": len(cases), "families_held": sum(c["held"] for c in cases),
               "cases": kills, "tried": len(kills),
               "survived": sum(r["files_whole"] and r["rerun_same"] for r in kills)}
    (RESULTS / "reliability.json").write_text(json.dumps(summary, indent=1) + "\n")
    (RESULTS / "reliability.md").write_text(_page(summary))
    print(f"{summary['families_held']} of {len(cases)} family cases held; {summary['survived']} of {len(kills)} "
          f"kill cases survived; wrote {RESULTS / 'reliability.md'}")


if __name__ == "__main__":
    main()
