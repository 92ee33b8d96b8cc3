"""Pinned output of the synthetic street renderer: the same seed must give the same pixels.

The hashes below were computed with the renderer as it was before it was split
into the modules of :mod:`topoloc.synth` (one ``route.py``), so they also guard
refactorings: a change of either hash means that a seed no longer renders what
it used to, and every test, demo and benchmark built on synthetic routes sees
different data.  Update them only for an intended change of the images.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2
import numpy as np

from topoloc.synth import Pose, RouteConfig, build_world, generate_route, render_view, tour_lighting

TINY = RouteConfig(n_places=4, width=64, height=48, seed=7)

# Pins the renderer's output: decoded pixels of every image of both tours, and
# the places.csv files (depends on the JPEG codec that OpenCV ships as well).
ROUTE_SHA256 = "f4a7b2fbf81a001691a35e2e91e83d60e034e7e180220a5ed5db046bd68e8b67"
# Pins the renderer's output before JPEG: raw views at dawn, noon, dusk and night.
VIEWS_SHA256 = "044e500e644bd1cb25b9f5f80df3d6c931b8b69f75aed8f864cc784ac17f9ac5"


def test_tiny_route_renders_the_pinned_pixels(tmp_path: Path) -> None:
    folders = generate_route(tmp_path, config=TINY, tours=(("day", 13.0), ("night", 22.5)))
    h = hashlib.sha256()
    n = 0
    for folder in folders:
        for p in sorted(folder.glob("*.jpg")):
            img = cv2.imread(str(p), cv2.IMREAD_COLOR)
            assert img is not None and img.shape == (TINY.height, TINY.width, 3)
            h.update(p.name.encode())
            h.update(str(img.shape).encode())
            h.update(img.tobytes())
            n += 1
        h.update((folder / "places.csv").read_bytes())
    assert n == 10
    assert h.hexdigest() == ROUTE_SHA256


def test_raw_views_render_the_pinned_pixels() -> None:
    world = build_world(TINY)
    h = hashlib.sha256()
    for hour in (7.0, 13.0, 19.5, 23.0):
        light = tour_lighting(world, hour, key=3)
        pose = Pose(s=3.0, lateral=-0.4, yaw_deg=4.0)
        img = render_view(world, pose, hour, np.random.default_rng(11), lighting=light)
        h.update(img.tobytes())
    assert h.hexdigest() == VIEWS_SHA256
