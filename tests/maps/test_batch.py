"""Batch localisation through an executor gives the lines of the online localiser, in order."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from topoloc.cluster import LocalExecutor
from topoloc.maps import Map
from topoloc.maps.batch import localize_on


@pytest.mark.parametrize("method,params", [("bow", {}), ("seqslam", {"ds": 3})])
def test_batches_equal_the_online_localiser(method: str, params: dict[str, Any], tiny_route: dict[str, Any],
                                            tmp_path: Path) -> None:
    voc = tiny_route["vocabulary"] if method != "seqslam" else None
    built = Map.build(method=method, tours=[tiny_route["map"]], params=params, vocabulary=voc,
                      cache_dir=tmp_path / "cache")
    m = Map.load(built.save(tmp_path / "m.tlm"))
    frames = tiny_route["query_frames"]
    online = m.localizer(top_k=3, sequence=2)
    want = [online.step(f, name=f"q{k}") for k, f in enumerate(frames)]
    loc = m.localizer(top_k=3, sequence=2)
    items = iter([(f"q{k}", None, f) for k, f in enumerate(frames)])
    # Batches of 5 frames over 2 threads: several windows, batches finishing out of order.
    got = [line for line, _ in localize_on(LocalExecutor(n_jobs=2), loc, items, batch_frames=5)]
    assert got == want
    assert loc.frames == len(frames) and loc.summary()["frames"] == len(frames)


def test_a_map_not_loaded_from_a_file_is_refused(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    from topoloc.errors import TopolocError

    m = Map.build(method="bow", tours=[tiny_route["map"]], vocabulary=tiny_route["vocabulary"],
                  cache_dir=tmp_path / "cache")
    with pytest.raises(TopolocError, match="loaded from a file"):
        next(localize_on(LocalExecutor(n_jobs=1), m.localizer(), iter([])))
