"""The default features (``auto``): XFeat where its runtime (ONNX Runtime) is installed, else SIFT with one warning."""

from __future__ import annotations

import importlib.util
import logging

import pytest

from topoloc.errors import TopolocError
from topoloc.spec import parts
from topoloc.spec.parts import FeatureSpec, default_feature_method


def test_auto_is_xfeat_where_the_extra_is_installed(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TOPOLOC_FEATURES")
    installed = importlib.util.find_spec("onnxruntime") is not None
    assert installed, "ONNX Runtime is a dependency of topoloc"
    assert default_feature_method() == "xfeat"
    assert FeatureSpec().method == default_feature_method()
    assert FeatureSpec(method="AUTO").method == default_feature_method()
    assert FeatureSpec(method="orb").method == "orb"


def test_without_its_runtime_auto_is_sift_with_one_warning(monkeypatch: pytest.MonkeyPatch,
                                                         caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.delenv("TOPOLOC_FEATURES")
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "onnxruntime" else real(name, *a))
    monkeypatch.setattr(parts, "_told_missing_extra", False)
    with caplog.at_level(logging.WARNING, logger="topoloc.spec.parts"):
        assert FeatureSpec().method == "sift"
        assert FeatureSpec().method == "sift"
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "pip install onnxruntime" in lines[0]


def test_the_environment_chooses_and_is_checked(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TOPOLOC_FEATURES", "rootsift")
    assert FeatureSpec().method == "rootsift"
    monkeypatch.setenv("TOPOLOC_FEATURES", "surf")
    with pytest.raises(TopolocError, match=r"TOPOLOC_FEATURES must be auto or one of sift, .*got 'surf'"):
        FeatureSpec()
