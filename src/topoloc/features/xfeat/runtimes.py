"""What runs XFeat's network: one small class per runtime, the network file it loads, and its checks.

Every runtime is a :class:`Network`: called with the network's input (float32
(B, 1, H, W), :func:`topoloc.features.xfeat.postprocess.network_input`) it
returns the three raw maps as NumPy arrays; everything after them is
:mod:`topoloc.features.xfeat.postprocess`, shared.

* ``onnxruntime`` (the default, a core dependency): ``xfeat.onnx`` on ONNX
  Runtime's CPU provider, or its CUDA provider where ``onnxruntime-gpu`` is
  installed.  No PyTorch.
* ``torch`` (``pip install 'topoloc[learned]'``): :class:`~topoloc.features.
  xfeat.network.XFeatNet` with the weights of ``xfeat.npz``, on the CPU or a
  CUDA device; what the ONNX file is exported from (``scripts/export_xfeat_onnx.py``).

Both files ship inside this package, beside ``PROVENANCE.json`` (where the
weights come from, the export's settings and each file's SHA-256, checked
when a file is loaded) and the weights' licence (``LICENSE``, Apache-2.0).
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import importlib.resources
import importlib.util
import io
import json
import logging
import threading
from typing import Any, Protocol

import numpy as np

from topoloc.errors import TopolocError

log = logging.getLogger(__name__)

RUNTIMES = ("onnxruntime", "torch")

#: The network's file for each runtime, inside this package.
FILES = {"onnxruntime": "xfeat.onnx", "torch": "xfeat.npz"}

#: How to install each runtime, for the one-line errors.
INSTALL = {"onnxruntime": "pip install onnxruntime (a dependency of topoloc)",
           "torch": "pip install 'topoloc[learned]'"}

#: PyTorch threads of one extraction, whatever it is asked (see :mod:`topoloc.features.learned`); ONNX Runtime's
#: threads follow the free cores.
THREADS = 1


#: Whether ONNX Runtime's helper threads spin between the network's layers (they stop when a frame ends either way):
#: woken for each layer instead, a frame paced at 10 Hz on 2 idle cores took longer
#: (``docs/results/learned_features.md``, "Extraction speed", rows ``xfeat`` and ``xfeat (helpers sleep)``).
#: Spinning past the frame's end would take the core that matches the frame before (``localize`` describes one frame
#: while it matches another).
SPIN_WITHIN_FRAME = True


class MissingExtraError(TopolocError):
    """A learned feature was asked for but what runs it is not installed, does not load, or its file is damaged."""


def _short(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def import_runtime(name: str) -> Any:
    """The runtime's Python module (``onnxruntime`` or ``torch``), or one line naming it and the way out.

    A runtime that is missing, and one that is installed but does not load (its
    import raising anything, e.g. an ``OSError`` from a shared library), are
    each said in one line naming the runtime.
    """
    try:
        return _import(name)
    except Exception as exc:  # ImportError, or a broken install: a shared library that does not load, a bad build
        if isinstance(exc, ImportError) and not _found(name):
            raise MissingExtraError(f"xfeat features on the {name} runtime need {name}: {INSTALL[name]}, "
                                    "or use --features sift") from None
        raise MissingExtraError(f"xfeat features: {name} is installed but does not load ({_short(exc)}): "
                                f"reinstall it ({INSTALL[name]}) or use --features sift") from None


#: How a runtime is imported (tests replace it to play a missing or broken install).
_import = importlib.import_module


def _found(name: str) -> bool:
    """Whether the top-level module ``name`` is installed, without importing it."""
    try:
        return importlib.util.find_spec(name) is not None
    except (ValueError, ImportError):  # a module set to None in sys.modules, a broken parent
        return False


@functools.lru_cache(maxsize=1)
def manifest() -> dict[str, Any]:
    """``PROVENANCE.json``: the weights' source, the export's settings and the SHA-256 of each shipped file."""
    try:
        text = importlib.resources.files(__package__).joinpath("PROVENANCE.json").read_text()
        out: dict[str, Any] = json.loads(text)
    except (OSError, ValueError) as exc:
        raise MissingExtraError(f"xfeat features: the network's PROVENANCE.json inside topoloc does not read "
                                f"({_short(exc)}): reinstall topoloc") from None
    return out


def network_bytes(runtime: str) -> bytes:
    """The bytes of ``runtime``'s network file, checked against its SHA-256 in ``PROVENANCE.json``."""
    name = FILES[runtime]
    res = importlib.resources.files(__package__).joinpath(name)
    try:
        data = res.read_bytes()
    except OSError as exc:
        raise MissingExtraError(f"xfeat features: the network file {res} does not read ({_short(exc)}): "
                                "reinstall topoloc") from None
    expected = manifest()["files"][name]["sha256"]
    got = hashlib.sha256(data).hexdigest()
    if got != expected:
        raise MissingExtraError(f"xfeat features: the network file {res} is damaged (SHA-256 {got[:12]}..., "
                                f"expected {expected[:12]}... from PROVENANCE.json): reinstall topoloc")
    return data


def is_present(runtime: str) -> bool:
    """Whether ``runtime`` and its network file are installed, without importing the runtime."""
    return (_found(runtime)
            and importlib.resources.files(__package__).joinpath(FILES[runtime]).is_file())


