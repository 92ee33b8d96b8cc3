"""The HTML report page: its content, and the page itself in headless Chromium.

The browser test drives Debian's ``chromium`` through the DevTools protocol over
a pipe (``--remote-debugging-pipe``: no websocket, no Selenium, nothing
downloaded); it is skipped cleanly when no ``chromium`` is installed
(``apt-get install chromium``; ``.ci/run`` installs it where apt is available).
It loads the page, fails on any console error or uncaught exception, moves the
threshold slider with a real ``input`` event and checks that the counts shown
change, and saves a screenshot (also to ``$TOPOLOC_SCREENSHOT`` when set).
"""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from benchmarks.common import find_browser as _find_browser
from typer.testing import CliRunner

from topoloc.cli.main import app
from topoloc.errors import TopolocError
from topoloc.evaluation.columns import distinct_labels, markdown_table, run_columns
from topoloc.evaluation.html import build_html_report, render_html
from topoloc.evaluation.pipeline import evaluate
from topoloc.synth import RouteConfig, generate_route


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """Two seqslam runs of one synthetic route (no vocabulary: fast), at tolerance 0:2 and 0:0."""
    root = tmp_path_factory.mktemp("html")
    noon, dusk = generate_route(root / "route", config=RouteConfig(n_places=24, width=160, height=120),
                                tours=[("noon", 12), ("dusk", 18.5)])
    a = root / "run_a"
    b = root / "run_b"
    evaluate(method="seqslam-single", maps=[noon], query=dusk, out=a, tolerance="0:2", cache_dir=root / "cache")
    evaluate(method="seqslam-single", maps=[noon], query=dusk, out=b, tolerance="0:0", cache_dir=root / "cache")
    return root, a, b


def _payload(page: str) -> dict[str, Any]:
    m = re.search(r"<script type='application/json' id='data'>(.*?)</script>", page, re.S)
    assert m is not None
    return json.loads(m.group(1).replace("<\\/", "</"))


def test_page_is_self_contained_and_complete(runs: tuple[Path, Path, Path]) -> None:
    _, a, b = runs
    assert (a / "gt_hard.npy").is_file() and (a / "gt_soft.npy").is_file()
    page = render_html([a, b], title="T")
    # Nothing is fetched from elsewhere: no http(s) URL in any src or href.
    assert not re.search(r"""(src|href)=['"]?https?:""", page)
    data = _payload(page)
    r0, r1 = data["runs"]
    n = len(np.load(a / "queries.npy"))
    assert r0["n_queries"] == n and len(r0["items"]) == n
    # Identical titles are made distinct by the column in which the runs differ (the tolerance).
    assert r0["label"] != r1["label"] and "0:2" in r0["label"] and "0:0" in r1["label"]
    # Each image is encoded once: the map images are shared by both runs.
    keys = {it["q"]["img"] for it in r0["items"]} | {it["q"]["img"] for it in r1["items"]}
    assert len(keys) == n and keys <= set(data["thumbs"])
    assert all(v.startswith("data:image/jpeg;base64,") for v in data["thumbs"].values())
    # The scores agree with metrics.json: at the lowest threshold, correct / queries-with-a-place = R@1.
    m = json.loads((a / "metrics.json").read_text())
    assert sum(r0["right"]) / r0["n_pos"] == pytest.approx(m["recall_at_1"])
    item = r0["items"][0]
    assert item["correct"]["place"] in range(0, 3) and item["rank"] >= 1
    assert item["q"]["file"].endswith(".jpg")
    assert "<th>ground truth</th>" in page
    # seqslam-single reads no local features and no vocabulary: the table does not show settings it ignores.
    for k in ("vocabulary", "preprocessing", "features", "vocabulary s"):
        assert f"<th>{k}</th>" not in page
    # The matrix in both colourings, and the colour scale's stops.
    assert r0["matrix"]["rank"].startswith("data:image/png;base64,") and r0["matrix"]["score"] != r0["matrix"]["rank"]
    assert r0["matrix"]["lo"] < r0["matrix"]["hi"] and len(data["colours"]) > 5
    assert r0["calibrated"] is None  # not a saved map's run: the slider opens at the best F1


