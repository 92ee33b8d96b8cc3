"""SeqSLAM's image preprocessing: grey, downsample, patch-normalise, quantise (Milford & Wyeth, ICRA 2012).

Patch normalisation follows OpenSeqSLAM's ``patchNormalize.m``; the
quantisation keeps ``levels_per_std`` grey levels per standard deviation
(``1`` is the original release's rounding), see
:mod:`topoloc.methods.seq_slam` for why.

*Frames without structure.*  A patch without spread (uniform, black,
saturated) has no z-scores and becomes 0, so a uniform, dark, overexposed or
featureless frame becomes (almost) the zero image, the centre of all
normalised images.  Its mean absolute difference to any image is that
image's mean ``|z|`` (about 0.8), while two images of the same place in
different seasons differ by about 0.87 on Nordland: such a frame is nearer
to every query than its true place, a "hub".  (OpenSeqSLAM leaves ``0 / 0``
as NaN, which MATLAB's ``uint8`` turns into 0, i.e. ``z = -127``: the opposite
extreme, far from everything.)  No single value for a structureless patch is
neutral under the L1 difference, so the representation is unchanged and the
hub is contained where a frame can do harm, in the sequence search: a single
image is one of the ``ds + 1`` frames of any trajectory, including at the
start of the route (see "Start of the database" in
:mod:`topoloc.sequence.search`, issue #12).
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from topoloc.datasets.decode import to_gray


@lru_cache(maxsize=16)
def _patch_labels(height: int, width: int, patch_size: int) -> tuple[np.ndarray, int]:
    """Patch index of every pixel (row-major), and the number of patches."""
    ny = -(-height // patch_size)
    nx = -(-width // patch_size)
    yy, xx = np.mgrid[0:height, 0:width]
    labels = (yy // patch_size) * nx + (xx // patch_size)
    labels.setflags(write=False)
    return labels.ravel(), ny * nx


def patch_normalize(img: np.ndarray, patch_size: int = 8) -> np.ndarray:
    """Patch normalisation of SeqSLAM (OpenSeqSLAM ``patchNormalize.m``, mode 1).

    Every ``patch_size x patch_size`` patch is standardised to zero mean and
    unit sample standard deviation (``ddof=1``, MATLAB's ``std``), which
    removes local brightness and contrast (day/night, season, exposure).
    Vectorised with one ``bincount`` per statistic; patches cut by the image
    border are normalised on their own pixels (the release leaves them raw).
    Patches without spread become 0.

    Parameters
    ----------
    img : ndarray, shape (H, W)
        Grey image.
    patch_size : int
        Side of the patches, >= 2.

    Returns
    -------
    ndarray of float64, shape (H, W)
        Normalised intensities ``z``.
    """
    if img.ndim != 2:
        raise ValueError(f"expected a grey image (H, W), got shape {img.shape}")
    if patch_size < 2:
        raise ValueError(f"patch_size must be >= 2, got {patch_size}")
    h, w = img.shape
    labels, n_patches = _patch_labels(h, w, int(patch_size))
    x = img.astype(np.float64).ravel()
    cnt = np.bincount(labels, minlength=n_patches).astype(np.float64)
    s1 = np.bincount(labels, weights=x, minlength=n_patches)
    mean = s1 / cnt
    d = x - mean[labels]
    ss = np.bincount(labels, weights=d * d, minlength=n_patches)
    std = np.sqrt(ss / np.maximum(cnt - 1.0, 1.0))
    ok = (cnt >= 2) & (std > 1e-9)
    inv = np.where(ok, 1.0 / np.where(ok, std, 1.0), 0.0)
    return (d * inv[labels]).reshape(h, w)


def preprocess_image(
    img: np.ndarray,
    *,
    width: int = 64,
    height: int = 32,
    patch_size: int = 8,
    levels_per_std: float = 16.0,
) -> np.ndarray:
    """SeqSLAM's image preprocessing: grey, downsample, patch-normalise, quantise.

    Parameters
    ----------
    img : ndarray of uint8, shape (H, W) or (H, W, 3) BGR
    width, height : int
        Size after downsampling (area interpolation when shrinking, which
        averages like MATLAB's antialiased ``imresize``; linear when growing).
    patch_size : int
        Patch normalisation side; ``0`` keeps the raw grey levels.
    levels_per_std : float
        Grey levels per standard deviation when storing the normalised image
        as ``127 + round(levels_per_std * z)`` (clipped to 0..255);
        ``1`` is OpenSeqSLAM's own rounding.

    Returns
    -------
    ndarray of uint8, shape (height * width,)
    """
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    if img.ndim == 3:
        img = to_gray(img)  # the conversion every source's frames get
    if img.shape != (height, width):
        shrink = img.shape[0] >= height and img.shape[1] >= width
        img = cv2.resize(
            img, (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
        )
    if patch_size == 0:
        return np.ascontiguousarray(img).ravel()
    z = patch_normalize(img, patch_size)
    q = np.clip(np.rint(127.0 + levels_per_std * z), 0, 255)
    return q.astype(np.uint8).ravel()
