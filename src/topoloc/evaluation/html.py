"""One self-contained HTML page to browse ``evaluate`` runs (``report --html``, ``evaluate --html``).

The page needs no server and no network: styles, script, the similarity-matrix
images and the thumbnails are inline (images as base64 JPEG / PNG, each image
once).  It shows

- the runs' table, with every column needed to know whether two rows are
  comparable (:mod:`topoloc.evaluation.columns`) and the scores;
- the PR curves of all runs;
- for each run: a threshold slider that shows precision, recall and the
  accepted, correct, wrong and rejected counts at that threshold; the
  similarity matrix with the ground truth and the accepted best matches drawn
  over it; and the list of queries (filter: correct / wrong / rejected /
  no correct place) with the query, its best map image and its correct map
  image as thumbnails, the score and the rank of the correct place; for a
  verified run (``verification.npz``), whether each answer was verified, with
  its inliers, and its inlier matches drawn between the query and the map image
  they were found in on demand (a button; at most :data:`MAX_MATCH_LINES` lines).

A query's best match, correctness and the PR curve follow the metrics of
``docs/protocol.md`` exactly (soft-only cells are masked; a query is accepted
when its best score is at least the threshold).
"""

from __future__ import annotations

import base64
import html
import json
import logging
from dataclasses import dataclass, field
from datetime import UTC, datetime
from importlib import resources as importlib_resources
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.datasets.groundtruth import GroundTruth, ground_truth_from_places, parse_tolerance
from topoloc.datasets.traverse import Traverse, load_traverse
from topoloc.errors import TopolocError
from topoloc.evaluation.columns import NOT_USED, distinct_labels, run_columns, shown_columns, uses_vocabulary
from topoloc.evaluation.metrics import best_matches, pr_curve
from topoloc.evaluation.report import load_run, run_title
from topoloc.io.container import atomic_write_bytes
from topoloc.io.dirs import HTML_GENERATOR
from topoloc.io.paths import through_link
from topoloc.progress import ProgressFactory, no_progress

log = logging.getLogger(__name__)

#: Width in pixels of the thumbnails (JPEG); 1,000 queries stay well under 20 MB.
THUMB_WIDTH = 120
#: JPEG quality of the thumbnails.
THUMB_QUALITY = 70
#: The similarity matrix image is at most this many pixels on a side (block means beyond).
MATRIX_MAX_SIDE = 1000
#: At most this many ground-truth cells are drawn over the matrix.
MAX_GT_CELLS = 200_000
#: At most this many points of each PR curve are embedded.
MAX_PR_POINTS = 600
#: At most this many inlier matches of each verified answer are embedded (evenly chosen).
MAX_MATCH_LINES = 60


def _verification(run_dir: Path, n_queries: int, thumbs: _Thumbs) -> list[dict[str, Any]] | None:
    """Per query: verified, its support (``inliers``), confidence and supporting matches (fractions of each image's
    size); runs written before answers had a confidence have none."""
    path = run_dir / "verification.npz"
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            verified, inliers = z["verified"], z["inliers"]
            confidence = z["confidence"] if "confidence" in z.files else None
            xy, offsets = z["match_xy"], z["match_offsets"]
            names, shapes = z["match_image"], z["match_shapes"]
    except (ValueError, OSError, KeyError) as exc:
        raise TopolocError(f"corrupt verification.npz ({exc.__class__.__name__}): {run_dir}") from None
    if len(verified) != n_queries or len(offsets) != n_queries + 1:
        raise TopolocError(f"verification.npz does not match S.npy's {n_queries} queries: {run_dir}")
    out = []
    for j in range(n_queries):
        entry: dict[str, Any] = {"verified": bool(verified[j]), "inliers": int(inliers[j])}
        if confidence is not None:
            entry["confidence"] = round(float(confidence[j]), 3)
        pairs = xy[offsets[j]:offsets[j + 1]]
        hq, wq, hm, wm = (int(x) for x in shapes[j])
        if len(pairs) and min(hq, wq, hm, wm) > 0 and str(names[j]):
            pick = np.unique(np.linspace(0, len(pairs) - 1, min(len(pairs), MAX_MATCH_LINES)).round().astype(int))
            rel = pairs[pick] / np.array([wq, hq, wm, hm], np.float32)
            entry["match"] = {"img": thumbs.key(Path(str(names[j]))), "file": Path(str(names[j])).name,
                              "xy": np.round(rel, 4).tolist(), "aspect": [hq / wq, hm / wm]}
        out.append(entry)
    return out


