"""The "traditional" image-per-node topological map: feature voting (Johns & Yang 2011, Sec. VIII).

Every map image is a node.  Each query feature is matched to every map image
with Lowe's ratio test (nearest over second-nearest descriptor distance in
that image below ``ratio``); the matches to an image are pruned by estimating
the epipolar geometry with RANSAC, and the number of surviving matches (the
inliers) is the image's vote.  As in Ramisa et al. (ICRA 2008), the method the
paper compares against.

Matching to every image at once uses one faiss index over all map descriptors
with the image id of each row: the ``n_neighbours`` nearest map descriptors of
a query feature are grouped by image, and within an image the first two give
``d1`` and ``d2``.  An image with a single descriptor among them has
``d2 >= d_K`` (the farthest of the ``n_neighbours``), so its ratio is bounded
by ``d1 / d_K``; an image with none has ``d1 >= d_K`` and is not matched by
this feature (approximation: such a match would be among the weakest).
RANSAC runs only on the ``n_verify`` images with most ratio-test matches;
the others score their ratio-test match count divided by ``min_matches``
capped below one vote, 0 without matches.

Pure functions on descriptor and keypoint-position arrays;
:class:`topoloc.methods.image_voting.ImageVoting` is the recogniser (several
map images of one place: the maximum of their votes).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import faiss
import numpy as np

from topoloc.geometry import epipolar_inliers, normalise_descriptors


@dataclass(frozen=True, eq=False)
class DescriptorIndex:
    """All map descriptors in one faiss index, with the image and position of each row.

    Attributes
    ----------
    index : faiss.IndexFlatL2
        Unit-normalised descriptors of every map image, image after image.
    desc_image : ndarray of int64, shape (n_descriptors,)
        Map image of every indexed descriptor.
    desc_xy : ndarray of float32, shape (n_descriptors, 2)
        Keypoint position of every indexed descriptor (pixels).
    n_images : int
        Number of map images (images without features included).
    """

    index: faiss.IndexFlatL2
    desc_image: np.ndarray
    desc_xy: np.ndarray
    n_images: int


def build_index(descriptors: Sequence[np.ndarray], xy: Sequence[np.ndarray]) -> DescriptorIndex:
    """Index the descriptors of every map image.

    Parameters
    ----------
    descriptors : sequence of ndarray, shape (n_i, d)
        Descriptors of each map image (any real dtype; unit-normalised here).
    xy : sequence of ndarray, shape (n_i, 2)
        Keypoint positions of each map image, row for row.

    Returns
    -------
    DescriptorIndex
        The index has dimension ``d`` (128 when no image has a feature).
    """
    if len(descriptors) != len(xy):
        raise ValueError(f"{len(descriptors)} descriptor arrays but {len(xy)} position arrays")
    counts = np.array([len(d) for d in descriptors], np.int64)
    desc_image = np.repeat(np.arange(len(descriptors), dtype=np.int64), counts)
    desc_xy = (np.concatenate(list(xy)).astype(np.float32)
               if counts.sum() else np.zeros((0, 2), np.float32))
    descs = [normalise_descriptors(d) for d in descriptors if len(d)]
    dim = descs[0].shape[1] if descs else 128
    index = faiss.IndexFlatL2(dim)
    if descs:
        index.add(np.ascontiguousarray(np.concatenate(descs)))
    return DescriptorIndex(index=index, desc_image=desc_image, desc_xy=desc_xy, n_images=len(descriptors))


def merge_indexes(descriptors: Sequence[np.ndarray], counts: Sequence[np.ndarray], xy: Sequence[np.ndarray],
                  order: np.ndarray) -> DescriptorIndex:
    """One index from the indexed images of several partial maps (shards), images in map order.

    Parameters
    ----------
    descriptors : sequence of ndarray of float32, shape (n_k, d)
        Each part's unit-normalised descriptors, image after image.
    counts : sequence of ndarray of int64, shape (m_k,)
        Descriptors of each of the part's ``m_k`` images.
    xy : sequence of ndarray of float32, shape (n_k, 2)
        Their keypoint positions.
    order : ndarray of int64, shape (sum m_k,)
        Image ``j`` of the result is image ``order[j]`` of the parts' images in order.

    Returns
    -------
    DescriptorIndex
        Equal, row for row, to :func:`build_index` over the images in map order
        (normalisation is per row, so it commutes with the reordering).
    """
    n = np.concatenate([np.asarray(c, np.int64) for c in counts])[order]
    starts = np.r_[0, np.cumsum(np.concatenate([np.asarray(c, np.int64) for c in counts]))][:-1][order]
    offsets = np.cumsum(n) - n
    rows = np.repeat(starts - offsets, n) + np.arange(int(n.sum()), dtype=np.int64)
    blocks = [np.asarray(d, np.float32) for d in descriptors if len(d)]
    desc = np.concatenate(blocks) if blocks else np.zeros((0, 128), np.float32)
    index = faiss.IndexFlatL2(desc.shape[1])
    if len(rows):
        index.add(np.ascontiguousarray(desc[rows]))
    all_xy = np.concatenate([np.asarray(a, np.float32).reshape(-1, 2) for a in xy])
    return DescriptorIndex(index=index, desc_image=np.repeat(np.arange(len(n), dtype=np.int64), n),
                           desc_xy=all_xy[rows], n_images=len(n))


def ratio_matches(
    index: DescriptorIndex, descriptors: np.ndarray, *, ratio: float = 0.8, n_neighbours: int = 16,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ratio-test matches of one query image's features to every map image.

    Parameters
    ----------
    index : DescriptorIndex
        The map (:func:`build_index`).
    descriptors : ndarray, shape (n_q, d)
        Query descriptors (unit-normalised here).
    ratio : float
        Lowe's threshold on ``d1 / d2`` (distances).
    n_neighbours : int
        Nearest map descriptors fetched per query feature (see module docstring).

    Returns
    -------
    query_rows, map_rows, map_images : ndarray of int64, shape (n_matches,)
        Query feature, indexed map descriptor and its map image of every
        match; at most one match per query feature and map image.
    """
    if len(descriptors) == 0 or index.index.ntotal == 0:
        empty = np.zeros(0, np.int64)
        return empty, empty.copy(), empty.copy()
    k = min(n_neighbours, index.index.ntotal)
    dist2, nn = index.index.search(normalise_descriptors(descriptors), k)
    d = np.sqrt(np.maximum(dist2, 0.0))
    img = index.desc_image[nn]  # (n_q, k)
    n_q = len(descriptors)
    # First and second occurrence of each image in every query's sorted neighbour list.
    key = np.arange(n_q)[:, None] * index.n_images + img
    flat_key = key.ravel()
    order = np.argsort(flat_key, kind="stable")  # stable keeps the distance order per image
    sk = flat_key[order]
    first = np.r_[True, sk[1:] != sk[:-1]]
    second = np.r_[False, ~first[1:]] & np.r_[False, first[:-1]]
    pos1 = order[first]
    d1 = d.ravel()[pos1]
    d2 = np.full(len(pos1), np.nan)
    grp = np.cumsum(first) - 1
    d2[grp[second]] = d.ravel()[order[second]]
    # No second descriptor of this image among the k: d2 >= d_K bounds the ratio.
    d_k = d[:, -1].repeat(k)[pos1]
    denom = np.where(np.isnan(d2), d_k, d2)
    ok = d1 < ratio * denom
    return pos1[ok] // k, nn.ravel()[pos1[ok]], img.ravel()[pos1[ok]]


