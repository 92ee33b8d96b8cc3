"""Tours of a synthetic route: where each tour takes its images, and writing them to disk.

Every tour drives the route with its own speed profile (accelerations,
cruising, stops), lateral offset, camera wobble and lit windows; images are
taken at a fixed frame interval, so slow stretches give several images of a
place and fast ones skip places.  The place id of an image is the nearest
place along the route (place ``k`` lies at ``s = k * place_spacing_m``).
:func:`generate_route` renders every tour (:func:`~topoloc.synth.camera.render_view`)
and writes it as a traverse folder of JPEG images and a ``places.csv``.  For
tests and demonstrations only: never publish results measured on these images.
"""

from __future__ import annotations

import csv
import math
import zlib
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path

import cv2
import numpy as np

from topoloc.errors import input_error
from topoloc.synth.camera import Pose, render_view
from topoloc.synth.config import _TAG_FRAME, _TAG_TOUR, RouteConfig, _rng
from topoloc.synth.lighting import Lighting, tour_lighting
from topoloc.synth.world import build_world

__all__ = ["DEFAULT_TOURS", "TourPlan", "generate_route", "plan_tour", "speed_profile"]

#: Tours written by :func:`generate_route` unless told otherwise: (folder name, hour).
DEFAULT_TOURS: tuple[tuple[str, float], ...] = (
    ("tour_0900", 9.0),
    ("tour_1300", 13.0),
    ("tour_1700", 17.0),
    ("tour_2200", 22.0),
)

#: The fixed date of every time stamp, so that files never depend on the clock.
DATE = datetime(2024, 6, 21)


@dataclass(frozen=True, eq=False)
class TourPlan:
    """Where and when one tour takes its images.

    Attributes
    ----------
    name : str
        Folder name of the tour.
    hour : float
        Hour of the day of the start.
    key : int
        CRC-32 of the name; seeds everything tour-specific.
    times : ndarray of float64, shape (n,)
        Seconds since the start of the tour.
    poses : tuple of Pose, length n
    places : ndarray of int64, shape (n,)
        Nearest place of each image.
    """

    name: str
    hour: float
    key: int
    times: np.ndarray
    poses: tuple[Pose, ...]
    places: np.ndarray


def speed_profile(
    *,
    n_places: int,
    spacing_m: float,
    rng: np.random.Generator,
    images_per_place: float = 1.15,
    speed_mps: float = 4.0,
    variation: float = 0.4,
    stop_probability: float = 0.08,
) -> tuple[np.ndarray, np.ndarray]:
    """Times and positions of a tour's images along the route.

    The vehicle starts from standing, then changes speed every few seconds
    (linear ramps between random cruising speeds, sometimes a stop of a few
    seconds) until it reaches the last place.  Images are taken at a constant
    frame interval chosen so that the tour has ``n_places * images_per_place``
    images: slow stretches and stops give several images per place, fast
    stretches skip places.

    Parameters
    ----------
    n_places : int
    spacing_m : float
    rng : numpy.random.Generator
    images_per_place : float
    speed_mps : float
        Mean cruising speed.
    variation : float
        Cruising speeds are drawn from ``speed_mps * [1 - variation, 1 + variation]``.
    stop_probability : float
        Chance that a speed change is a stop.

    Returns
    -------
    times : ndarray of float64, shape (n,)
        Seconds since the start, increasing.
    s : ndarray of float64, shape (n,)
        Metres along the route, non-decreasing, from 0 to ``(n_places - 1) * spacing_m``.
    """
    s_end = (n_places - 1) * spacing_m
    kt, kv = [0.0, float(rng.uniform(1.0, 3.0))], [0.0, 0.0]  # standing at the start
    dist = 0.0
    while dist < s_end * 1.05 + 1:
        dt = float(rng.uniform(3.0, 8.0))
        if rng.random() < stop_probability:  # brake to a standstill, wait
            dist += 0.5 * kv[-1] * dt
            kt += [kt[-1] + dt, kt[-1] + dt + float(rng.uniform(2.0, 5.0))]
            kv += [0.0, 0.0]
        else:
            v = speed_mps * float(rng.uniform(1 - variation, 1 + variation))
            dist += 0.5 * (kv[-1] + v) * dt
            kt.append(kt[-1] + dt)
            kv.append(v)
    tg = np.arange(0.0, kt[-1], 0.02)
    vg = np.interp(tg, kt, kv)
    sg = np.concatenate([[0.0], np.cumsum(0.5 * (vg[1:] + vg[:-1]) * np.diff(tg))])
    i = int(np.searchsorted(sg, s_end))
    i = min(max(i, 1), len(sg) - 1)
    t_end = tg[i - 1] + (s_end - sg[i - 1]) / max(sg[i] - sg[i - 1], 1e-12) * (tg[i] - tg[i - 1])
    n = max(2, round(n_places * images_per_place))
    times = np.linspace(0.0, t_end, n)
    s = np.minimum(np.interp(times, tg, sg), s_end)
    s[-1] = s_end
    return times, s