def _asset(name: str) -> str:
    return importlib_resources.files("topoloc.evaluation").joinpath("html_assets", name).read_text()


@dataclass
class _Thumbs:
    """Thumbnails keyed by image path, each encoded once."""

    width: int = THUMB_WIDTH
    keys: dict[str, str] = field(default_factory=dict)
    data: dict[str, str] = field(default_factory=dict)

    def key(self, path: Path | None) -> str | None:
        if path is None:
            return None
        p = str(path)
        if p not in self.keys:
            self.keys[p] = f"i{len(self.keys)}"
        return self.keys[p]

    def encode_all(self, progress: ProgressFactory) -> None:
        import cv2

        from topoloc.datasets.decode import read_image
        from topoloc.errors import TopolocError

        todo = [(p, k) for p, k in self.keys.items() if k not in self.data]
        advance = progress("HTML thumbnails", len(todo))
        for path, key in todo:
            try:  # not cv2.imread: a name that is not UTF-8 crashed OpenCV (issue #41); the size is checked first
                img = read_image(path, gray=False)
            except TopolocError:
                img = None
            if img is None:
                log.warning("cannot read image for a thumbnail: %s", path)
                advance(1)
                continue
            h, w = img.shape[:2]
            if w > self.width:
                img = cv2.resize(img, (self.width, max(1, round(h * self.width / w))), interpolation=cv2.INTER_AREA)
            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, THUMB_QUALITY])
            if ok:
                self.data[key] = "data:image/jpeg;base64," + base64.b64encode(buf.tobytes()).decode()
            advance(1)


