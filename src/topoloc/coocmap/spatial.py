"""Spatial words: quantisation of feature pairs in image space (Cooc-Map, Sec. II-A).

Johns & Yang (ICRA 2013), Sec. II-A and III-B: "images were spatially quantised
into 12 x 8 = 96 squares in image space.  Features can appear both above and
below each other, and to the right and left of each other, and as such the size
of the spatial dictionary is 96 x 4 = 384 spatial words".  Sec. IV adds that the
method "considers only the spatial relationships between feature pairs - not
their absolute position on an image".

Our reading
-----------
The spatial word of the *ordered* pair (a -> b) describes where ``b`` lies
relative to ``a``.  With the displacement ``(dx, dy) = xy_b - xy_a`` in pixels
of an image of width ``W`` and height ``H``:

* the *square* is the cell of the regular ``grid_x x grid_y`` grid over the
  image that the absolute displacement falls in:
  ``cx = min(floor(|dx| * grid_x / W), grid_x - 1)``,
  ``cy = min(floor(|dy| * grid_y / H), grid_y - 1)``
  (a displacement spans at most the image, so the grid over the image covers
  every offset magnitude; 12 x 8 cells on a 640 x 480 image are ~53 x 60 px);
* the *quadrant* says whether ``b`` is to the right (``dx > 0``) or left, and
  below (``dy > 0``, image rows grow downwards) or above ``a``: 4 relations;
* ``spatial_word = quadrant * (grid_x * grid_y) + cy * grid_x + cx`` with
  ``quadrant = 2 * below + right``, i.e. ``4 * grid_x * grid_y`` words (384).

Ties (``dx == 0`` or ``dy == 0``) are broken lexicographically (``right`` is
``dx > 0 or (dx == 0 and dy > 0)``, ``below`` is ``dy > 0 or (dy == 0 and
dx > 0)``) so that reversing a pair flips *both* relations and keeps the square:
``word(b -> a)`` is ``word(a -> b)`` with the opposite quadrant, for every pair
except two features at the very same position.  Consistency of two
correspondences therefore does not depend on which one is called first.

Positions are first mapped to a resolution-independent integer frame
(:func:`normalise_xy`, 16 bits per axis), which also makes a location model
compact (two ``uint16`` per feature) and independent of the image size.
"""

from __future__ import annotations

import numpy as np

#: Normalised coordinates run over ``[0, NORM)`` along each image axis.
NORM_BITS = 16
NORM = 1 << NORM_BITS


def n_spatial_words(grid_x: int, grid_y: int) -> int:
    """Size of the spatial dictionary, ``4 * grid_x * grid_y`` (384 for 12 x 8)."""
    return 4 * int(grid_x) * int(grid_y)


def normalise_xy(xy: np.ndarray, image_shape: tuple[int, int]) -> np.ndarray:
    """Map pixel positions to the 16-bit normalised image frame.

    Parameters
    ----------
    xy : ndarray, shape (n, 2)
        Keypoint ``x, y`` in pixels (OpenCV convention: centre of the top-left
        pixel at 0).
    image_shape : (int, int)
        ``(height, width)`` of the image.

    Returns
    -------
    ndarray of uint16, shape (n, 2)
        ``floor((x + 0.5) / W * 65536)`` and likewise for ``y``, clipped to
        ``[0, 65535]``.
    """
    h, w = int(image_shape[0]), int(image_shape[1])
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    scale = np.array([NORM / max(w, 1), NORM / max(h, 1)])
    q = np.floor((xy + 0.5) * scale)
    return np.clip(q, 0, NORM - 1).astype(np.uint16)