def plan_tour(
    config: RouteConfig,
    name: str,
    hour: float,
    *,
    lateral_offset: float | None = None,
) -> TourPlan:
    """Speed profile, camera poses and places of one tour.

    Parameters
    ----------
    config : RouteConfig
    name : str
        Tour name; its CRC-32 seeds everything tour-specific.
    hour : float
    lateral_offset : float, optional
        Metres right of the centre line; a small random offset when omitted.

    Returns
    -------
    TourPlan
    """
    cfg = config
    key = zlib.crc32(name.encode("utf-8"))
    rng = _rng(cfg.seed, _TAG_TOUR, key)
    # Drawn even when an offset is given, so that the rest of the tour stays the same.
    default_offset = float(rng.uniform(-0.7, 0.7))
    offset = default_offset if lateral_offset is None else float(lateral_offset)
    times, s = speed_profile(
        n_places=cfg.n_places,
        spacing_m=cfg.place_spacing_m,
        rng=rng,
        images_per_place=cfg.images_per_place,
        speed_mps=cfg.speed_mps,
        variation=cfg.speed_variation,
        stop_probability=cfg.stop_probability,
    )
    n = len(s)
    j = cfg.pose_jitter_deg
    # Smooth wobble along the route plus a little per-frame shake.
    ph = rng.uniform(0, 2 * np.pi, 4)
    lam = rng.uniform(15.0, 35.0, 2)
    yaw = j * (rng.normal(0, 0.5) + 0.7 * np.sin(2 * np.pi * s / lam[0] + ph[0]) + rng.normal(0, 0.25, n))
    pitch = cfg.pitch_deg + j * (
        rng.normal(0, 0.4) + 0.3 * np.sin(2 * np.pi * s / lam[1] + ph[1]) + rng.normal(0, 0.2, n)
    )
    roll = j * (rng.normal(0, 0.3) + rng.normal(0, 0.2, n))
    lateral = offset + 0.12 * np.sin(2 * np.pi * s / 40.0 + ph[2])
    height = cfg.camera_height_m + rng.normal(0, 0.03) + rng.normal(0, 0.01, n)
    poses = tuple(
        Pose(float(s[k]), float(lateral[k]), float(height[k]), float(yaw[k]), float(pitch[k]), float(roll[k]))
        for k in range(n)
    )
    places = np.clip(np.rint(s / cfg.place_spacing_m), 0, cfg.n_places - 1).astype(np.int64)
    return TourPlan(name=name, hour=float(hour), key=key, times=times, poses=poses, places=places)


def _encode(img: np.ndarray, quality: int) -> bytes:
    # Every encoder option is pinned so that files are byte-identical across runs.
    params = [
        cv2.IMWRITE_JPEG_QUALITY,
        quality,
        cv2.IMWRITE_JPEG_PROGRESSIVE,
        0,
        cv2.IMWRITE_JPEG_OPTIMIZE,
        0,
        cv2.IMWRITE_JPEG_RST_INTERVAL,
        0,
        cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
        cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420,
    ]
    ok, buf = cv2.imencode(".jpg", img, params)
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


