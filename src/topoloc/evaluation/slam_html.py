"""One self-contained HTML page of a ``topoloc slam`` run (``slam --html``, ``report --html`` of a slam folder).

It reads the run's folder (``slam.json``, ``posterior.npy``, ``assignments.csv``,
``loop_closures.csv``, ``loop_closures.png``) and the traverse the run names,
and shows: the run's parameters and counts; the route as a strip of images
with each loop closure drawn from the image that closed it back to the image
that founded the place (with image names, not only indices); the posterior over
time (probability of a new place, and of the most probable earlier place); the
loop-closure matrix; and every accepted closure as a pair of thumbnails with
both file names and the probability.  No script, no server, no network.
"""

from __future__ import annotations

import base64
import csv
import html
import io
import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.errors import TopolocError
from topoloc.evaluation.html import _asset, _load_traverse_or_none, _Thumbs
from topoloc.io.container import atomic_write_bytes
from topoloc.io.dirs import HTML_GENERATOR
from topoloc.io.paths import through_link
from topoloc.progress import ProgressFactory, no_progress


def is_slam_run(folder: Path) -> bool:
    """Whether ``folder`` holds the outputs of ``topoloc slam``."""
    return (folder / "slam.json").is_file() and (folder / "posterior.npy").is_file()


def _png(fig: Any) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def _posterior_plot(post: np.ndarray, closures: list[tuple[int, int, float]], names: list[str],
                    threshold: float) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(post)
    p_new = post[:, -1]
    old = post[:, :-1]
    p_old = np.nanmax(np.where(np.isnan(old), -np.inf, old), axis=1) if old.shape[1] else np.zeros(n)
    p_old = np.where(np.isfinite(p_old), p_old, 0.0)
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(10, 5.2), dpi=100, sharex=True,
                                   gridspec_kw={"height_ratios": [1.2, 1]})
    x = np.arange(n)
    ax1.plot(x, p_new, color="#999", lw=1.2, label="p(new place)")
    ax1.plot(x, p_old, color="#1f77b4", lw=1.2, label="p(most probable earlier place)")
    ax1.axhline(threshold, color="#d62728", lw=0.8, ls="--", label=f"acceptance threshold {threshold}")
    if closures:
        ax1.scatter([a for a, _, _ in closures], [p for _, _, p in closures], color="#d62728", s=18, zorder=3,
                    label="accepted loop closure")
    ax1.set_ylim(-0.02, 1.05)
    ax1.set_ylabel("posterior")
    ax1.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5), frameon=False)
    ax1.set_title("Posterior over time", fontsize=10)
    # The route: each closure as an arc from the closing image back to the image that founded the place.
    for a, b, _ in closures:
        xs = np.linspace(b, a, 30)
        ax2.plot(xs, np.sin(np.linspace(0, np.pi, 30)) * (a - b), color="#d62728", lw=0.8, alpha=0.7)
    ax2.set_ylim(0, max([a - b for a, b, _ in closures], default=1) * 1.08 + 1)
    ax2.set_yticks([])
    ax2.set_xlabel("image (traverse order)")
    ax2.set_title("Loop closures along the route (arc: closing image -> image that founded the place)", fontsize=10)
    ticks = np.linspace(0, n - 1, min(n, 9)).round().astype(int) if n else np.zeros(0, int)
    ax2.set_xticks(ticks)
    ax2.set_xticklabels([f"{t}\n{names[t]}" if t < len(names) else str(t) for t in ticks], fontsize=7)
    fig.tight_layout()
    return _png(fig)


