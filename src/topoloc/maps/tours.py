"""What a map keeps of the tours it was built from, and how it reads them again.

A map records each tour (:func:`tour_record`: its folder or recording, size,
times, a fingerprint of its images and places, and the first image of each
place); :func:`reload_tour` reads a tour again from that record, checked
against the fingerprint, when a map needs its images after the build (adding a
tour where the map is rebuilt, verifying answers).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.datasets.traverse import Traverse, load_traverse
from topoloc.errors import TopolocError, input_error
from topoloc.features import FeatureConfig
from topoloc.maps.place_images import PlaceImages
from topoloc.maps.tour_images import TourImages


def tour_record(tour: Traverse) -> dict[str, Any]:
    """What a map remembers of a tour: name, size, times and a fingerprint of its images and places.

    ``place_images`` (:class:`~topoloc.maps.place_images.PlaceImages`, saved as arrays) maps each
    place of the tour to its first image (:func:`topoloc.evaluation.pairs.image_name`), what
    ``localize --pairs-out`` writes for the place; ``images``
    (:class:`~topoloc.maps.tour_images.TourImages`, saved as arrays) is every image's name, place and
    content digest, what verification reads again.
    """
    rec: dict[str, Any] = {
        "name": tour.name, "root": tour_root(tour),
        "n_images": len(tour), "n_places": len(np.unique(tour.places)), "fingerprint": tour.fingerprint(),
        "median_hour": tour.median_time_of_day(), "start": None, "end": None,
        "place_images": PlaceImages.of_tour(tour), "images": TourImages.of_tour(tour),
    }
    if tour.times is not None and len(tour.times):
        rec["start"], rec["end"] = str(tour.times.min()), str(tour.times.max())
    if tour.source is not None:
        rec["source"] = dict(tour.source)  # a recording: its file and frame selection
        if "file" in rec["source"]:
            rec["source"]["file"] = os.path.abspath(rec["source"]["file"])
    return rec


def reload_tour(rec: dict[str, Any], *, purpose: str = "to add a tour") -> Traverse:
    """The tour a map's tour record names, read again from its folder or recording.

    Raises
    ------
    TopolocError
        One line naming the tour: it was held in memory, is gone, or its images or
        places differ from those the map was built from (another fingerprint).
    """
    root = str(rec.get("root", ""))
    if root.startswith("<"):
        raise TopolocError(f"tour {rec.get('name')!r} of the map was built from images in memory, which cannot "
                           f"be read again {purpose}: build the map from all tours")
    src = rec.get("source") or {}
    if src:
        from topoloc.datasets.sources import load_input

        t = load_input(Path(src["file"]), topic=src.get("topic"), every_s=src.get("every_s"),
                       every_m=src.get("every_m"), pose_topic=src.get("pose_topic"))
    else:
        if not Path(root).is_dir():
            where = ("" if Path(root).is_absolute() else
                     f" from {Path.cwd()} (the map recorded it relative to the folder it was built in; run from "
                     "there, or build it again)")
            raise input_error(f"tour {rec.get('name')!r} of the map is needed again {purpose}, but its "
                              f"folder is gone{where}", root)
        t = load_traverse(root)
    if t.fingerprint() != rec["fingerprint"]:
        raise input_error(f"tour {rec.get('name')!r} has changed since the map was built (other images or "
                          "places): build the map again", root)
    return t


def tour_root(tour: Traverse) -> str:
    """A tour's folder, the recording it was read from, or ``<images in memory>``."""
    # Absolute: ``map add`` may run from another folder than ``map build`` (issue #41).
    if tour.kind == "files":
        return os.path.abspath(tour.root)
    if tour.source is not None and "file" in tour.source:
        return os.path.abspath(tour.source["file"])
    return f"<{tour.kind} in memory>"


def xy_sums(tours: Sequence[Traverse], place_ids: np.ndarray) -> np.ndarray:
    """Per place: sum of x, sum of y and number of the tours' images with a position, shape (n_places, 3)."""
    sums = np.zeros((len(place_ids), 3))
    for t in tours:
        if t.xy is None:
            continue
        # A frame without a position (NaN, as recordings give it) adds nothing: summed, it would
        # make its place's mean position NaN for good, whatever later tours add.
        known = np.isfinite(t.xy).all(axis=1)
        rows = np.searchsorted(place_ids, t.places[known])
        np.add.at(sums, rows, np.c_[t.xy[known], np.ones(int(known.sum()))])
    return sums


def check_feature_kind(traverse: Traverse, features: FeatureConfig, where: str | Path | None = None) -> None:
    """Refuse a traverse of features extracted elsewhere that are not of the map's kind (one line naming it).

    Images are described with the map's ``features``; a traverse of
    :class:`~topoloc.features.FeatureSet` is used as it is, so its descriptors
    must have the map's columns and be binary (uint8) exactly when the map's
    are.  Otherwise a method without a vocabulary (landmarks, voting) would fail
    deep in its index search, or a map would record features it was not built from.
    """
    if traverse.kind != "features":
        return
    dim, binary = features.descriptor_dim, features.descriptor_dtype == np.uint8
    for k, fs in enumerate(traverse.frames or ()):
        d = np.asarray(fs.descriptors)
        if len(d) and (d.shape[1] != dim or (d.dtype == np.uint8) != binary):
            raise input_error(f"traverse {traverse.name!r} holds descriptors of {d.shape[1]} {d.dtype} columns "
                              f"(image {k}), not the map's {features.descriptor_kind} features", where)


#: Keys of a tour record held as arrays of the map file, not in its header.
ARRAY_KEYS = ("place_images", "images")


def header_record(rec: dict[str, Any]) -> dict[str, Any]:
    """A tour record as the map file's header holds it (without what it keeps as arrays)."""
    return {k: v for k, v in rec.items() if k not in ARRAY_KEYS}


__all__ = ["ARRAY_KEYS", "check_feature_kind", "header_record", "reload_tour", "tour_record", "tour_root", "xy_sums"]
