"""How a pairs file (hloc's format) names an image and a place: ``<folder name>/<path under the folder>``.

Shared by ``evaluate``'s and ``localize``'s pairs files (:mod:`topoloc.evaluation.pairs`) and saved maps,
which remember the first image of each place (:mod:`topoloc.maps.place_images`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

from topoloc.datasets.traverse import Traverse


def image_name(traverse: Traverse, i: int) -> str:
    """The name of image ``i`` of ``traverse`` in a pairs file: ``<folder name>/<path under the folder>``."""
    img = Path(traverse.images[i])
    if traverse.kind != "files":
        return img.as_posix()  # already <name>/<k>
    try:
        rel = img.relative_to(traverse.root).as_posix()
    except ValueError:
        rel = img.name
    return f"{traverse.root.name or traverse.name}/{rel}"


def image_names(traverse: Traverse) -> list[str]:
    """:func:`image_name` of every image of ``traverse``, in order."""
    return [image_name(traverse, i) for i in range(len(traverse.images))]


def first_images(traverse: Traverse) -> dict[int, str]:
    """The first image of each place of ``traverse``: place id -> :func:`image_name`."""
    # np.unique's return_index is the first occurrence: one name built per place, not per image.
    ids, first = np.unique(np.asarray(traverse.places), return_index=True)
    return {int(p): image_name(traverse, int(i)) for p, i in zip(ids.tolist(), first.tolist(), strict=True)}


def place_names(place_ids: Sequence[int] | np.ndarray, tours: Iterable[Mapping[int, str]]) -> list[str]:
    """The image each place is written as: the first of ``tours`` (place -> image) naming it, else ``place-<id>``."""
    known: dict[int, str] = {}
    for tour in tours:
        for p, name in tour.items():
            known.setdefault(int(p), name)
    return [known.get(int(p), f"place-{int(p)}") for p in np.asarray(place_ids).tolist()]


__all__ = ["first_images", "image_name", "image_names", "place_names"]
