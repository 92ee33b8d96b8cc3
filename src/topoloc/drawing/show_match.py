"""Match drawings as in the Cooc-Map paper's Fig. 1 and 5 (``topoloc show-match``).

The query image is drawn beside a training image of the best location with a
line for every correspondence of the final consistent group ``K``, which the
method declares (:meth:`~topoloc.methods.cooc_map.CoocMap.consistent_group`,
a :class:`~topoloc.methods.cooc_map.FeatureGroup`; any recogniser with that
method is drawn the same way).  The model stores no images or per-tour
feature lists, so the training image is taken from the map traverses: among
the images of the best place, the one whose features contain the most words
of ``K``; each query feature of ``K`` is joined to the feature of the same
word in that image whose offset is closest to the median offset of all
same-word pairs (a drawing aid only; matching never uses it).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np

from topoloc.datasets.traverse import Traverse, load_traverse
from topoloc.errors import input_error
from topoloc.io.container import atomic_write_bytes
from topoloc.io.dirs import signed_png
from topoloc.io.paths import through_link
from topoloc.methods.cooc_map import CoocMap, FeatureGroup
from topoloc.resources import Resources


@runtime_checkable
class GroupMatcher(Protocol):
    """A fitted recogniser that says which query features made its match (Cooc-Map's ``K``)."""

    place_ids_: np.ndarray
    resources_: Resources

    def consistent_group(self, query: Traverse, *, index: int = 0,
                         resources: Resources | None = None) -> FeatureGroup: ...


def draw_correspondences(query_bgr: np.ndarray, map_bgr: np.ndarray, pts_query: np.ndarray,
                         pts_map: np.ndarray, *, seed: int = 0) -> np.ndarray:
    """Side-by-side image with one coloured line per correspondence.

    Parameters
    ----------
    query_bgr, map_bgr : ndarray of uint8, shape (H, W, 3)
    pts_query, pts_map : ndarray of float, shape (k, 2)
        Pixel positions in each image.

    Returns
    -------
    ndarray of uint8, shape (H', Wq' + Wm', 3)
        Both images scaled to the height of the taller one.
    """
    h = max(query_bgr.shape[0], map_bgr.shape[0])
    sq, sm = h / query_bgr.shape[0], h / map_bgr.shape[0]
    q = cv2.resize(query_bgr, (round(query_bgr.shape[1] * sq), h))
    m = cv2.resize(map_bgr, (round(map_bgr.shape[1] * sm), h))
    canvas = np.hstack([q, m])
    colours = np.random.default_rng(seed).integers(64, 256, (len(pts_query), 3))
    for (xq, yq), (xm, ym), c in zip(pts_query * sq, pts_map * sm, colours, strict=True):
        a = (round(float(xq)), round(float(yq)))
        b = (round(float(xm)) + q.shape[1], round(float(ym)))
        col = tuple(int(v) for v in c)
        cv2.line(canvas, a, b, col, 1, cv2.LINE_AA)
        cv2.circle(canvas, a, 4, col, 2, cv2.LINE_AA)
        cv2.circle(canvas, b, 4, col, 2, cv2.LINE_AA)
    return canvas


def _pair_up(qw: np.ndarray, qxy: np.ndarray, mw: np.ndarray, mxy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each query feature, the same-word map feature nearest the median offset."""
    same = qw[:, None] == mw[None, :]
    if not same.any():
        return np.zeros((0, 2)), np.zeros((0, 2))
    off = mxy[None, :, :] - qxy[:, None, :]
    med = np.median(off[same], axis=0)
    dist = np.where(same, np.linalg.norm(off - med, axis=2), np.inf)
    j = np.argmin(dist, axis=1)
    ok = np.isfinite(dist[np.arange(len(qw)), j])
    return qxy[ok], mxy[j[ok]]


def frame_pixels(traverse: Traverse, index: int, shape: tuple[int, int]) -> np.ndarray:
    """The image to draw on: its pixels, or a white canvas of its size for a traverse of features."""
    if traverse.kind in ("files", "images"):
        return traverse.read(index, gray=False)
    return np.full((*shape, 3), 255, np.uint8)


@dataclass
class _GroupMatch:
    """One query's declared group, with the map image of its best place that holds most words of the group."""

    words: np.ndarray
    kp: np.ndarray
    shape: tuple[int, int]
    group: np.ndarray
    place: int
    score: float
    map_ref: tuple[Traverse, int]
    map_words: np.ndarray
    map_kp: np.ndarray
    map_shape: tuple[int, int]


def _group_match(method: GroupMatcher, query: Traverse, maps: Sequence[Traverse], index: int,
                 resources: Resources | None, g: FeatureGroup | None = None) -> _GroupMatch:
    if g is None:
        g = method.consistent_group(query, index=index, resources=resources)
    res = resources if resources is not None else method.resources_
    fs = res.features(query)[index]
    k = g.used
    words, group = g.words, g.group
    kp = fs.keypoints[:k, :2]
    place = int(method.place_ids_[g.row])
    # The training image of the best place holding the most words of K.
    best_ref, best_hits, best_feats = None, -1, None
    for t in maps:
        feats = res.features(t)
        tw = res.words(t)
        for i in np.flatnonzero(t.places == place):
            hits = int(np.isin(words[group], tw[i][:k]).sum())
            if hits > best_hits:
                best_ref, best_hits, best_feats = (t, int(i)), hits, (tw[i][:k], feats[i])
    if best_ref is None or best_feats is None:
        raise input_error("the best place has no image in the map traverses", str(place))
    return _GroupMatch(words=words, kp=kp.astype(np.float64), shape=fs.image_shape, group=group, place=place,
                       score=g.score, map_ref=best_ref,
                       map_words=np.asarray(best_feats[0]),
                       map_kp=best_feats[1].keypoints[:k, :2].astype(np.float64),
                       map_shape=best_feats[1].image_shape)


def match_drawing(
    method: CoocMap, query: Traverse, maps: Sequence[Traverse], *, index: int = 0,
    resources: Resources | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Localise image ``index`` of ``query`` and draw it beside its best match (Fig. 1 / 5 of the paper).

    Parameters
    ----------
    method : CoocMap
        Fitted on ``maps``.
    query : Traverse
        Holds the query image (files, an in-memory image or its features).
    maps : sequence of Traverse
        The map traverses ``method`` was fitted on (the model keeps no images).
    index : int
        Which image of ``query``.
    resources : Resources, optional
        Default: the ones ``method`` was fitted with.

    Returns
    -------
    canvas : ndarray of uint8, shape (H, W, 3)
    info : dict
        ``best_place``, ``score`` (size of ``K``), ``map_image`` (the training
        image drawn), ``n_lines``.
    """
    m = _group_match(method, query, maps, index, resources)
    pq, pm = _pair_up(m.words[m.group], m.kp[m.group], m.map_words, m.map_kp)
    canvas = draw_correspondences(frame_pixels(query, index, m.shape),
                                  frame_pixels(m.map_ref[0], m.map_ref[1], m.map_shape), pq, pm, seed=method.seed)
    return canvas, {"best_place": m.place, "score": m.score,
                    "map_image": str(m.map_ref[0].images[m.map_ref[1]]), "n_lines": len(pq)}


def group_correspondences(
    method: GroupMatcher, query: Traverse, maps: Sequence[Traverse], *, index: int = 0,
    resources: Resources | None = None, group: FeatureGroup | None = None,
) -> tuple[Traverse, int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The map image of the best place drawn by :func:`match_drawing` and its correspondences.

    ``method`` is any fitted recogniser that declares ``consistent_group`` (:class:`GroupMatcher`);
    ``group`` is what it returned for this image, when already at hand.

    Returns
    -------
    traverse, image index : the map image (the best place's image with the most words of ``K``)
    (pts_query, pts_map, in_group) : pixel positions of the same-word pairs of the query and that image
        (each query feature to the same-word map feature nearest the median offset) and whether the
        query feature is in the final consistent group ``K``.
    """
    m = _group_match(method, query, maps, index, resources, group)
    in_group = np.zeros(len(m.words), bool)
    in_group[m.group] = True
    # Pair every query feature whose word the image has; K's pairs as match_drawing pairs them.
    pq_k, pm_k = _pair_up(m.words[m.group], m.kp[m.group], m.map_words, m.map_kp)
    rest = ~in_group & np.isin(m.words, m.map_words)
    pq_o, pm_o = _pair_up(m.words[rest], m.kp[rest], m.map_words, m.map_kp)
    pq, pm = np.vstack([pq_k, pq_o]), np.vstack([pm_k, pm_o])
    consistent = np.r_[np.ones(len(pq_k), bool), np.zeros(len(pq_o), bool)]
    return m.map_ref[0], m.map_ref[1], (pq, pm, consistent)


def show_match(query_image: str | Path, map_dirs: Sequence[str | Path], out_png: str | Path, *,
               resources: Resources, method: CoocMap | None = None,
               **params: Any) -> dict[str, Any]:
    """Localise one image file against map folders and write the drawing of :func:`match_drawing`.

    Parameters
    ----------
    query_image : path
        The query image.
    map_dirs : sequence of paths
        The map traverses (tours).
    out_png : path
        Where to write the drawing.
    resources : Resources
        Feature extractor and vocabulary.
    method : CoocMap, optional
        A method already fitted on ``map_dirs``; else one is built with ``params``.

    Returns
    -------
    dict
        ``best_place``, ``score``, ``map_image``, ``n_lines``, ``out``.
    """
    maps = [load_traverse(d) for d in map_dirs]
    if method is None:
        method = CoocMap(**params).fit(maps, resources=resources)
    path = Path(query_image)
    query = Traverse(root=path.parent, images=(path,), places=np.zeros(1, np.int64), name=path.name)
    canvas, info = match_drawing(method, query, maps, resources=resources)
    out = Path(out_png)
    write_png(canvas, out)
    return {**info, "out": str(out)}


def write_png(canvas: np.ndarray, out: Path) -> None:
    """Write ``canvas`` as a PNG atomically, signed ``Software: topoloc`` (so that a later run may replace it).

    ``out`` named through a symbolic link is written where the link points (the link kept).
    """
    ok, buf = cv2.imencode(".png", canvas)
    if not ok:
        raise input_error("could not encode the drawing", out)
    out = through_link(Path(out))
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out, signed_png(buf.tobytes()))

