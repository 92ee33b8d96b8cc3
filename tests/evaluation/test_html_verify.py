"""The HTML page of a verified run: each query says whether it was verified, and draws its inlier matches on demand."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from tests.evaluation.test_html import _find_browser, _payload, _Pipe

from topoloc.evaluation.html import MAX_MATCH_LINES, build_html_report, render_html
from topoloc.evaluation.pipeline import evaluate
from topoloc.synth import RouteConfig, generate_route


@pytest.fixture(scope="module")
def verified_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("html_verify")
    noon, dusk = generate_route(root / "route", config=RouteConfig(n_places=12, width=192, height=144, seed=3),
                                tours=[("noon", 12), ("dusk", 18.0)])
    out = root / "run"
    evaluate(method="seqslam-single", maps=[noon], query=dusk, out=out, tolerance="0:1", cache_dir=root / "cache",
             verify=True)
    return out


def test_the_page_carries_each_querys_check_and_matches(verified_run: Path) -> None:
    z = np.load(verified_run / "verification.npz")
    items = _payload(render_html([verified_run]))["runs"][0]["items"]
    assert [it["check"]["verified"] for it in items] == z["verified"].tolist()
    assert [it["check"]["inliers"] for it in items] == z["inliers"].tolist()
    assert _payload(render_html([verified_run]))["runs"][0]["verified"] == z["verified"].tolist()
    # Every answer's supporting matches are drawn, an unverified one's too (they show why it fell short).
    stored = np.diff(z["match_offsets"]) > 0
    assert ["match" in it["check"] for it in items] == stored.tolist()
    assert stored[z["verified"]].all() and z["verified"].sum() > 0
    drawn = [it["check"]["match"] for it in items if "match" in it["check"]]
    for m, n in zip(drawn, z["inliers"][stored], strict=True):
        assert len(m["xy"]) == min(int(n), MAX_MATCH_LINES) or len(m["xy"]) <= MAX_MATCH_LINES
        assert np.all((np.array(m["xy"]) >= 0) & (np.array(m["xy"]) <= 1))
        assert m["img"] is not None and m["file"].endswith((".png", ".jpg"))

def test_a_run_without_verification_shows_none_and_a_bad_file_is_one_error(verified_run: Path,
                                                                             tmp_path: Path) -> None:
    from topoloc.errors import TopolocError

    plain = tmp_path / "plain"
    shutil.copytree(verified_run, plain)
    (plain / "verification.npz").unlink()
    assert all("check" not in it for it in _payload(render_html([plain]))["runs"][0]["items"])
    (plain / "verification.npz").write_bytes(b"not a zip")
    with pytest.raises(TopolocError, match=r"corrupt verification\.npz"):
        render_html([plain])


@pytest.mark.skipif(_find_browser() is None, reason="no chromium installed (apt-get install chromium)")
def test_matches_are_drawn_on_demand_in_headless_chromium(verified_run: Path, tmp_path: Path) -> None:
    # Beside the run, a copy with every other answer unverified (their confidence kept).
    half = tmp_path / "half"
    shutil.copytree(verified_run, half)
    z = dict(np.load(half / "verification.npz"))
    half_verified = z["verified"] & (np.arange(len(z["verified"])) % 2 == 0)
    np.savez(half / "verification.npz", **{**z, "verified": half_verified})
    assert 0 < int(half_verified.sum()) < len(half_verified)
    page = build_html_report([verified_run, half], tmp_path / "index.html", title="verified")
    browser = _find_browser()
    assert browser is not None
    cdp = _Pipe(browser, tmp_path / "profile")
    try:
        target = cdp.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = cdp.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        for domain in ("Runtime.enable", "Page.enable"):
            cdp.send(domain, session=session)
        cdp.send("Page.navigate", {"url": page.resolve().as_uri()}, session=session)
        cdp.wait_event("Page.loadEventFired", timeout=60)

        def js(expr: str) -> object:
            res = cdp.send("Runtime.evaluate", {"expression": expr, "returnByValue": True}, session=session)
            assert "exceptionDetails" not in res, res
            return res["result"].get("value")

        assert js("document.querySelectorAll('#cards0 .badge.verified').length") > 0
        assert js("document.querySelectorAll('#cards0 svg.matches').length") == 0  # drawn only when asked
        js("document.querySelector('#cards0 .check button').click()")
        assert js("document.querySelectorAll('#cards0 svg.matches line').length") > 0
        assert js("document.querySelectorAll('#cards0 svg.matches image').length") == 2
        js("document.querySelector('#cards0 .check button').click()")  # and hidden again
        assert js("document.querySelectorAll('#cards0 svg.matches').length") == 0
        # The slider accepts as localize does: at its lowest threshold every verified answer and no other.
        js("(() => { const s = document.querySelector('#run1 input.thr'); s.value = 0;"
           " s.dispatchEvent(new Event('input')); })()")
        assert js("Number(document.querySelector('#run1 .v-acc').textContent)") == int(half_verified.sum())
    finally:
        cdp.close()