def render_slam_html(run_dir: Path, title: str = "", progress: ProgressFactory | None = None) -> str:
    """The page of the ``slam`` output folder ``run_dir``."""
    prog = progress or no_progress
    run_dir = Path(run_dir)
    if not is_slam_run(run_dir):
        raise TopolocError(f"not a slam output folder (no slam.json / posterior.npy): {run_dir}")
    try:
        summary = json.loads((run_dir / "slam.json").read_text())
        post = np.load(run_dir / "posterior.npy", allow_pickle=False)
        with (run_dir / "loop_closures.csv").open(newline="") as fh:
            rows = list(csv.DictReader(fh))
        closures = [(int(r["image"]), int(r["matched_image"]), float(r["probability"])) for r in rows]
    except (ValueError, OSError, KeyError) as exc:
        raise TopolocError(f"corrupt slam output ({exc.__class__.__name__}): {run_dir}") from None
    params = summary.get("params", {})
    names = [str(x) for x in params.get("images", [])] or [str(i) for i in range(len(post))]
    trav = _load_traverse_or_none(str(params.get("traverse", "")))
    paths = list(trav.images) if trav is not None and trav.kind == "files" and len(trav) == len(post) else []
    thumbs = _Thumbs()
    pairs = []
    for a, b, p in closures:
        pairs.append((a, b, p, thumbs.key(paths[a]) if paths else None, thumbs.key(paths[b]) if paths else None))
    thumbs.encode_all(prog)
    threshold = float(params.get("threshold", 0.98))
    plot = _posterior_plot(post, closures, names, threshold)
    matrix = run_dir / "loop_closures.png"
    matrix_html = ""
    if matrix.is_file():
        src = "data:image/png;base64," + base64.b64encode(matrix.read_bytes()).decode()
        matrix_html = (f"<h2>Loop-closure matrix</h2><img src='{src}' alt='loop-closure matrix' width='560'>"
                       "<p class='legend'>Entry (k, j): posterior, at image k, of the place founded by image j; "
                       "accepted loop closures circled.</p>")
    shown = {k: v for k, v in params.items() if k not in {"images"}}
    cards = []
    for a, b, p, ka, kb in pairs:
        def fig(key: str | None, label: str, idx: int) -> str:
            src = thumbs.data.get(key or "")
            pic = f"<img src='{src}' alt='{html.escape(names[idx])}'>" if src else "<div class='noimg'>no image</div>"
            return (f"<figure>{pic}<figcaption><b>{label}</b><div>{html.escape(names[idx])}</div>"
                    f"<div>image {idx}</div></figcaption></figure>")
        cards.append(f"<div class='card correct'><div><span class='badge correct'>loop closure</span> "
                     f"{html.escape(names[a])} → {html.escape(names[b])} · p = {p:.4f}</div>"
                     f"<div class='imgs'>{fig(ka, 'image', a)}{fig(kb, 'matched place', b)}</div></div>")
    title = title or f"FAB-MAP SLAM: {Path(str(params.get('traverse', run_dir))).name}"
    generated = datetime.now(UTC).isoformat(timespec="seconds")
    return (
        f"<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>{HTML_GENERATOR}"
        f"<title>{html.escape(title)}</title><style>{_asset('report.css')}</style></head><body>"
        f"<h1>{html.escape(title)}</h1>"
        f"<p class='meta'>topoloc slam run {html.escape(str(run_dir))}, page generated {generated}. "
        "Image indices count from 0 in traverse order; names are the files'.</p>"
        f"<p>{summary.get('n_images', len(post))} images, {summary.get('n_places', '?')} places, "
        f"<b>{len(closures)}</b> accepted loop closures.</p>"
        "<details><summary>parameters</summary><pre>"
        f"{html.escape(json.dumps(shown, indent=2, default=str))}</pre></details>"
        f"<h2>Along the route</h2><img src='{plot}' alt='posterior over time and loop closures' width='1000'>"
        f"{matrix_html}"
        f"<h2>Accepted loop closures ({len(closures)})</h2><div class='cards'>{''.join(cards)}</div>"
        "</body></html>\n"
    )


def build_slam_html(run_dir: Path, out: Path, title: str = "", progress: ProgressFactory | None = None) -> Path:
    """Write :func:`render_slam_html` to ``out`` atomically (through a link, to its target); return ``out``."""
    out = through_link(Path(out))
    page = render_slam_html(run_dir, title=title, progress=progress)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out, page.encode("utf-8", "surrogateescape"))
    return out
