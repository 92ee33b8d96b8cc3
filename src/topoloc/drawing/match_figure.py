"""Match drawings that explain themselves (``topoloc show-match``), for any method.

A drawing shows the query beside a map image of the place it was matched to,
with a header naming both sides (query file, time and true place where its
folder tells them; map place id, tour, file and time), the score and rank of
the drawn place among all places, and the number of consistent
correspondences; and a verdict line (right or wrong by the query folder's
place ids, with the distance in places).  Correspondences are coloured by
consistency: green for those in the consistent group (Cooc-Map's final group
``K``; for other methods the epipolar-RANSAC inliers of ratio-test matches),
red (faint) for the rest, so that a wrong match, with few consistent lines and many
inconsistent ones, can be told from a right one.

At its best place, a method that declares which query features made its
match (``consistent_group``, :class:`~topoloc.drawing.show_match.GroupMatcher`:
Cooc-Map's group ``K``) is drawn with that group in green
(:func:`topoloc.drawing.show_match.group_correspondences`); for every other
method, and for a place chosen with ``place=``, correspondences are ratio-test
matches of the query's descriptors to the map image's, split by a RANSAC
fundamental matrix (exactly what ``voting`` scores; a drawing aid for the
other methods).  A method whose ranks are not all exact says so through
``rank_note(rank)``, printed under the score.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from topoloc.datasets.traverse import Traverse, load_traverse
from topoloc.drawing.show_match import GroupMatcher, frame_pixels, group_correspondences
from topoloc.errors import ParameterError, TopolocError, input_error
from topoloc.geometry import epipolar_inliers
from topoloc.methods.base import PlaceRecognizer
from topoloc.resources import Resources

GREEN = (60, 200, 60)
RED = (40, 40, 230)
TEXT = (20, 20, 20)
MIN_WIDTH = 960


@dataclass(frozen=True)
class QueryInfo:
    """What the query image's folder says about it (nothing for a lone image)."""

    file: str
    place: int | None = None
    time: str | None = None


def query_info(path: Path) -> QueryInfo:
    """The query's true place and time from its folder (``places.csv``, or natural order), when it is a traverse."""
    try:
        trav = load_traverse(path.parent)
    except TopolocError:
        return QueryInfo(path.name)
    names = [p.name for p in trav.images]
    if path.name not in names:
        return QueryInfo(path.name)
    i = names.index(path.name)
    time = str(trav.times[i]) if trav.times is not None else None
    return QueryInfo(path.name, int(trav.places[i]), time)


def _ratio_matches(desc_q: np.ndarray, desc_m: np.ndarray, ratio: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """Lowe ratio-test matches (query rows, map rows)."""
    if len(desc_q) < 2 or len(desc_m) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    binary = desc_q.dtype == np.uint8
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING if binary else cv2.NORM_L2)
    dq = desc_q if binary else np.ascontiguousarray(desc_q, np.float32)
    dm = desc_m if binary else np.ascontiguousarray(desc_m, np.float32)
    qi, mi = [], []
    for pair in matcher.knnMatch(dq, dm, k=2):
        if len(pair) == 2 and pair[0].distance < ratio * pair[1].distance:
            qi.append(pair[0].queryIdx)
            mi.append(pair[0].trainIdx)
    return np.asarray(qi, np.int64), np.asarray(mi, np.int64)