def generate_route(
    out_dir: str | Path,
    *,
    # RouteConfig is frozen, so one default instance shared by all calls is safe.
    config: RouteConfig = RouteConfig(),  # noqa: B008
    tours: Sequence[tuple[str, float]] = DEFAULT_TOURS,
    lateral_offsets: Sequence[float] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[Path]:
    """Write a synthetic route: one traverse folder per tour.

    Each folder ``out_dir/<name>/`` holds JPEG images ``00000.jpg``, ... and a
    ``places.csv`` with columns ``image,place,time,x,y`` (``docs/protocol.md``):
    the nearest place, the ISO 8601 time on a fixed date (the tour's hour plus
    the seconds elapsed along the route), the metres along the route ``x`` and
    the lateral offset ``y``.  For tests and demonstrations only.

    Parameters
    ----------
    out_dir : str or Path
        Created if missing; existing files of the same names are overwritten.
    config : RouteConfig
    tours : sequence of (str, float)
        Folder name and hour of the day (0-24) of each tour.
    lateral_offsets : sequence of float, optional
        Metres right of the centre line, one per tour; small random offsets
        when omitted.
    progress : callable, optional
        Called as ``progress(done, total)`` after each image.

    Returns
    -------
    list of Path
        The tour folders, in the order of ``tours``.

    Raises
    ------
    TopolocError
        For bad tours or offsets.
    """
    tours = list(tours)
    if not tours:
        raise input_error("synthetic route: no tours given")
    names = [str(n) for n, _ in tours]
    for name in names:
        if not name or name in (".", "..") or "/" in name or "\\" in name:
            raise input_error(f"synthetic route: bad tour name {name!r}")
    if len(set(names)) != len(names):
        raise input_error("synthetic route: tour names must be unique")
    hours = [float(h) for _, h in tours]
    if not all(math.isfinite(h) and 0 <= h <= 24 for h in hours):
        raise input_error("synthetic route: tour hours must be in [0, 24]")
    if lateral_offsets is not None:
        lateral_offsets = [float(o) for o in lateral_offsets]
        if len(lateral_offsets) != len(tours):
            raise input_error("synthetic route: give one lateral offset per tour")
        limit = config.street_width_m / 2 - config.sidewalk_m
        if not all(math.isfinite(o) and abs(o) <= limit for o in lateral_offsets):
            raise input_error(f"synthetic route: lateral offsets must be within +-{limit:g} m")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    world = build_world(config)
    plans = [
        plan_tour(config, n, h, lateral_offset=None if lateral_offsets is None else lateral_offsets[i])
        for i, (n, h) in enumerate(zip(names, hours, strict=True))
    ]
    total = sum(len(p.poses) for p in plans)
    done = 0
    folders = []
    for plan in plans:
        lighting = tour_lighting(world, plan.hour, key=plan.key)
        folder = out / plan.name
        folder.mkdir(parents=True, exist_ok=True)
        start = DATE + timedelta(hours=plan.hour)
        rows = []

        def render(k: int, plan: TourPlan = plan, lighting: Lighting = lighting) -> bytes:
            rng = _rng(config.seed, _TAG_FRAME, plan.key, k)
            img = render_view(world, plan.poses[k], plan.hour, rng, lighting=lighting)
            return _encode(img, config.jpeg_quality)

        # OpenCV and NumPy release the GIL, so two threads use both cores; every
        # frame has its own generator, so the result does not depend on scheduling.
        with ThreadPoolExecutor(max_workers=2) as pool:
            for k, data in enumerate(pool.map(render, range(len(plan.poses)))):
                pose = plan.poses[k]
                name = f"{k:05d}.jpg"
                (folder / name).write_bytes(data)
                when = start + timedelta(seconds=round(float(plan.times[k]), 3))
                time = when.isoformat(timespec="milliseconds")
                rows.append([name, int(plan.places[k]), time, f"{pose.s:.3f}", f"{pose.lateral:.3f}"])
                done += 1
                if progress is not None:
                    progress(done, total)
        with (folder / "places.csv").open("w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh, lineterminator="\n")
            writer.writerow(["image", "place", "time", "x", "y"])
            writer.writerows(rows)
        folders.append(folder)
    return folders