def spatial_words(
    xy_a: np.ndarray, xy_b: np.ndarray, *, grid_x: int = 12, grid_y: int = 8
) -> np.ndarray:
    """Spatial word of each ordered pair ``a -> b`` (Sec. II-A, III-B).

    Parameters
    ----------
    xy_a, xy_b : ndarray of uint16/int, shape (..., 2)
        Normalised positions (:func:`normalise_xy`) of the first and second
        feature of each pair; broadcast against each other.
    grid_x, grid_y : int
        Squares across and down the image (paper: 12 x 8).

    Returns
    -------
    ndarray of int16, shape (...)
        Ids in ``[0, 4 * grid_x * grid_y)``; see the module docstring.
    """
    a = np.asarray(xy_a, dtype=np.int32)
    b = np.asarray(xy_b, dtype=np.int32)
    dx = b[..., 0] - a[..., 0]
    dy = b[..., 1] - a[..., 1]
    return _words_from_offsets(dx, dy, grid_x, grid_y)


def _words_from_offsets(dx: np.ndarray, dy: np.ndarray, grid_x: int, grid_y: int) -> np.ndarray:
    # |d| < 2^16 and grid < 2^15, so the products fit int32 without overflow.
    cx = np.minimum((np.abs(dx) * grid_x) >> NORM_BITS, grid_x - 1)
    cy = np.minimum((np.abs(dy) * grid_y) >> NORM_BITS, grid_y - 1)
    right = (dx > 0) | ((dx == 0) & (dy > 0))
    below = (dy > 0) | ((dy == 0) & (dx > 0))
    quadrant = 2 * below.astype(np.int32) + right.astype(np.int32)
    return (quadrant * (grid_x * grid_y) + cy * grid_x + cx).astype(np.int16)


def pair_word_matrix(xy: np.ndarray, *, grid_x: int = 12, grid_y: int = 8) -> np.ndarray:
    """Spatial words of all ordered pairs of one image's features.

    Parameters
    ----------
    xy : ndarray of uint16, shape (n, 2)
        Normalised positions.

    Returns
    -------
    ndarray of int16, shape (n, n)
        Element ``[i, j]`` is the spatial word of ``i -> j``.
    """
    p = np.asarray(xy, dtype=np.int32).reshape(-1, 2)
    return _words_from_offsets(p[None, :, 0] - p[:, None, 0], p[None, :, 1] - p[:, None, 1],
                               grid_x, grid_y)


def signed_cells(dx: np.ndarray, dy: np.ndarray, grid_x: int, grid_y: int) -> tuple[np.ndarray, np.ndarray]:
    """The spatial word as signed grid coordinates ``(sx, sy)``.

    ``sx = cx`` to the right and ``-cx - 1`` to the left (likewise ``sy`` with
    below/above), a bijection with the spatial words of
    :func:`spatial_words` in which neighbouring squares, also across the
    left/right or above/below boundary, differ by 1.  Used for the optional
    tolerance ``|sx - sx'| <= t and |sy - sy'| <= t`` (``t = 0`` is equality
    of spatial words, the paper).

    Parameters
    ----------
    dx, dy : ndarray of int32
        Offsets ``b - a`` in normalised units.

    Returns
    -------
    sx, sy : ndarray of int8, same shape
    """
    cx = np.minimum((np.abs(dx) * grid_x) >> NORM_BITS, grid_x - 1)
    cy = np.minimum((np.abs(dy) * grid_y) >> NORM_BITS, grid_y - 1)
    right = (dx > 0) | ((dx == 0) & (dy > 0))
    below = (dy > 0) | ((dy == 0) & (dx > 0))
    return (np.where(right, cx, -cx - 1).astype(np.int8),
            np.where(below, cy, -cy - 1).astype(np.int8))


def pair_cell_matrices(xy: np.ndarray, *, grid_x: int = 12,
                       grid_y: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """:func:`signed_cells` of all ordered pairs of one image, each (n, n) int8."""
    p = np.asarray(xy, dtype=np.int32).reshape(-1, 2)
    return signed_cells(p[None, :, 0] - p[:, None, 0], p[None, :, 1] - p[:, None, 1], grid_x, grid_y)


def flip_word(word: np.ndarray, *, grid_x: int = 12, grid_y: int = 8) -> np.ndarray:
    """The spatial word of the reversed pair (opposite quadrant, same square).

    Exact for every pair of distinct positions (see the tie rule above).
    """
    cells = grid_x * grid_y
    w = np.asarray(word, dtype=np.int32)
    return ((3 - w // cells) * cells + w % cells).astype(np.int16)