def geometric_correspondences(
    query_feats: Any, map_feats: Any, *, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ratio-test matches between two ``FeatureSet``s and their RANSAC inlier mask.

    Returns
    -------
    pts_query, pts_map : ndarray of float64, shape (m, 2)
    consistent : ndarray of bool, shape (m,)
    """
    qi, mi = _ratio_matches(query_feats.descriptors, map_feats.descriptors)
    pq = query_feats.keypoints[qi, :2].astype(np.float64)
    pm = map_feats.keypoints[mi, :2].astype(np.float64)
    return pq, pm, epipolar_inliers(pq, pm, seed=seed)


def draw_labelled(
    query_bgr: np.ndarray, map_bgr: np.ndarray, pts_query: np.ndarray, pts_map: np.ndarray,
    consistent: np.ndarray, *, left: Sequence[str], right: Sequence[str], bottom: Sequence[str],
    verdict: tuple[str, bool | None] | None = None,
) -> np.ndarray:
    """The two images side by side with labelled headers and correspondences coloured by consistency.

    Inconsistent correspondences are drawn first and thin (red), consistent ones on top (green).
    """
    h = max(query_bgr.shape[0], map_bgr.shape[0])
    width = query_bgr.shape[1] * h / query_bgr.shape[0] + map_bgr.shape[1] * h / map_bgr.shape[0]
    if width < MIN_WIDTH:  # small images are enlarged so that the labels stay legible
        h = round(h * MIN_WIDTH / width)
    sq, sm = h / query_bgr.shape[0], h / map_bgr.shape[0]
    q = cv2.resize(query_bgr, (round(query_bgr.shape[1] * sq), h))
    m = cv2.resize(map_bgr, (round(map_bgr.shape[1] * sm), h))
    pics = np.hstack([q, m])
    cv2.line(pics, (q.shape[1], 0), (q.shape[1], h - 1), (255, 255, 255), 2)
    # Inconsistent correspondences: thin, half transparent, underneath; consistent ones solid on top.
    faint = pics.copy()
    blended = False
    for i in np.argsort(consistent, kind="stable"):
        a = (round(float(pts_query[i, 0] * sq)), round(float(pts_query[i, 1] * sq)))
        b = (round(float(pts_map[i, 0] * sm)) + q.shape[1], round(float(pts_map[i, 1] * sm)))
        if not consistent[i]:
            cv2.line(faint, a, b, RED, 1, cv2.LINE_AA)
            cv2.circle(faint, a, 3, RED, 1, cv2.LINE_AA)
            cv2.circle(faint, b, 3, RED, 1, cv2.LINE_AA)
            continue
        if not blended:  # blend the faint layer once, before the first consistent line
            pics = cv2.addWeighted(faint, 0.45, pics, 0.55, 0)
            blended = True
        cv2.line(pics, a, b, GREEN, 2, cv2.LINE_AA)
        cv2.circle(pics, a, 4, GREEN, 2, cv2.LINE_AA)
        cv2.circle(pics, b, 4, GREEN, 2, cv2.LINE_AA)
    if not blended:
        pics = cv2.addWeighted(faint, 0.45, pics, 0.55, 0)
    W = pics.shape[1]
    font, scale, thick, line_h = cv2.FONT_HERSHEY_SIMPLEX, 0.55, 1, 22

    def band(columns: list[tuple[int, int, Sequence[str]]], n_lines: int) -> np.ndarray:
        img = np.full((line_h * n_lines + 10, W, 3), 255, np.uint8)
        for x0, x1, lines in columns:
            for k, text in enumerate(lines):
                while len(text) > 1 and cv2.getTextSize(text, font, scale, thick)[0][0] > x1 - x0 - 12:
                    text = text[:-2] + "~"  # shortened to fit its column
                cv2.putText(img, text, (x0 + 6, line_h * (k + 1)), font, scale, TEXT, thick, cv2.LINE_AA)
        return img

    head = band([(0, q.shape[1], left), (q.shape[1], W, right)], max(len(left), len(right)))
    foot_lines = list(bottom)
    foot = band([(0, W, foot_lines)], len(foot_lines) + (1 if verdict else 0))
    if verdict:
        text, ok = verdict
        colour = (0, 140, 0) if ok else (0, 0, 200) if ok is False else TEXT
        cv2.putText(foot, text, (6, line_h * (len(foot_lines) + 1)), font, scale, colour, 2, cv2.LINE_AA)
    return np.vstack([head, pics, foot])


def _place_image(maps: Sequence[Traverse], place: int, res: Resources, query_feats: Any, seed: int
                 ) -> tuple[Traverse, int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Among the map images of ``place``, the one with the most consistent correspondences."""
    best: tuple[Traverse, int, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
    for t in maps:
        idx = np.flatnonzero(t.places == place)
        if not len(idx):
            continue
        feats = res.features(t)
        for i in idx:
            corr = geometric_correspondences(query_feats, feats[i], seed=seed)
            if best is None or int(corr[2].sum()) > int(best[2][2].sum()):
                best = (t, int(i), corr)
    if best is None:
        raise input_error("the place has no image in the map traverses", str(place))
    return best


def labelled_match(
    method: PlaceRecognizer, query_image: Path, maps: Sequence[Traverse], *, resources: Resources,
    place: int | None = None, tolerance: int = 0,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Localise ``query_image`` with the fitted ``method`` and draw it against its best place (or ``place``).

    Returns
    -------
    canvas : ndarray of uint8, shape (H, W, 3)
    info : dict
        ``method``, ``query``, ``query_place``, ``place`` (drawn), ``best_place``, ``score``, ``rank``,
        ``n_places``, ``map_image``, ``n_consistent``, ``n_lines``, ``correct`` (None when the
        query's place is unknown).
    """
    qinfo = query_info(query_image)
    query = Traverse(root=query_image.parent, images=(query_image,), places=np.zeros(1, np.int64),
                     name=query_image.name)
    S = np.asarray(method.similarity(query, resources=resources), dtype=np.float64)[:, 0]
    ids = np.asarray(method.place_ids_)
    best_row = int(np.argmax(S))
    if place is None:
        row = best_row
    else:
        rows = np.flatnonzero(ids == place)
        if not len(rows):
            raise ParameterError("place", f"{place} is not a place of the map (places {ids.min()}..{ids.max()})")
        row = int(rows[0])
    drawn = int(ids[row])
    rank = int((S > S[row]).sum()) + 1
    qfeats = resources.features(query)[0]
    if isinstance(method, GroupMatcher) and row == best_row:
        g = method.consistent_group(query, resources=resources)
        t, i, (pq, pm, consistent) = group_correspondences(method, query, maps, resources=resources, group=g)
        how = f"{g.label} {g.symbol} (green) / same-word pairs outside {g.symbol} (red)"
    else:
        t, i, (pq, pm, consistent) = _place_image(maps, drawn, resources, qfeats, seed=0)
        how = "ratio-test matches: epipolar RANSAC inliers (green) / outliers (red)"
    mfeats = resources.features(t)[i]
    time_m = str(t.times[i]) if t.times is not None else None
    n_cons = int(consistent.sum())
    left = [f"QUERY  {qinfo.file}", f"time {qinfo.time}" if qinfo.time else "time: unknown",
            f"true place {qinfo.place}" if qinfo.place is not None else "true place: unknown"]
    right = [f"MAP  place {drawn}  ({'best match' if row == best_row else 'chosen with --place'})",
             f"tour {t.name}, file {t.images[i].name}", f"time {time_m}" if time_m else "time: unknown"]
    bottom = [f"{method.name}: score {S[row]:.4g}, rank {rank} of {len(S)} places"
              + (f" (best: place {int(ids[best_row])}, score {S[best_row]:.4g})" if row != best_row else ""),
              f"{n_cons} consistent correspondences of {len(pq)} drawn; {how}"]
    rank_note = getattr(method, "rank_note", None)
    note = rank_note(rank) if rank_note is not None else ""
    if note:
        bottom.append(note)
    correct = None
    verdict = None
    if qinfo.place is not None:
        d = abs(drawn - qinfo.place)
        correct = d <= tolerance
        verdict = (f"{'RIGHT' if correct else 'WRONG'}: drawn place {drawn}, true place {qinfo.place} "
                   f"({d} places apart, tolerance {tolerance})", correct)
    canvas = draw_labelled(frame_pixels(query, 0, qfeats.image_shape), frame_pixels(t, i, mfeats.image_shape),
                           pq, pm, consistent, left=left, right=right, bottom=bottom, verdict=verdict)
    info = {"method": method.name, "query": str(query_image), "query_place": qinfo.place, "place": drawn,
            "best_place": int(ids[best_row]), "score": float(S[row]), "rank": rank, "n_places": len(S),
            "map_image": str(t.images[i]), "n_consistent": n_cons, "n_lines": len(pq), "correct": correct}
    return canvas, info

