"""Tiny images for the dataset-format tests (each test writes its own sample dataset)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest


@pytest.fixture
def write_image() -> Callable[[Path], Path]:
    """``write_image(path)`` writes a 24 x 16 random image (any suffix cv2 knows) and returns the path."""
    rng = np.random.default_rng(0)

    def write(path: Path) -> Path:
        path.parent.mkdir(parents=True, exist_ok=True)
        ok = cv2.imwrite(str(path), rng.integers(0, 255, (16, 24, 3), dtype=np.uint8))
        assert ok, path
        return path

    return write
