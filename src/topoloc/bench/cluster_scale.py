"""A long synthetic route for the cluster scale benchmark (``benchmarks/bench_cluster.py``).

The route is made of independent synthetic streets (:mod:`topoloc.synth`),
``places_per_segment`` places each, laid end to end: segment ``s`` holds places
``s * places_per_segment ...``.  Every segment is rendered by one task of an
:class:`~topoloc.cluster.Executor`, so a route of tens of thousands of places is
generated on the same cluster the pipeline then runs on.  The map tour covers
every place (at ``map_hour``); a query tour (at ``query_hour``) is rendered for
one segment in ``query_every``, and a tour to add to the map (``map add``, at
``add_hour``) for one segment in ``add_every`` (0: none).  They are written as
ordinary traverse folders (``map/``, ``query/``, ``add/``) with a ``places.csv`` (``image,place,time,x,y``; ``x`` in
metres along the whole route), so ``topoloc`` commands read them as they read
any recording.  Images made here are for timing, never for accuracy claims.
"""

from __future__ import annotations

import csv
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from topoloc.cluster import Executor
from topoloc.errors import input_error
from topoloc.progress import ProgressFactory, no_progress

HEADER = ["image", "place", "time", "x", "y"]


@dataclass(frozen=True)
class ScaleRoute:
    """What :func:`generate_scale_route` wrote.

    Attributes
    ----------
    root : Path
    map_dir, query_dir, add_dir : Path
        Traverse folders (images + ``places.csv``); ``add_dir`` is empty without an added tour.
    n_places : int
        Places of the map tour.
    n_map_images, n_query_images, n_add_images : int
    width, height : int
        Image size in pixels.
    """

    root: Path
    map_dir: Path
    query_dir: Path
    n_places: int
    n_map_images: int
    n_query_images: int
    width: int
    height: int
    add_dir: Path | None = None
    n_add_images: int = 0


def _render_segment(task: tuple[Any, ...]) -> dict[str, list[list[str]]]:
    """Render segment ``seg`` into ``root/map`` (and ``root/query``); return its ``places.csv`` rows.

    A module-level function so that Dask workers can run it; a segment already
    rendered (its rows file present) is not rendered again, so an interrupted
    generation resumes.
    """
    from topoloc.synth import RouteConfig, generate_route

    root_s, seg, per_seg, width, height, map_hour, query_hour, with_query, seed, add_hour = task
    root = Path(root_s)
    done = root / "segments" / f"{seg:05d}.csv"
    if done.is_file():
        return _read_rows(done)
    config = RouteConfig(n_places=per_seg, width=width, height=height, seed=seed + seg)
    tmp = root / "segments" / f"{seg:05d}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tours = ([("map", map_hour)] + ([("query", query_hour)] if with_query else [])
             + ([("add", add_hour)] if add_hour is not None else []))
    folders = generate_route(tmp, config=config, tours=tours)
    length_m = per_seg * config.place_spacing_m
    out: dict[str, list[list[str]]] = {"map": [], "query": [], "add": []}
    for folder in folders:
        dest = root / folder.name
        with (folder / "places.csv").open(encoding="utf-8") as fh:
            reader = csv.reader(fh)
            next(reader)
            for name, place, when, x, y in reader:
                new = f"s{seg:05d}_{name}"
                (folder / name).replace(dest / new)
                out[folder.name].append([new, str(int(place) + seg * per_seg), when,
                                         f"{float(x) + seg * length_m:.3f}", y])
    with done.with_suffix(".part").open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        for tour, rows in out.items():
            w.writerows([[tour, *r] for r in rows])
    done.with_suffix(".part").replace(done)
    shutil.rmtree(tmp, ignore_errors=True)
    return out


def _read_rows(path: Path) -> dict[str, list[list[str]]]:
    out: dict[str, list[list[str]]] = {"map": [], "query": [], "add": []}
    with path.open(encoding="utf-8") as fh:
        for tour, *row in csv.reader(fh):
            out[tour].append(row)
    return out


def generate_scale_route(
    root: str | Path, *, n_places: int, executor: Executor, places_per_segment: int = 100, width: int = 160,
    height: int = 120, query_every: int = 20, map_hour: float = 12.0, query_hour: float = 16.0, seed: int = 0,
    add_every: int = 0, add_hour: float = 18.0, progress: ProgressFactory | None = None,
) -> ScaleRoute:
    """Write a route of ``n_places`` places (see the module docstring).

    Parameters
    ----------
    root : path
        Output folder; ``map/``, ``query/`` and ``segments/`` (resume records) are made in it.
    n_places : int
        Places of the route; a multiple of ``places_per_segment``.
    executor : Executor
        Where the segments are rendered (local threads or a Dask cluster whose
        workers see ``root`` at the same path).
    places_per_segment, width, height, query_every, map_hour, query_hour, seed
        Size of a segment, image size, one query segment in ``query_every``,
        the tours' hours, and the seed of segment 0 (segment ``s`` uses ``seed + s``).
    add_every, add_hour
        One segment in ``add_every`` (0: none) also has a tour at ``add_hour``, in ``add/``.
    progress : callable, optional
        Progress factory (one step per segment).

    Returns
    -------
    ScaleRoute
    """
    if n_places < 1 or places_per_segment < 1 or n_places % places_per_segment:
        raise input_error(f"scale route: n_places ({n_places}) must be a positive multiple of "
                          f"places_per_segment ({places_per_segment})")
    if query_every < 1:
        raise input_error("scale route: query_every must be >= 1")
    root = Path(root)
    for sub in ("map", "query", "add", "segments"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    n_seg = n_places // places_per_segment
    # One segment in query_every has a query tour (at least one, however short the route).
    queried = set(range(min(query_every // 2, n_seg - 1), n_seg, query_every))
    added = set(range(0, n_seg, add_every)) if add_every > 0 else set()
    tasks: list[Any] = [(str(root), s, places_per_segment, width, height, map_hour, query_hour,
                         s in queried, seed, add_hour if s in added else None) for s in range(n_seg)]
    advance = (progress or no_progress)("rendering segments", n_seg)
    parts = executor.map(_render_segment, tasks, advance=advance)
    counts = {}
    for tour in ("map", "query", "add"):
        rows = [r for part in parts for r in part[tour]]
        with (root / tour / "places.csv").open("w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(HEADER)
            w.writerows(rows)
        counts[tour] = len(rows)
    return ScaleRoute(root=root, map_dir=root / "map", query_dir=root / "query", n_places=n_places,
                      n_map_images=counts["map"], n_query_images=counts["query"], width=width, height=height,
                      add_dir=root / "add", n_add_images=counts["add"])


__all__ = ["ScaleRoute", "generate_scale_route"]
