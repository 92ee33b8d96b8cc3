"""Determinism: the same inputs give byte-identical localize lines and S for every method and mode,
whatever the thread count and whatever else runs on the machine (issue #41).

Each method's reference is computed on one thread, one frame at a time, on an idle machine; it is then
recomputed with the thread counts that ``n_jobs=-1`` would follow on machines of 2 and 8 cores
(``os.cpu_count``), frames described ahead on a pool, while busy processes share the cores, so that
threads are descheduled at varying moments.  Not one byte may differ.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.maps import Map
from topoloc.methods import available_methods

#: Methods whose map is built with the route's vocabulary (the others need none).
_VOCABULARY = {"bow", "coocmap", "fabmap", "fabmap2"}
_PARAMS: dict[str, dict[str, Any]] = {"seqslam": {"ds": 3}, "coocmap": {"top_k": 2}}


@contextmanager
def _busy(n: int = 2) -> Iterator[None]:
    """``n`` processes spinning on the cores while the block runs; ended by their ids."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


@contextmanager
def _stale_thresholds(mp: pytest.MonkeyPatch) -> Iterator[None]:
    """Cooc-Map's matcher as a schedule whose helpers claimed every location before any threshold rose.

    On a loaded machine helper threads claim chunks early and run late; here each location is its own
    chunk, matched against no threshold, so every location is finished -- a schedule the operating
    system can produce, deterministically.
    """
    from topoloc.coocmap import compiled

    claim = compiled._Shared.claim

    def early(shared: compiled._Shared, helper: bool) -> tuple[int, int, np.ndarray, int] | None:
        job = claim(shared, helper)
        return None if job is None else (job[0], job[1], np.full_like(job[2], -1.0), 0)

    mp.setattr(compiled, "FIRST_CHUNK", 1)
    mp.setattr(compiled, "MAX_CHUNK", 1)
    mp.setattr(compiled._Shared, "claim", early)
    yield


def _outputs(m: Map, query: Any, frames: list[tuple[str, None, np.ndarray]], *, sequence: tuple[int, str],
             prefetch: int) -> tuple[list[str], bytes]:
    lines = []
    if m.recognizer.name != "descriptors":  # it reads descriptors computed elsewhere: it cannot describe a camera frame
        loc = m.localizer(top_k=4, sequence=sequence[0], sequence_mode=sequence[1], prefetch=prefetch)
        lines = [json.dumps(line) for line in loc.stream(iter(frames))]
    S = m.similarity(query)
    if sequence[0]:  # evaluate --sequence: the search over the whole S, its tiles on n_jobs threads
        from topoloc.sequence import sequence_similarity

        S = sequence_similarity(S, ds=sequence[0], mode=sequence[1])  # type: ignore[arg-type]
    return lines, np.ascontiguousarray(S, np.float32).tobytes()


@pytest.mark.parametrize("method", available_methods())
def test_lines_and_S_are_identical_whatever_the_threads_and_the_load(method: str, tiny_route: dict[str, Any],
                                                                     tmp_path: Path) -> None:
    m = Map.build(method=method, tours=[tiny_route["map"]], params=_PARAMS.get(method, {}),
                  vocabulary=tiny_route["vocabulary"] if method in _VOCABULARY else None,
                  cache_dir=tmp_path / "cache")
    frames = [(f"q{k}.jpg", None, f) for k, f in enumerate(tiny_route["query_frames"])]
    query = tiny_route["query"]
    # Single images, and both sequence searches (constant velocity, Cooc-Map's forward paths).
    sequences = [(0, "constant")] if m.recognizer.scores_whole_sequence else [
        (0, "constant"), (3, "constant"), (3, "acceleration")]
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(os, "cpu_count", lambda: 1)
        reference = {s: _outputs(m, query, frames, sequence=s, prefetch=0) for s in sequences}
    with _busy():
        for cores in (2, 8):
            with pytest.MonkeyPatch.context() as mp:
                mp.setattr(os, "cpu_count", lambda cores=cores: cores)
                for s in sequences:
                    lines, S = _outputs(m, query, frames, sequence=s, prefetch=-1)
                    assert S == reference[s][1], f"{method}: S differs on {cores} cores beside busy processes"
                    assert lines == reference[s][0], (f"{method} --sequence {s}: lines differ on {cores} cores "
                                                      "beside busy processes")
    with pytest.MonkeyPatch.context() as mp, _stale_thresholds(mp):
        for s in sequences:
            lines, S = _outputs(m, query, frames, sequence=s, prefetch=0)
            assert (lines, S) == reference[s], f"{method}: another schedule of the matcher changed the output"


@pytest.mark.parametrize("method,sequence", [("coocmap", 0), ("bow", 3)])
def test_verified_lines_are_identical_whatever_the_threads_and_the_load(method: str, sequence: int,
                                                                        tiny_route: dict[str, Any],
                                                                        tmp_path: Path) -> None:
    """Verification (issue #40): matching and MAGSAC are seeded and run on one BLAS thread, on the matching thread."""
    m = Map.build(method=method, tours=[tiny_route["map"]], params=_PARAMS.get(method, {}),
                  vocabulary=tiny_route["vocabulary"], cache_dir=tmp_path / "cache")
    frames = [(f"q{k}.jpg", None, f) for k, f in enumerate(tiny_route["query_frames"])]

    def lines(prefetch: int) -> list[str]:
        loc = m.localizer(top_k=4, sequence=sequence, verify=True, prefetch=prefetch)
        return [json.dumps(line) for line in loc.stream(iter(frames))]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(os, "cpu_count", lambda: 1)
        reference = lines(0)
    assert all('"verified"' in x for x in reference)
    with _busy():
        for cores in (2, 8):
            with pytest.MonkeyPatch.context() as mp:
                mp.setattr(os, "cpu_count", lambda cores=cores: cores)
                assert lines(-1) == reference, f"{method}: verified lines differ on {cores} cores beside busy processes"