def test_rebuilds_tolerance_ground_truth_of_old_runs(runs: tuple[Path, Path, Path], tmp_path: Path) -> None:
    _, a, _ = runs
    old = tmp_path / "old"
    shutil.copytree(a, old)
    (old / "gt_hard.npy").unlink()
    (old / "gt_soft.npy").unlink()
    assert _payload(render_html([old]))["runs"][0]["right"] == _payload(render_html([a]))["runs"][0]["right"]
    m = json.loads((old / "metrics.json").read_text())
    m["run"]["ground_truth"] = "file x.npy"
    (old / "metrics.json").write_text(json.dumps(m))
    with pytest.raises(TopolocError, match=r"gt_hard\.npy"):
        render_html([old])


def test_missing_similarity_is_one_clear_error(runs: tuple[Path, Path, Path], tmp_path: Path) -> None:
    _, a, _ = runs
    broken = tmp_path / "broken"
    shutil.copytree(a, broken)
    (broken / "S.npy").unlink()
    res = CliRunner().invoke(app, ["report", str(broken), "--out", str(tmp_path / "rep"),
                                   "--html", str(tmp_path / "rep" / "index.html")])
    assert res.exit_code == 2
    assert "S.npy" in res.output and "Traceback" not in res.output


def test_cli_report_html_and_columns(runs: tuple[Path, Path, Path], tmp_path: Path) -> None:
    _, a, b = runs
    out = tmp_path / "rep"
    res = CliRunner().invoke(app, ["report", str(a), str(b), "--out", str(out), "--html", str(out / "index.html")])
    assert res.exit_code == 0, res.output
    assert (out / "index.html").stat().st_size < 2_000_000
    md = (out / "report.md").read_text()
    assert "tolerance 0:2" in md and "tolerance 0:0" in md
    ma, mb = (json.loads((d / "metrics.json").read_text()) for d in (a, b))
    assert run_columns(ma)["ground_truth"] != run_columns(mb)["ground_truth"]
    assert len(set(distinct_labels([ma, mb], ["x", "x"]))) == 2
    assert "| ground truth |" in markdown_table([ma, mb])