def image_votes(
    index: DescriptorIndex,
    xy: np.ndarray,
    descriptors: np.ndarray,
    *,
    ratio: float = 0.8,
    n_neighbours: int = 16,
    n_verify: int = 10,
    ransac_px: float = 3.0,
    min_matches: int = 8,
) -> np.ndarray:
    """Votes of every map image for one query image.

    Parameters
    ----------
    index : DescriptorIndex
        The map (:func:`build_index`).
    xy : ndarray, shape (n_q, 2)
        Query keypoint positions (pixels).
    descriptors : ndarray, shape (n_q, d)
        Query descriptors, row for row with ``xy``.
    ratio, n_neighbours
        See :func:`ratio_matches`.
    n_verify : int
        Map images (most ratio-test matches first) verified by RANSAC.
    ransac_px : float
        Largest distance of a point from its epipolar line (pixels).
    min_matches : int
        Images with fewer ratio-test matches get no RANSAC and score their
        match count divided by ``min_matches`` (< 1 inlier-vote).

    Returns
    -------
    ndarray of float64, shape (n_images,)
        RANSAC inliers of the verified images, the capped match fraction of
        the others; all 0 for a query or a map without features.
    """
    votes = np.zeros(index.n_images, np.float64)
    if len(descriptors) == 0 or index.index.ntotal == 0:
        return votes
    q_idx, m_idx, m_img = ratio_matches(index, descriptors, ratio=ratio, n_neighbours=n_neighbours)
    counts = np.bincount(m_img, minlength=index.n_images).astype(np.float64)
    votes[:] = np.minimum(counts, min_matches - 1) / min_matches
    cand = np.argsort(-counts, kind="stable")[:n_verify]
    cand = cand[counts[cand] >= min_matches]
    order = np.argsort(m_img, kind="stable")
    lo = np.searchsorted(m_img[order], cand, "left")
    hi = np.searchsorted(m_img[order], cand, "right")
    for c, a, b in zip(cand, lo, hi, strict=True):
        sel = order[a:b]
        inl = epipolar_inliers(xy[q_idx[sel]], index.desc_xy[m_idx[sel]],
                               ransac_px=ransac_px, min_matches=min_matches, seed=int(c))
        votes[c] = float(inl.sum())
    return votes
