"""The README's screenshot of the HTML report, drawn again from runs of the current code.

    .venv/bin/python -m benchmarks.draw_report_screenshot [--work DIR]

Runs, each in its own process and with default settings (the default features
and vocabulary, verification on):

1. ``topoloc evaluate --method coocmap`` and ``--method bow``, map gardens_point
   ``day_left``, queries ``night_right`` (one day tour against night frames,
   where verified and unverified answers are both common);
2. ``topoloc report RUN_COOCMAP RUN_BOW --html PAGE``;
3. Debian's ``chromium`` headless, 1,400 x 2,300 px, with a virtual-time budget
   so that the page's scripts have drawn it, writing a PNG that is saved as
   ``docs/results/html_report_gardens_point.jpg`` (JPEG, quality 85).

The picture shows what the page shows a user who opens it: the runs' table, the
PR curves, the similarity matrix with the accepted matches, the threshold slider
and the first query cards with their verified flag and confidence.  Without a
``chromium`` on the PATH it stops with one line (``apt-get install chromium``).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import tempfile
from pathlib import Path

import cv2

from benchmarks.common import GP, RESULTS, TOPOLOC, find_browser, require_data
from topoloc.io.container import atomic_write_bytes

OUT = RESULTS / "html_report_gardens_point.jpg"
WINDOW = (1400, 2300)
#: Milliseconds of the page's own time the browser lets pass before the screenshot (its scripts draw the canvases).
VIRTUAL_TIME_MS = 10_000


def _browser() -> str:
    path = find_browser()
    if path is None:
        raise SystemExit("no chromium on the PATH (apt-get install chromium)")
    return path


def _run(cmd: list[str]) -> None:
    print("$ " + " ".join(cmd), flush=True)
    # The product's defaults: benchmarks.common pins SIFT and no verification for the pages written before them.
    env = {k: v for k, v in os.environ.items() if k not in ("TOPOLOC_FEATURES", "TOPOLOC_VERIFY")}
    subprocess.run(cmd, check=True, env=env)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=None, help="Keep the runs and the page here.")
    args = ap.parse_args()
    require_data()
    browser = _browser()
    with tempfile.TemporaryDirectory(prefix="topoloc_shot_") as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        runs = []
        for method in ("coocmap", "bow"):
            run = work / f"{method}_night"
            _run([str(TOPOLOC), "evaluate", "--method", method, "--map", str(GP / "day_left"),
                  "--query", str(GP / "night_right"), "--out", str(run), "--quiet"])
            runs.append(str(run))
        page = work / "report" / "index.html"
        _run([str(TOPOLOC), "report", *runs, "--out", str(work / "report"), "--title",
              "gardens_point day_left -> night_right, defaults", "--html", str(page), "--quiet"])
        png = work / "shot.png"
        _run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
              f"--user-data-dir={work / 'profile'}", f"--window-size={WINDOW[0]},{WINDOW[1]}",
              f"--virtual-time-budget={VIRTUAL_TIME_MS}", f"--screenshot={png}", page.resolve().as_uri()])
        img = cv2.imread(str(png), cv2.IMREAD_COLOR)
        if img is None:
            raise SystemExit(f"the browser wrote no readable screenshot: {png}")
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
        if not ok:
            raise SystemExit(f"could not encode {png} as JPEG")
        atomic_write_bytes(OUT, buf.tobytes())
        print(f"wrote {OUT} ({img.shape[1]} x {img.shape[0]} px, {len(buf) / 1e3:.0f} kB)")


if __name__ == "__main__":
    main()
