"""XFeat's sparse inference after the network, in NumPy and OpenCV, shared by every runtime.

The network (:mod:`topoloc.features.xfeat.runtimes`) gives, for a gray image
of ``H x W`` pixels (multiples of 32), three maps on the grid of 8 x 8 cells:
descriptors ``F`` (64, H/8, W/8), keypoint logits ``K`` (65, H/8, W/8) and
reliability ``R`` (1, H/8, W/8).  Sparse extraction (paper Sec. 3.3) then

1. turns the logits into a full-resolution heatmap ``h = softmax(K)[:64]``,
   the 64 values of a cell laid out row by row over its 8 x 8 pixels;
2. keeps the pixels that are the largest of their :data:`NMS_WINDOW`-square
   window and above the detection threshold;
3. scores each ``s(p) = h(p) * R(p)`` (``R`` sampled bilinearly) and keeps
   the ``max_features`` highest, ties in raster order;
4. samples the L2-normalised ``F`` bicubically at the kept positions and
   normalises again.

The sampling follows the reference inference's convention (PyTorch's
``grid_sample`` with ``align_corners=False`` on positions normalised by
``W - 1`` and ``H - 1``, zero outside the map, bicubic with ``A = -0.75``):
the weights were trained with it, so it is kept exactly, not "corrected".
Written once here, so that every runtime's raw maps become keypoints the same
way and runtimes differ only in the network's arithmetic.
"""

from __future__ import annotations

import cv2
import numpy as np

#: Side of the cells XFeat predicts keypoints in (its feature maps are at 1/8 of the input).
CELL = 8

#: Input sides are rounded down to multiples of this (the network downsamples five times).
STRIDE = 32

#: Non-maximum suppression window of the keypoint heatmap (the reference inference's 5 x 5).
NMS_WINDOW = 5

#: Descriptor columns.
DIM = 64

#: Version of the arithmetic below; part of the feature cache key (:func:`topoloc.features.learned.provenance`), so
#: that features computed by an earlier post-processing are never read as this one's.
VERSION = 1

_NMS_KERNEL = np.ones((NMS_WINDOW, NMS_WINDOW), np.uint8)