def version(runtime: str) -> str:
    """``major.minor`` of the runtime's installed release (whose kernels may round differently between releases)."""
    import importlib.metadata

    dist = {"onnxruntime": ("onnxruntime", "onnxruntime-gpu"), "torch": ("torch",)}[runtime]
    for d in dist:
        try:
            return ".".join(importlib.metadata.version(d).split("+")[0].split(".")[:2])
        except importlib.metadata.PackageNotFoundError:
            continue
    return "unknown"


def onnx_cuda_listed() -> bool:
    """Whether the installed ONNX Runtime has a CUDA provider (``onnxruntime-gpu``); no session is made."""
    if not _found("onnxruntime"):
        return False
    return "CUDAExecutionProvider" in import_runtime("onnxruntime").get_available_providers()


def torch_sees_cuda() -> bool:
    """Whether PyTorch is installed and sees a CUDA device (imports PyTorch: about a second)."""
    if not _found("torch"):
        return False
    return bool(import_runtime("torch").cuda.is_available())


class Network(Protocol):
    """XFeat's network on one runtime and device: float32 (B, 1, H, W) -> descriptors, keypoint logits, reliability.

    ``threads`` is a wish: a runtime whose output depends on its thread count
    (PyTorch's oneDNN) runs on :data:`THREADS` whatever it is asked.
    """

    runtime: str
    device: str

    def __call__(self, batch: np.ndarray, threads: int = THREADS) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


class OnnxNetwork:
    """``xfeat.onnx`` in ONNX Runtime sessions, one per intra-op thread count asked for; thread-safe.

    ONNX Runtime's CPU kernels split a convolution's work between threads
    without splitting its sums, so the output is the same whatever the thread
    count (``tests/features/test_learned.py``): a frame may use every free
    core without its features depending on the machine's load.
    """

    runtime = "onnxruntime"

    def __init__(self, device: str = "cpu") -> None:
        self._ort = import_runtime("onnxruntime")
        self._model = network_bytes("onnxruntime")
        self._lock = threading.Lock()
        self._sessions: dict[int, Any] = {}
        self.device = device
        self.session = self._session(THREADS)
        if device == "cuda" and "CUDAExecutionProvider" not in self.session.get_providers():
            raise TopolocError("device cuda was asked for but ONNX Runtime's CUDA provider does not start here "
                               "(use --device cpu or auto)")
        self._input = self.session.get_inputs()[0].name

    def _session(self, threads: int) -> Any:
        with self._lock:
            sess = self._sessions.get(threads)
            if sess is not None:
                return sess
            ort = self._ort
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = threads
            opts.inter_op_num_threads = 1
            opts.log_severity_level = 3
            opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if SPIN_WITHIN_FRAME else "0")
            opts.add_session_config_entry("session.force_spinning_stop", "1")
            providers = (["CUDAExecutionProvider", "CPUExecutionProvider"] if self.device == "cuda"
                         else ["CPUExecutionProvider"])
            try:
                sess = ort.InferenceSession(self._model, opts, providers=providers)
            except Exception as exc:
                raise MissingExtraError(f"xfeat features: onnxruntime does not load the network ({_short(exc)}): "
                                        f"reinstall it ({INSTALL['onnxruntime']}) or use --features sift") from None
            self._sessions[threads] = sess
            return sess

    def __call__(self, batch: np.ndarray, threads: int = THREADS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        sess = self.session if threads == THREADS or self.device == "cuda" else self._session(threads)
        desc, logits, rel = sess.run(None, {self._input: np.ascontiguousarray(batch, np.float32)})
        return desc, logits, rel


class TorchNetwork:
    """:class:`~topoloc.features.xfeat.network.XFeatNet` with the shipped weights, on the CPU or CUDA."""

    runtime = "torch"

    def __init__(self, device: str = "cpu") -> None:
        torch = import_runtime("torch")
        from topoloc.features.xfeat.network import XFeatNet, load_state

        with np.load(io.BytesIO(network_bytes("torch"))) as z:
            state = {k: torch.from_numpy(z[k]) for k in z.files}
        self.net = load_state(XFeatNet(), state).to(device)
        self.device = device
        self._torch = torch

    def __call__(self, batch: np.ndarray, threads: int = THREADS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        torch = self._torch
        if torch.get_num_threads() != THREADS:
            torch.set_num_threads(THREADS)  # process-wide in PyTorch; every extraction sets what it runs with
        with torch.inference_mode():
            out = self.net(torch.from_numpy(batch).to(self.device))
            desc, logits, rel = (t.float().cpu().numpy() for t in out)
        return desc, logits, rel


def make_network(runtime: str, device: str) -> Network:
    """A new :class:`Network` of ``runtime`` on ``device`` (``"cpu"`` or ``"cuda"``)."""
    if runtime == "onnxruntime":
        return OnnxNetwork(device)
    if runtime == "torch":
        return TorchNetwork(device)
    raise TopolocError(f"XFeat runtime must be one of {', '.join(RUNTIMES)}, got {runtime!r} (TOPOLOC_XFEAT_RUNTIME)")