class _Pipe:
    """The DevTools protocol over ``--remote-debugging-pipe`` (fd 3: commands in, fd 4: replies out)."""

    def __init__(self, browser: str, profile: Path) -> None:
        self.to_r, self.to_w = os.pipe()
        self.from_r, self.from_w = os.pipe()
        # The child reads fd 3 and writes fd 4.

        def child_fds() -> None:
            os.dup2(self.to_r, 3)
            os.dup2(self.from_w, 4)

        self.proc = subprocess.Popen(
            [browser, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
             "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-extensions",
             "--remote-debugging-pipe", f"--user-data-dir={profile}", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            # The pipes are close-on-exec; only their copies at fd 3 and 4 (dup2: inheritable) reach the browser.
            close_fds=False, preexec_fn=child_fds,
        )
        os.close(self.to_r)
        os.close(self.from_w)
        self.buf = b""
        self.next_id = 0
        self.events: list[dict[str, Any]] = []

    def _read_message(self, deadline: float) -> dict[str, Any]:
        import select

        while b"\0" not in self.buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("no answer from the browser")
            ready, _, _ = select.select([self.from_r], [], [], left)
            if ready:
                chunk = os.read(self.from_r, 1 << 20)
                if not chunk:
                    raise RuntimeError("the browser closed the pipe")
                self.buf += chunk
        msg, self.buf = self.buf.split(b"\0", 1)
        return json.loads(msg)

    def send(self, method: str, params: dict[str, Any] | None = None, session: str | None = None,
             timeout: float = 30.0) -> dict[str, Any]:
        self.next_id += 1
        msg: dict[str, Any] = {"id": self.next_id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self.to_w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            reply = self._read_message(deadline)
            if reply.get("id") == self.next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            self.events.append(reply)

    def wait_event(self, method: str, timeout: float = 30.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        for ev in self.events:
            if ev.get("method") == method:
                return ev
        while True:
            ev = self._read_message(deadline)
            self.events.append(ev)
            if ev.get("method") == method:
                return ev

    def close(self) -> None:
        try:
            self.send("Browser.close", timeout=5)
        except (RuntimeError, TimeoutError, OSError):
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self.to_w)
        os.close(self.from_r)


def open_page(html_path: Path, profile: Path, screenshot: Path, browser: str, n_runs: int = 1) -> dict[str, Any]:
    """Load ``html_path`` at 1,400 px, move run 0's threshold slider, switch its colouring, screenshot.

    Returns what was seen: the counts, the cards, the widths of the page and of
    the runs' table, where each of the first ``n_runs`` sliders opened.
    """
    cdp = _Pipe(browser, profile)
    try:
        target = cdp.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = cdp.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        for domain in ("Runtime.enable", "Log.enable", "Page.enable"):
            cdp.send(domain, session=session)
        cdp.send("Emulation.setDeviceMetricsOverride",
                 {"width": 1400, "height": 1000, "deviceScaleFactor": 1, "mobile": False}, session=session)
        cdp.send("Page.navigate", {"url": html_path.resolve().as_uri()}, session=session)
        cdp.wait_event("Page.loadEventFired", timeout=60)

        def js(expr: str) -> Any:
            res = cdp.send("Runtime.evaluate", {"expression": expr, "returnByValue": True, "awaitPromise": True},
                           session=session)
            if "exceptionDetails" in res:
                raise AssertionError(f"script error in the page: {res['exceptionDetails']}")
            return res["result"].get("value")

        counts = "document.querySelector('#run0 .counts').textContent"
        seen: dict[str, Any] = {"ready": js("document.body.dataset.ready"), "before": js(counts)}
        seen["opened_counts"] = [js(f"document.querySelector('#run{k} .counts').textContent") for k in range(n_runs)]
        seen["slider_max"] = js("Number(document.querySelector('#run0 input.thr').max)")
        seen["cards_before"] = js("document.querySelectorAll('#cards0 .card').length")
        # Cards whose pictures run past their border (into the next card), and the most pictures a card holds.
        seen["cards_overflowing"] = js("Array.from(document.querySelectorAll('.card'))"
                                       ".filter(c => c.scrollWidth > c.clientWidth + 1).length")
        seen["most_figures"] = js("Math.max(...Array.from(document.querySelectorAll('.card'))"
                                  ".map(c => c.querySelectorAll('figure').length))")
        seen["images"] = js("Array.from(document.images).filter(i => i.naturalWidth > 0).length")
        js("(() => { const s = document.querySelector('#run0 input.thr'); s.value = s.max;"
           " s.dispatchEvent(new Event('input', {bubbles: true})); })()")
        seen["at_max"] = js(counts)
        js("(() => { const s = document.querySelector('#run0 input.thr'); s.value = 0;"
           " s.dispatchEvent(new Event('input', {bubbles: true})); })()")
        seen["at_min"] = js(counts)
        js("document.querySelector('#filters0 button[data-filter=wrong]').click()")
        seen["wrong_cards"] = js("document.querySelectorAll('#cards0 .card.wrong').length")
        seen["other_cards"] = js("document.querySelectorAll('#cards0 .card:not(.wrong)').length")
        seen["errors_box"] = js("document.getElementById('errors').textContent")
        seen["scroll_width"] = js("document.documentElement.scrollWidth")
        seen["wrap"] = js("(() => { const w = document.querySelector('.table-wrap');"
                          " return [w.scrollWidth, w.clientWidth, getComputedStyle(w).overflowX]; })()")
        seen["opened"] = [js(f"document.querySelector('#run{k} .opened').textContent") for k in range(n_runs)]
        seen["scale_rank"] = js("document.querySelector('#run0 .scale').textContent")
        js("document.querySelector('#run0 input[value=score]').click()")
        seen["scale_score"] = js("document.querySelector('#run0 .scale').textContent")
        js("(() => { const s = document.querySelector('#run0 input.thr'); s.value = Math.floor(s.max / 2);"
           " s.dispatchEvent(new Event('input', {bubbles: true}));"
           " document.querySelector('#filters0 button[data-filter=all]').click(); })()")
        shot = cdp.send("Page.captureScreenshot", {"format": "png", "captureBeyondViewport": False},
                        session=session, timeout=60)
        screenshot.write_bytes(base64.b64decode(shot["data"]))
        seen["console_errors"] = [
            json.dumps(ev["params"])[:300] for ev in cdp.events
            if ev.get("method") == "Runtime.exceptionThrown"
            or (ev.get("method") == "Runtime.consoleAPICalled" and ev["params"].get("type") in {"error", "assert"})
            or (ev.get("method") == "Log.entryAdded" and ev["params"]["entry"].get("level") == "error")
        ]
        return seen
    finally:
        cdp.close()


def _calibrated_copy(run: Path, to: Path, threshold: float) -> Path:
    """The run as if it had scored a saved map calibrated at ``threshold`` (what ``evaluate --map-file`` records)."""
    shutil.copytree(run, to)
    m = json.loads((to / "metrics.json").read_text())
    m["run"]["calibration"] = {"threshold": threshold, "precision": 0.99}
    (to / "metrics.json").write_text(json.dumps(m))
    return to


def _wide_copy(run: Path, to: Path) -> Path:
    """The run with long names (map folders, a parameter's value without a space): wider than the page."""
    shutil.copytree(run, to)
    m = json.loads((to / "metrics.json").read_text())
    m["run"]["map"] = [f"/data/{'a_long_dataset_folder_name_' * 3}/tour_{i:02d}" for i in range(3)]
    m["params"]["descriptor_file"] = "descriptors_of_every_image_" * 12 + ".h5"  # in the table and the titles
    (to / "metrics.json").write_text(json.dumps(m))
    return to


@pytest.mark.skipif(_find_browser() is None, reason="no chromium installed (apt-get install chromium)")
def test_page_in_headless_chromium(runs: tuple[Path, Path, Path], tmp_path: Path) -> None:
    _, a, b = runs
    scores = _payload(render_html([a]))["runs"][0]["score"]
    mid = sorted(scores)[len(scores) // 2]  # a threshold that accepts about half the queries
    cal = _calibrated_copy(a, tmp_path / "calibrated", mid)
    wide = _wide_copy(b, tmp_path / "wide")
    page = build_html_report([a, cal, wide], tmp_path / "index.html", title="browser test")
    browser = _find_browser()
    assert browser is not None
    shot = tmp_path / "page.png"
    seen = open_page(page, tmp_path / "profile", shot, browser, n_runs=3)
    # The page fits 1,400 px; the three-run table scrolls in its own box.
    assert seen["scroll_width"] <= 1400, seen["scroll_width"]
    assert seen["wrap"][2] == "auto" and seen["wrap"][0] > seen["wrap"][1], seen["wrap"]
    # The calibrated run opens at its threshold: exactly the queries scoring at least it are accepted.
    accepted = sum(x >= mid for x in scores)
    assert "calibrated threshold" in seen["opened"][1] and "best F1" in seen["opened"][0], seen["opened"]
    assert re.search(rf"accepted {accepted} ", seen["opened_counts"][1]), seen["opened_counts"][1]
    # The colour scale follows the view: ranks, then scores from the 1st to the 99th percentile.
    assert "worst place" in seen["scale_rank"] and "best place" in seen["scale_rank"]
    assert "percentile" in seen["scale_score"] and "worst place" not in seen["scale_score"]
    assert seen["console_errors"] == [], seen["console_errors"]
    assert seen["errors_box"] == ""
    assert seen["ready"] == "1"
    assert seen["images"] > 10  # thumbnails and the matrix decoded
    assert seen["cards_before"] > 0
    # Every card holds its pictures, four included (the method's top answer in the ignored band).
    assert seen["most_figures"] == 4, seen["most_figures"]
    assert seen["cards_overflowing"] == 0, seen["cards_overflowing"]
    # Moving the threshold changes what is counted: nothing accepted at the top, everything at the bottom.
    assert seen["at_max"] != seen["at_min"] != seen["before"] or seen["at_max"] != seen["at_min"]
    n = len(np.load(a / "queries.npy"))
    assert re.search(r"accepted 0 ", seen["at_max"]) and f"rejected {n}" in seen["at_max"]
    assert "rejected 0" in seen["at_min"]
    assert seen["other_cards"] == 0
    assert shot.stat().st_size > 10_000
    assert np.frombuffer(shot.read_bytes()[:8], np.uint8).tolist() == [137, 80, 78, 71, 13, 10, 26, 10]
    if os.environ.get("TOPOLOC_SCREENSHOT"):
        shutil.copy(shot, os.environ["TOPOLOC_SCREENSHOT"])


def test_cli_evaluate_html_version_and_methods(runs: tuple[Path, Path, Path], tmp_path: Path) -> None:
    root, _, _ = runs
    out = tmp_path / "ev"
    res = CliRunner().invoke(app, [
        "evaluate", "--method", "seqslam-single", "--map", str(root / "route" / "noon"),
        "--query", str(root / "route" / "dusk"), "--out", str(out), "--tolerance", "0:1", "-q",
        "--cache-dir", str(root / "cache"), "--html", str(out / "index.html"),
    ])
    assert res.exit_code == 0, res.output
    assert (out / "index.html").is_file() and (out / "gt_hard.npy").is_file()
    m = json.loads((out / "metrics.json").read_text())
    assert m["run"]["vocabulary_seconds"] == 0.0 and m["run"]["fit_seconds"] >= 0
    res = CliRunner().invoke(app, ["--version"])
    assert res.exit_code == 0 and res.output.startswith("topoloc ")
    res = CliRunner().invoke(app, ["methods", "coocmap"])
    assert res.exit_code == 0 and "spatial_tolerance = 1" in res.output and "not documented" not in res.output
    res = CliRunner().invoke(app, ["methods", "fabmap2"])
    assert res.exit_code == 0 and "not documented" not in res.output
    res = CliRunner().invoke(app, ["methods", "nope"])
    assert res.exit_code == 2 and "unknown method" in res.output


def test_slam_page(fabmap_loop_model: Any, tmp_path: Path) -> None:
    from topoloc.datasets.traverse import Traverse
    from topoloc.evaluation.slam import run_slam
    from topoloc.evaluation.slam_html import render_slam_html
    from topoloc.synth.words import loop_sequence

    seq, _ = loop_sequence(12, n_words=400, seed=3)
    # Images named from 1, as many cameras name them: the page shows the names beside the indices.
    tr = Traverse(root=tmp_path, images=tuple(tmp_path / f"{k + 1}.jpg" for k in range(len(seq))),
                  places=np.arange(len(seq)))
    res = run_slam(tr, out_dir=tmp_path / "slam", model=fabmap_loop_model, words=seq, min_gap=5)
    page = render_slam_html(tmp_path / "slam")
    a, b, _ = res.loop_closures()[0]
    assert f"{a + 1}.jpg → {b + 1}.jpg" in page
    assert "Posterior over time" not in page  # drawn into the PNG, not as text
    assert page.count("data:image/png;base64,") == 2 and "<script" not in page
    with pytest.raises(TopolocError, match="not a slam output folder"):
        render_slam_html(tmp_path)


def test_infinite_scores_stay_valid_json(runs: tuple[Path, Path, Path], tmp_path: Path) -> None:
    _, a, _ = runs
    run = tmp_path / "inf"
    shutil.copytree(a, run)
    S = np.load(run / "S.npy")
    S[:, 0] = -np.inf  # e.g. a query with no features
    np.save(run / "S.npy", S)
    page = render_html([run])
    blob = re.search(r"id='data'>(.*?)</script>", page, re.S)
    assert blob is not None and "Infinity" not in blob.group(1) and "NaN" not in blob.group(1)
    r0 = _payload(page)["runs"][0]
    assert r0["score"][0] < min(r0["score"][1:])


def test_scores_are_shown_at_the_precision_they_have() -> None:
    from topoloc.evaluation.html import score_decimals

    assert score_decimals(np.array([456.0, 974.0, -12.0, np.inf])) == 0  # group sizes, votes
    assert score_decimals(np.array([0.5, 1.25, 3.0], dtype=np.float32)) == 2
    assert score_decimals(np.array([0.1, 0.2, 0.7], dtype=np.float32)) == 1  # float32's 0.1 is still one decimal
    # Scores with every digit of a float32: 3 significant digits of their spread.
    rng = np.random.default_rng(0)
    assert score_decimals(rng.uniform(0, 0.2, 50).astype(np.float32)) == 3
    assert score_decimals(rng.uniform(-40, 40, 50).astype(np.float32)) == 1
    assert score_decimals(np.array([np.nan, -np.inf])) == 0


def test_rank_view_shows_each_querys_best_place_brightest() -> None:
    import base64

    import cv2

    from topoloc.evaluation.html import _matrix_pngs, colour_stops

    rng = np.random.default_rng(1)
    # Columns on very different scales (as the margin confidence gives): by score, one stripe per query.
    S = rng.normal(size=(20, 30)) + np.arange(30)[None, :] * 50.0
    best = S.argmax(axis=0)
    pngs = _matrix_pngs(S)
    img = cv2.imdecode(np.frombuffer(base64.b64decode(pngs["rank"].split(",", 1)[1]), np.uint8), cv2.IMREAD_COLOR)
    assert img.shape[:2] == S.shape
    brightest = colour_stops()[-1]
    rgb = img[best, np.arange(S.shape[1])][:, ::-1]
    assert all(f"#{r:02x}{g:02x}{b:02x}" == brightest for r, g, b in rgb.tolist())
    assert pngs["lo"] < pngs["hi"]


def test_a_calibrated_maps_run_opens_at_its_threshold_only_when_scored_as_calibrated(
        runs: tuple[Path, Path, Path], tmp_path: Path) -> None:
    """The threshold of 10-frame sequences was applied to single-image scores without a word (issue #49)."""
    root, _, _ = runs
    route = root / "route"
    m = tmp_path / "m.tlm"
    cli = CliRunner()
    for args in (["map", "build", "--method", "seqslam-single", "--map", str(route / "noon"), "--out", str(m), "-q",
                  "--cache-dir", str(root / "cache")],
                 ["map", "calibrate", str(m), "--query", str(route / "dusk"), "--precision", "0.5", "-q",
                  "--cache-dir", str(root / "cache")]):
        res = cli.invoke(app, args)
        assert res.exit_code == 0, res.output
    from topoloc.maps import Map

    threshold = Map.load(m).threshold
    assert threshold is not None and Map.load(m).calibrated_sequence.length == 10  # the tour travels the route
    pages = {}
    # evaluate --map-file scores as the map was calibrated unless told otherwise (issue #46): --sequence 0 asks
    # for single images.
    for name, extra in (("single", ["--sequence", "0"]), ("seq", []), ("seq10", ["--sequence", "10"])):
        out = tmp_path / name
        res = cli.invoke(app, ["evaluate", "--map-file", str(m), "--query", str(route / "dusk"), "--out", str(out),
                               "-q", "--cache-dir", str(root / "cache"), "--html", str(out / "index.html"), *extra])
        assert res.exit_code == 0, res.output
        assert json.loads((out / "metrics.json").read_text())["run"]["calibration"]["threshold"] == threshold
        pages[name] = (out / "index.html").read_text()
    for name in ("seq", "seq10"):
        seq = _payload(pages[name])["runs"][0]
        assert seq["calibrated"] == threshold and not seq["calibration_note"]
    single = _payload(pages["single"])["runs"][0]
    assert single["calibrated"] is None
    assert "10-frame sequences" in single["calibration_note"] and "single images" in single["calibration_note"]
    assert "not applied" in single["calibration_note"]


def test_the_calibration_rule_of_the_slider() -> None:
    from topoloc.evaluation.html import calibrated_threshold

    def run(cal: dict[str, Any], **params: Any) -> dict[str, Any]:
        return {"params": {"sequence": 0, "verify": False, **params}, "run": {"calibration": cal}}

    single = {"threshold": 0.5}
    assert calibrated_threshold(run(single)) == (0.5, "")  # calibrated before sequences were recorded: single
    seq = {"threshold": 0.5, "sequence": {"length": 10, "mode": "constant"}}
    assert calibrated_threshold(run(seq, sequence=10, sequence_mode="constant")) == (0.5, "")
    assert calibrated_threshold(run(seq, sequence=10, sequence_mode="acceleration"))[0] is None
    assert calibrated_threshold(run(seq))[0] is None
    verified = {"threshold": 0.9, "verify": True, "threshold_on": "confidence"}
    value, note = calibrated_threshold(run(verified))  # an unverified run's page thresholds scores
    assert value is None and "confidence" in note and "not applied" in note
    assert calibrated_threshold(run(verified, verify=True), "confidence") == (0.9, "")
    value, note = calibrated_threshold(run(verified, verify=False), "confidence")
    assert value is None and "verified answers" in note and "unverified" in note
    stale = {"threshold": 1.3, "verify": True}  # chosen on verified scores before answers had a confidence
    value, note = calibrated_threshold(run(stale, verify=True), "confidence")
    assert value is None and "older topoloc" in note
    assert calibrated_threshold(run({"threshold": None})) == (None, "")


def test_a_saved_maps_run_shows_the_map_images_and_the_top_answer_in_the_band(
        runs: tuple[Path, Path, Path], tmp_path: Path) -> None:
    """"no image" for every map thumbnail of an evaluate --map-file run; a "best" that was not the method's
    top answer, unsaid (issue #49)."""
    root, _, _ = runs
    route = root / "route"
    tour = tmp_path / "noon"
    shutil.copytree(route / "noon", tour)
    m = tmp_path / "m.tlm"
    cli = CliRunner()
    common = ["-q", "--cache-dir", str(root / "cache")]
    for args in (["map", "build", "--method", "seqslam-single", "--map", str(tour), "--out", str(m), *common],
                 ["evaluate", "--map-file", str(m), "--query", str(route / "dusk"), "--out", str(tmp_path / "file"),
                  "--tolerance", "0:6", "--html", str(tmp_path / "file.html"), *common],
                 ["evaluate", "--method", "seqslam-single", "--map", str(tour), "--query", str(route / "dusk"),
                  "--out", str(tmp_path / "tours"), "--tolerance", "0:6", *common]):
        res = cli.invoke(app, args)
        assert res.exit_code == 0, res.output
    page = (tmp_path / "file.html").read_text()
    run = _payload(page)["runs"][0]
    thumbs = _payload(page)["thumbs"]
    assert all(it["best"]["img"] in thumbs for it in run["items"])  # every place shown with its map image
    S = np.load(tmp_path / "file" / "S.npy")
    top = np.argmax(S, axis=0)
    best = run["best_row"]
    places = np.load(tmp_path / "file" / "places.npy")
    for j, it in enumerate(run["items"]):
        assert ("top" in it) == (top[j] != best[j])
        if "top" in it:
            assert it["top"]["place"] == int(places[top[j]]) and it["top"]["img"] in thumbs
    assert run["n_top_in_band"] == int((top != np.asarray(best)).sum()) > 0
    assert "ignored band" in page and "top answer" in page
    # Both runs name their one vocabulary (none here) and their settings alike.
    a = run_columns(json.loads((tmp_path / "file" / "metrics.json").read_text()))
    b = run_columns(json.loads((tmp_path / "tours" / "metrics.json").read_text()))
    assert {k: v for k, v in a.items() if k != "map"} == {k: v for k, v in b.items() if k != "map"}
    # A tour folder that no longer holds what the map was built from gives no thumbnails, in one warning line.
    sorted(tour.glob("*.jpg"))[0].write_bytes(b"changed")
    again = _payload(render_html([tmp_path / "file"]))["runs"][0]
    assert all(it["best"]["img"] is None for it in again["items"])


def test_one_vocabulary_is_named_one_way(runs: tuple[Path, Path, Path], tmp_path: Path) -> None:
    """The vocabulary trained on the map's tours was "100 words, trained on the map tours" in a run from the
    tours and "trained on the map tours" in the run of the map built from them (issue #49)."""
    root, _, _ = runs
    route = root / "route"
    common = ["-q", "--cache-dir", str(root / "cache"), "--features", "sift"]
    m = tmp_path / "m.tlm"
    cli = CliRunner()
    for args in (["map", "build", "--method", "bow", "--map", str(route / "noon"), "--vocab-words", "50", "--out",
                  str(m), *common],
                 ["evaluate", "--map-file", str(m), "--query", str(route / "dusk"), "--out", str(tmp_path / "file"),
                  *common],
                 ["evaluate", "--method", "bow", "--map", str(route / "noon"), "--vocab-words", "50", "--query",
                  str(route / "dusk"), "--out", str(tmp_path / "tours"), *common]):
        res = cli.invoke(app, args)
        assert res.exit_code == 0, res.output
    a, b = (run_columns(json.loads((tmp_path / n / "metrics.json").read_text()))["vocabulary"]
            for n in ("file", "tours"))
    assert a == b and a.startswith("50 words, trained on the map tours")