def network_size(height: int, width: int) -> tuple[int, int]:
    """The ``(height, width)`` the network describes an image of this size at: rounded down to :data:`STRIDE`."""
    return max(STRIDE, (height // STRIDE) * STRIDE), max(STRIDE, (width // STRIDE) * STRIDE)


def network_input(images: list[np.ndarray] | tuple[np.ndarray, ...], size: tuple[int, int]) -> np.ndarray:
    """Gray uint8 images of one shape as the network's input: float32 (B, 1, H, W) of ``size``, pixel values 0-255.

    Resized bilinearly with pixel centres aligned (OpenCV's ``INTER_LINEAR``,
    PyTorch's ``interpolate(..., align_corners=False)``) where ``size`` differs.
    """
    hh, ww = size
    out = np.empty((len(images), 1, hh, ww), np.float32)
    for i, im in enumerate(images):
        f = im.astype(np.float32)
        out[i, 0] = f if f.shape == (hh, ww) else cv2.resize(f, (ww, hh), interpolation=cv2.INTER_LINEAR)
    return out


def heatmap(logits: np.ndarray) -> np.ndarray:
    """Keypoint logits (65, h, w) -> full-resolution heatmap float32 (8h, 8w): softmax, "no keypoint" bin dropped."""
    z = logits - logits.max(axis=0, keepdims=True)
    e = np.exp(z, dtype=np.float32)
    p = e[:CELL * CELL] / e.sum(axis=0, dtype=np.float32)
    gh, gw = logits.shape[-2:]
    return np.ascontiguousarray(p.reshape(CELL, CELL, gh, gw).transpose(2, 0, 3, 1).reshape(gh * CELL, gw * CELL))


def local_maxima(heat: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, cols)`` of the pixels that are the largest of their window and above ``threshold``, raster order.

    OpenCV's dilation gives each window's maximum (the border's missing pixels
    ignored, as max pooling with padding does).
    """
    peak = cv2.dilate(heat, _NMS_KERNEL)
    rows, cols = np.nonzero((heat == peak) & (heat > threshold))
    return rows, cols


def _grid_coords(xy: np.ndarray, size: tuple[int, int], grid: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Pixel positions ``xy`` (n, 2) of an image of ``size`` as coordinates on a map of ``grid`` cells.

    The reference's normalisation (positions over ``W - 1``, ``H - 1``) followed
    by ``grid_sample``'s unnormalisation with ``align_corners=False``.
    """
    (hh, ww), (gh, gw) = size, grid
    u = xy[:, 0].astype(np.float64) / (ww - 1) * gw - 0.5
    v = xy[:, 1].astype(np.float64) / (hh - 1) * gh - 0.5
    return u, v


def _padded(values: np.ndarray, pad: int) -> np.ndarray:
    """``values`` (C, h, w) as (h + 2 pad, w + 2 pad, C) with zeros around: out-of-map taps read zero, as
    ``grid_sample``'s ``padding_mode="zeros"`` gives, without a test per tap."""
    c, h, w = values.shape
    out = np.zeros((h + 2 * pad, w + 2 * pad, c), np.float32)
    out[pad:pad + h, pad:pad + w] = values.transpose(1, 2, 0)
    return out


def _gather(values: np.ndarray, xy: np.ndarray, size: tuple[int, int], taps: int) -> tuple[np.ndarray, ...]:
    """The ``taps x taps`` map values around each position: (n, taps, taps, C), and the fractions ``tx``, ``ty``.

    Positions lie inside the image, so their taps lie at most ``taps // 2``
    cells outside the map, inside the zero border.
    """
    pad = taps // 2
    u, v = _grid_coords(xy, size, values.shape[-2:])
    x0, y0 = np.floor(u), np.floor(v)
    first = 1 - taps // 2  # offset of the first tap from the cell at or left of / above the position
    hp, wp = values.shape[1] + 2 * pad, values.shape[2] + 2 * pad
    cols = np.clip(x0.astype(np.intp)[:, None] + np.arange(first, first + taps) + pad, 0, wp - 1)
    rows = np.clip(y0.astype(np.intp)[:, None] + np.arange(first, first + taps) + pad, 0, hp - 1)
    grid = _padded(values, pad)[rows[:, :, None], cols[:, None, :]]
    return grid, u - x0, v - y0


def sample_bilinear(values: np.ndarray, xy: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Map ``values`` (C, h, w) sampled bilinearly at pixel positions ``xy`` (n, 2) of a ``size`` image -> (n, C)."""
    grid, tx, ty = _gather(values, xy, size, 2)
    tx, ty = tx[:, None].astype(np.float32), ty[:, None].astype(np.float32)
    top = grid[:, 0, 0] * (1 - tx) + grid[:, 0, 1] * tx
    bottom = grid[:, 1, 0] * (1 - tx) + grid[:, 1, 1] * tx
    return (top * (1 - ty) + bottom * ty).astype(np.float32)


def _cubic_weights(t: np.ndarray, a: float = -0.75) -> np.ndarray:
    """Keys' cubic convolution weights of the 4 taps around a fraction ``t`` (n,) -> (n, 4)."""
    d = np.stack([1 + t, t, 1 - t, 2 - t], axis=1)
    near = ((a + 2) * d - (a + 3)) * d * d + 1  # |d| <= 1
    far = ((a * d - 5 * a) * d + 8 * a) * d - 4 * a  # 1 < |d| < 2
    return np.where(d <= 1, near, far)


def sample_bicubic(values: np.ndarray, xy: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Map ``values`` (C, h, w) sampled bicubically at pixel positions ``xy`` (n, 2) of a ``size`` image -> (n, C)."""
    c, h, w = values.shape
    u, v = _grid_coords(xy, size, (h, w))
    x0, y0 = np.floor(u), np.floor(v)
    pad = 2  # the 4 x 4 taps reach 1 cell before and 2 after the position's cell
    flat = _padded(values, pad).reshape(-1, c)
    wp = w + 2 * pad
    first = (y0.astype(np.intp) - 1 + pad) * wp + (x0.astype(np.intp) - 1 + pad)
    taps = np.clip(first[:, None] + (np.arange(4)[:, None] * wp + np.arange(4)).ravel(), 0, len(flat) - 1)
    weights = (_cubic_weights(v - y0)[:, :, None] * _cubic_weights(u - x0)[:, None, :]).reshape(-1, 16)
    return np.einsum("nk,nkc->nc", weights.astype(np.float32), flat[taps])


def normalise_rows(x: np.ndarray, axis: int) -> np.ndarray:
    """``x`` divided by its L2 norm along ``axis`` (at least 1e-12, as PyTorch's ``normalize``), float32."""
    norm = np.sqrt((x * x).sum(axis=axis, keepdims=True))
    return (x / np.maximum(norm, np.float32(1e-12))).astype(np.float32)


def sparse_features(
    descriptors: np.ndarray, logits: np.ndarray, reliability: np.ndarray, *,
    size: tuple[int, int], max_features: int, detection_threshold: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One image's network maps -> ``(xy, score, descriptors)`` at the network's resolution, strongest first.

    Parameters
    ----------
    descriptors, logits, reliability : ndarray of float32
        The network's maps for one image: (64, h, w), (65, h, w), (1, h, w).
    size : (int, int)
        ``(H, W)`` of the network's input (``8h``, ``8w``).
    max_features : int
        Keypoints kept, highest score first.
    detection_threshold : float
        Smallest heatmap value of a keypoint.

    Returns
    -------
    xy : ndarray of float32, shape (n, 2)
        Positions (x, y) in pixels of the network's input.
    score : ndarray of float32, shape (n,)
    descriptors : ndarray of float32, shape (n, 64), unit rows
    """
    heat = heatmap(logits)
    rows, cols = local_maxima(heat, detection_threshold)
    if len(rows) == 0:
        return np.empty((0, 2), np.float32), np.empty(0, np.float32), np.empty((0, DIM), np.float32)
    pos = np.stack([cols, rows], axis=1).astype(np.float32)
    score = heat[rows, cols] * sample_bilinear(reliability, pos, size)[:, 0]
    # Highest score first; ties broken by raster order (nonzero's order), so the output is deterministic.
    order = np.argsort(-score, kind="stable")[:max_features]
    pos, score = pos[order], score[order]
    dense = normalise_rows(descriptors, axis=0)
    desc = normalise_rows(sample_bicubic(dense, pos, size), axis=1)
    return pos, score.astype(np.float32), desc