def _run_ground_truth(run_dir: Path, m: dict[str, Any], places: np.ndarray, queries: np.ndarray) -> GroundTruth:
    """``gt_hard.npy``/``gt_soft.npy`` of the run, or rebuilt from a place-id tolerance."""
    hard_p, soft_p = run_dir / "gt_hard.npy", run_dir / "gt_soft.npy"
    if hard_p.is_file() and soft_p.is_file():
        try:
            hard, soft = np.load(hard_p, allow_pickle=False), np.load(soft_p, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise TopolocError(f"corrupt ground truth ({exc.__class__.__name__}): {hard_p}") from None
        return GroundTruth(hard, soft, m.get("run", {}).get("ground_truth", ""))
    desc = str(m.get("run", {}).get("ground_truth", ""))
    if desc.startswith("place ids, tolerance "):
        hard_t, soft_t = parse_tolerance(desc.removeprefix("place ids, tolerance ").split()[0])
        return ground_truth_from_places(places, queries, hard_t, soft_t)
    raise TopolocError(
        f"the run has no gt_hard.npy/gt_soft.npy and its ground truth ({desc or 'unknown'}) cannot be rebuilt; "
        f"run `topoloc evaluate` again to write them: {run_dir}"
    )


def _load_traverse_or_none(path: str) -> Traverse | None:
    try:
        p = Path(path)
        return load_traverse(p) if p.is_dir() else None
    except TopolocError as exc:
        log.warning("no thumbnails from %s (%s)", path, exc)
        return None


def _map_file_tours(records: list[dict[str, Any]]) -> list[Traverse]:
    """The tours a saved map was built from (``run.map_tours`` of an ``evaluate --map-file`` run), for thumbnails.

    A tour is read only where its folder still holds what the map recorded of it (the same images,
    sizes and places: its fingerprint); a map's tours are data it was built from, so a folder that
    changed, or that a map merely names, gives no thumbnails, said in one warning line.
    """
    out = []
    for rec in records if isinstance(records, list) else []:
        root = str(rec.get("root", "")) if isinstance(rec, dict) else ""
        trav = _load_traverse_or_none(root) if root else None
        if trav is None:
            continue
        if trav.fingerprint() != rec.get("fingerprint"):
            log.warning("no thumbnails of map tour %r: its folder no longer holds the images the map was built from: "
                        "%s", rec.get("name"), root)
            continue
        out.append(trav)
    return out


def _place_images(maps: list[Traverse]) -> dict[int, tuple[Path, str]]:
    """Place id -> (first image showing it, tour name), the first map tour first."""
    out: dict[int, tuple[Path, str]] = {}
    for trav in maps:
        if trav.kind != "files":
            continue
        for path, place in zip(trav.images, trav.places, strict=True):
            out.setdefault(int(place), (path, trav.name))
    return out


def _png_uri(norm: np.ndarray) -> tuple[str, int, int]:
    """``norm`` (values in [0, 1]) as a viridis PNG data URI, block-averaged to at most ``MATRIX_MAX_SIDE``."""
    import cv2

    h, w = norm.shape
    scale = min(1.0, MATRIX_MAX_SIDE / max(h, w, 1))
    if scale < 1.0:
        norm = cv2.resize(norm, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
    img = cv2.applyColorMap((np.clip(norm, 0, 1) * 255).round().astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - encoding a uint8 image does not fail
        raise TopolocError("cannot encode the similarity matrix image")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode(), img.shape[1], img.shape[0]


def colour_stops(n: int = 11) -> list[str]:
    """``n`` evenly spaced colours of the matrices' colour map (viridis, as OpenCV draws it), dark to bright."""
    import cv2

    bgr = cv2.applyColorMap(np.linspace(0, 255, n).round().astype(np.uint8)[:, None], cv2.COLORMAP_VIRIDIS)[:, 0]
    return [f"#{r:02x}{g:02x}{b:02x}" for b, g, r in bgr.tolist()]


def _matrix_pngs(S: np.ndarray) -> dict[str, Any]:
    """The matrix twice, as the page can colour it: by each cell's rank within its query, and by score.

    Scores of different queries are not on one scale (the margin confidence shifts
    each column), so coloured by score the matrix can show one stripe per query
    and hide the route; the rank of a place among all places for the same query
    (1 = best, bright) shows the route whatever the scale.  The score view
    spans the 1st to 99th percentile of the finite scores, given as ``lo``/``hi``
    for its colour scale.
    """
    from scipy.stats import rankdata

    A = np.asarray(S, dtype=np.float64)
    finite = np.isfinite(A)
    if finite.any():
        lo, hi = (float(x) for x in np.percentile(A[finite], [1, 99]))
        A = np.where(finite, A, np.where(A > 0, hi, lo))
    else:
        lo, hi = 0.0, 1.0
        A = np.zeros_like(A)
    score_src, w, h = _png_uri((A - lo) / (hi - lo if hi > lo else 1.0))
    n = A.shape[0]
    # 0 for the worst place of a query, 1 for its best (ties share their mean rank).
    rank = (rankdata(A, axis=0) - 1.0) / max(n - 1, 1) if n else A
    rank_src, _, _ = _png_uri(rank)
    return {"score": score_src, "rank": rank_src, "width": w, "height": h, "lo": lo, "hi": hi}


def score_decimals(score: np.ndarray) -> int:
    """Decimals that show ``score`` at the precision it has: 0 for whole numbers (group sizes, votes).

    The fewest decimals (at most 4) that give back every finite score up to
    float32 rounding (S.npy is float32); scores with more digits than that
    get 3 significant digits of their spread (their 1st to 99th percentile).
    """
    x = np.asarray(score, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return 0
    tol = 4 * float(np.finfo(np.float32).eps) * np.abs(x) + 1e-12
    for d in range(5):
        if np.all(np.abs(x - np.round(x, d)) <= tol):
            return d
    lo, hi = np.percentile(x, [1, 99])
    spread = float(hi - lo) or float(np.abs(x).max()) or 1.0
    return int(min(6, max(0, 2 - np.floor(np.log10(spread)))))


def _subsample(p: np.ndarray, r: np.ndarray) -> list[list[float]]:
    idx = np.arange(len(p))
    if len(idx) > MAX_PR_POINTS:
        idx = np.unique(np.r_[np.linspace(0, len(p) - 1, MAX_PR_POINTS).round().astype(int), len(p) - 1])
    return [[round(float(r[i]), 5), round(float(p[i]), 5)] for i in idx]


def _run_data(run_dir: Path, m: dict[str, Any], thumbs: _Thumbs, label: str) -> dict[str, Any]:
    """Everything the page's script needs about one run (JSON-serialisable)."""
    def need(name: str) -> np.ndarray:
        path = run_dir / name
        if not path.is_file():
            raise TopolocError(f"the HTML page needs {name} of the run (written by `topoloc evaluate`): {run_dir}")
        try:
            return np.load(path, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise TopolocError(f"corrupt {name} ({exc.__class__.__name__}): {run_dir}") from None

    S = np.asarray(need("S.npy"), dtype=np.float64)
    places = np.asarray(need("places.npy"), dtype=np.int64)
    queries = np.asarray(need("queries.npy"), dtype=np.int64)
    if S.shape != (len(places), len(queries)):
        raise TopolocError(f"S.npy {S.shape} does not match places.npy and queries.npy: {run_dir}")
    gt = _run_ground_truth(run_dir, m, places, queries)
    if gt.shape != S.shape:
        raise TopolocError(f"ground truth {gt.shape} does not match S.npy {S.shape}: {run_dir}")
    idx, score, right = best_matches(S, gt)
    # The method's own top answer, before the metrics skip the places of the tolerance band (soft-only cells).
    top = np.argmax(np.where(np.isnan(S), -np.inf, S), axis=0) if S.shape[0] else np.zeros(S.shape[1], np.int64)
    # JSON has no infinities: +-inf scores become just above / below every finite one (same order).
    finite = score[np.isfinite(score)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 0.0)
    score = np.nan_to_num(score, posinf=hi + 1.0, neginf=lo - 1.0)
    precision, recall = pr_curve(S, gt)
    hard = gt.hard
    has_pos = hard.any(axis=0)
    Sm = S.copy()
    Sm[gt.soft & ~hard] = S.min()
    # The correct place shown for each query: its best-scoring GThard row; its rank among all rows.
    correct_row = np.where(has_pos, np.argmax(np.where(hard, Sm, -np.inf), axis=0), -1)
    cols = np.arange(S.shape[1])
    correct_score = np.where(has_pos, Sm[np.maximum(correct_row, 0), cols], np.nan)
    rank = np.where(has_pos, (Sm > correct_score[None, :]).sum(axis=0) + 1, 0)

    run = m.get("run", {})
    maps = [t for t in (_load_traverse_or_none(p) for p in run.get("map", [])) if t is not None]
    if not maps and run.get("map_tours"):  # a saved map's run: the tours it was built from
        maps = _map_file_tours(run["map_tours"])
    query_trav = _load_traverse_or_none(str(run.get("query", "")))
    if query_trav is not None and len(query_trav) != S.shape[1]:
        log.warning("query traverse %s has %d images but the run %d queries: no query thumbnails",
                    query_trav.root, len(query_trav), S.shape[1])
        query_trav = None
    place_img = _place_images(maps)

    def place_entry(row: int) -> dict[str, Any] | None:
        if row < 0:
            return None
        pid = int(places[row])
        found = place_img.get(pid)
        return {"place": pid, "file": found[0].name if found else None, "tour": found[1] if found else None,
                "img": thumbs.key(found[0]) if found else None}

    checks = _verification(run_dir, S.shape[1], thumbs)
    # A verified run is thresholded on its answers' confidence, as a calibrated map accepts them (the verified
    # scores of S order the answers the same way among verified ones, but are not for reading).
    by_confidence = checks is not None and all("confidence" in c for c in checks)
    if by_confidence:
        assert checks is not None
        score = np.array([c["confidence"] for c in checks], np.float64)
    calibrated, calibration_note = calibrated_threshold(m, "confidence" if by_confidence else "score")
    items = []
    for j in range(S.shape[1]):
        q: dict[str, Any] = {"place": int(queries[j]), "file": None, "img": None, "time": None}
        if query_trav is not None:
            q["file"] = query_trav.images[j].name
            q["img"] = thumbs.key(query_trav.images[j]) if query_trav.kind == "files" else None
            if query_trav.times is not None:
                q["time"] = str(query_trav.times[j])
        items.append({
            "q": q, "best": place_entry(int(idx[j])), "correct": place_entry(int(correct_row[j])),
            "rank": int(rank[j]), **({"check": checks[j]} if checks is not None else {}),
            # Where the method's top answer lies in the band the metrics ignore, the card shows it too.
            **({"top": place_entry(int(top[j]))} if int(top[j]) != int(idx[j]) else {}),
        })
    n_cells = int(hard.sum())
    rows, qcols = np.nonzero(hard)
    if n_cells > MAX_GT_CELLS:
        keep = np.linspace(0, n_cells - 1, MAX_GT_CELLS).round().astype(int)
        rows, qcols = rows[keep], qcols[keep]
    return {
        "label": label,
        "title": run_title(m),
        "dir": str(run_dir),
        "n_places": int(S.shape[0]),
        "n_queries": int(S.shape[1]),
        "n_pos": int(has_pos.sum()),
        "auc": float(m.get("auc", 0.0)),
        "pr": _subsample(precision, recall),
        "score": [float(x) for x in score],
        "right": [bool(x) for x in right],
        "has_pos": np.asarray(has_pos, dtype=bool).tolist(),
        "best_row": [int(x) for x in idx],
        "items": items,
        "gt_rows": rows.tolist(),
        "gt_cols": qcols.tolist(),
        "gt_drawn_all": n_cells <= MAX_GT_CELLS,
        "matrix": _matrix_pngs(S),
        "decimals": 3 if by_confidence else score_decimals(score),
        "score_name": "confidence" if by_confidence else "score",
        # A verified run's answers are accepted only where verified, as localize accepts them (the slider's rule).
        "verified": [bool(c["verified"]) for c in checks] if by_confidence and checks is not None else None,
        # The threshold the page opens at: the map's calibrated one where the run scored a calibrated map as it
        # was calibrated (the same sequence matching and verification, a threshold on the same quantity: the
        # confidence for a verified run, the score otherwise), else why not (issue #49).
        "calibrated": calibrated,
        "calibration_note": calibration_note,
        "n_top_in_band": int(sum("top" in it for it in items)),
        "ground_truth": gt.description or str(run.get("ground_truth", "")),
    }


def calibrated_threshold(m: dict[str, Any], on: str = "score") -> tuple[float | None, str]:
    """The acceptance threshold the page may open at, and what the page says of it.

    The threshold of the calibrated map an ``evaluate --map-file`` run scored, where the run
    scored as the map was calibrated: a threshold chosen on the scores of 10-frame sequences
    (or of verified answers) means nothing on single-image (or unverified) scores, which are
    on another scale; and a threshold on the quantity the page thresholds, ``on``: the
    confidence of a verified run's answers, or the score.  Otherwise None, and the page says
    why it opens elsewhere.
    """
    from topoloc.maps.calibration import threshold_kind

    cal = m.get("run", {}).get("calibration")
    if not isinstance(cal, dict):
        return None, ""
    kind = threshold_kind(cal)
    if kind != on and isinstance(cal.get("threshold"), int | float):
        what = {"score": "method's score", "confidence": "confidence"}.get(kind, "verified score of an older topoloc")
        return None, (f"the map's threshold {cal['threshold']:.4g} applies to the answers' {what} and this page "
                      f"thresholds their {on}: not applied")
    value = cal.get("threshold")
    if not (isinstance(value, int | float) and not isinstance(value, bool) and np.isfinite(value)):
        return None, ""
    params = m.get("params", {})
    given = cal.get("sequence")
    seq: dict[str, Any] = given if isinstance(given, dict) else {}
    cal_len, run_len = int(seq.get("length", 0) or 0), int(params.get("sequence", 0) or 0)

    def matching(n: int, mode: Any) -> str:
        return f"{n}-frame sequences ({mode})" if n else "single images"

    cal_mode, run_mode = seq.get("mode", "constant"), params.get("sequence_mode", "constant")
    if cal_len != run_len or (cal_len and cal_mode != run_mode):
        return None, (f"the map's threshold {value:.4g} was calibrated on {matching(cal_len, cal_mode)} and this run "
                      f"scored {matching(run_len, run_mode)}, whose scores are on another scale: not applied")
    if "verify" in cal and bool(cal["verify"]) != bool(params.get("verify", False)):
        said = {True: "verified", False: "unverified"}
        return None, (f"the map's threshold {value:.4g} was calibrated on {said[bool(cal['verify'])]} answers and this "
                      f"run scored {said[bool(params.get('verify', False))]} ones, on another scale: not applied")
    return float(value), ""


def _fmt(x: Any, spec: str) -> str:
    return format(x, spec) if isinstance(x, int | float) else "?"


def _table_html(runs: list[dict[str, Any]], labels: list[str]) -> str:
    columns = shown_columns(runs)
    vocab_s = any(k == "vocabulary" for k, _ in columns)
    heads = ["#", *(h for _, h in columns), "places × queries", "AUC", "R@100P", "R@1", "R@5", "R@10",
             "fit s", *(["vocabulary s"] if vocab_s else []), "ms/query"]
    out = ["<table class='runs'><thead><tr>", *(f"<th>{html.escape(h)}</th>" for h in heads), "</tr></thead><tbody>"]
    for i, m in enumerate(runs):
        c = run_columns(m)
        run = m.get("run", {})
        cells = [f"<a href='#run{i}' title='{html.escape(labels[i])}'>{i + 1}</a>",
                 # Paths may break after a slash, never inside a name.
                 *(html.escape(c[k]).replace("/", "/<wbr>") for k, _ in columns),
                 f"{m.get('n_places', '?')} × {m.get('n_queries', '?')}",
                 *(_fmt(m.get(k), ".3f") for k in ("auc", "recall_at_100_precision", "recall_at_1",
                                                   "recall_at_5", "recall_at_10")),
                 _fmt(run.get("fit_seconds"), ".2f"),
                 *([_fmt(run.get("vocabulary_seconds"), ".1f") if uses_vocabulary(m) else NOT_USED] if vocab_s else []),
                 _fmt(m.get("ms_per_query"), ".2f")]
        out.append("<tr>" + "".join(f"<td>{x}</td>" for x in cells) + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def render_html(run_dirs: list[Path], title: str = "Results", progress: ProgressFactory | None = None) -> str:
    """The page for the ``evaluate`` output folders ``run_dirs``, as one string."""
    prog = progress or no_progress
    if not run_dirs:
        raise TopolocError("the HTML report needs at least one evaluate output folder")
    metrics = [load_run(Path(d))[0] for d in run_dirs]
    labels = distinct_labels(metrics, [run_title(m) for m in metrics])
    thumbs = _Thumbs()
    runs = []
    advance = prog("HTML report runs", len(run_dirs))
    for d, m, label in zip(run_dirs, metrics, labels, strict=True):
        runs.append(_run_data(Path(d), m, thumbs, label))
        advance(1)
    thumbs.encode_all(prog)
    payload = {"runs": runs, "thumbs": thumbs.data, "thumb_width": thumbs.width, "colours": colour_stops()}
    # No "<" at all in the script element: "</script>" would end it early, and "<!--<script>" in a file
    # name would put the parser where the real "</script>" no longer ends it (JSON reads \u003c as "<").
    data = json.dumps(payload, separators=(",", ":")).replace("<", "\\u003c")
    generated = datetime.now(UTC).isoformat(timespec="seconds")
    return (
        f"<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>{HTML_GENERATOR}"
        f"<title>{html.escape(title)}</title>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<style>{_asset('report.css')}</style></head><body>"
        f"<h1>{html.escape(title)}</h1>"
        f"<p class='meta'>topoloc report of {len(runs)} run(s), generated {generated}. "
        "Rows are comparable only where the columns before the scores agree.</p>"
        f"<h2>Runs</h2><div class='table-wrap'>{_table_html(metrics, labels)}</div>"
        "<h2>Precision-recall</h2><div id='pr-wrap'><canvas id='pr' width='640' height='420'></canvas>"
        "<div id='pr-legend'></div></div>"
        "<div id='runs'></div>"
        "<div id='errors' hidden></div>"
        f"<script type='application/json' id='data'>{data}</script>"
        f"<script>{_asset('report.js')}</script>"
        "</body></html>\n"
    )


def build_html_report(
    run_dirs: list[Path], out: Path, title: str = "Results", progress: ProgressFactory | None = None
) -> Path:
    """Write :func:`render_html` of ``run_dirs`` to ``out`` (an ``.html`` file) atomically; return ``out``.

    ``out`` named through a symbolic link is written where the link points (the link kept).
    """
    out = through_link(Path(out))
    if out.exists() and out.is_dir():
        out = through_link(out / "index.html")
    page = render_html([Path(d) for d in run_dirs], title=title, progress=progress)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out, page.encode("utf-8", "surrogateescape"))
    return out
