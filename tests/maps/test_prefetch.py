"""Frames described ahead while one is matched: same lines in the same order, bounded memory, errors in turn."""

from __future__ import annotations

import json
import random
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.errors import ParameterError
from topoloc.maps import Map
from topoloc.maps.prefetch import ahead


def _slow_work(k: int, item: int) -> int:
    # Later items often finish first: the order must come from the input, not from completion.
    time.sleep(random.Random(k).uniform(0.0, 0.01))
    return item * item


def test_results_come_in_input_order_whatever_finishes_first() -> None:
    got = [(a.item, a.result) for a in ahead(iter(range(40)), _slow_work, depth=6, workers=4)]
    assert got == [(i, i * i) for i in range(40)]


@pytest.mark.parametrize("depth", [1, 3, 8])
def test_at_most_depth_items_are_read_and_not_yet_returned(depth: int) -> None:
    pulled = [0]

    def source() -> Iterator[int]:
        for i in range(30):
            pulled[0] += 1
            yield i

    worst = 0
    for n, a in enumerate(ahead(source(), _slow_work, depth=depth, workers=2), start=1):
        time.sleep(0.005)  # a slow consumer: the reader would run ahead without its bound
        worst = max(worst, pulled[0] - n)
        assert a.item == n - 1
    assert worst <= depth
    assert worst == depth or depth == 1  # the bound is reached, so the reader did run ahead


def test_a_read_error_comes_after_the_items_before_it() -> None:
    def source() -> Iterator[int]:
        yield from range(3)
        raise ValueError("frame 3 is damaged")

    seen: list[int] = []
    with pytest.raises(ValueError, match="frame 3"):
        for a in ahead(source(), _slow_work, depth=4):
            seen.append(a.item)
    assert seen == [0, 1, 2]


def test_a_work_error_is_raised_in_its_turn() -> None:
    def work(k: int, item: int) -> int:
        if item == 5:
            raise RuntimeError("no features")
        return item

    seen: list[int] = []
    with pytest.raises(RuntimeError, match="no features"):
        for a in ahead(iter(range(10)), work, depth=3):
            seen.append(a.result)
    assert seen == [0, 1, 2, 3, 4]


def test_stopping_early_stops_the_reader_and_closes_the_input() -> None:
    closed = threading.Event()

    def source() -> Iterator[int]:
        try:
            yield from range(10_000)
        finally:
            closed.set()

    before = threading.active_count()
    gen = ahead(source(), _slow_work, depth=4)
    assert [next(gen).item for _ in range(3)] == [0, 1, 2]
    gen.close()
    assert closed.is_set()
    assert threading.active_count() == before  # reader and pool threads are gone


@pytest.mark.parametrize("method,params,sequence", [("bow", {}, 2), ("coocmap", {"top_k": 3}, 0),
                                                    ("landmarks", {}, 0), ("seqslam", {"ds": 3}, 0)])
def test_prefetched_lines_equal_one_frame_at_a_time(method: str, params: dict[str, Any], sequence: int,
                                                    tiny_route: dict[str, Any], tmp_path: Path) -> None:
    voc = tiny_route["vocabulary"] if method in ("bow", "coocmap") else None
    m = Map.build(method=method, tours=[tiny_route["map"]], params=params, vocabulary=voc,
                  cache_dir=tmp_path / "cache")
    frames = [(f"q{k}.jpg", None if k % 2 else 0.1 * k, f) for k, f in enumerate(tiny_route["query_frames"])]
    serial = m.localizer(top_k=3, sequence=sequence, prefetch=0)
    want = [json.dumps(line) for line in serial.stream(iter(frames))]
    ahead_loc = m.localizer(top_k=3, sequence=sequence, prefetch=3)
    got = [json.dumps(line) for line in ahead_loc.stream(iter(frames))]
    assert got == want  # the same lines, byte for byte, in the same order
    s = ahead_loc.summary()
    assert s["frames"] == len(frames) and s["threads"] >= 1
    stages = ("ms_decode_mean", "ms_extract_mean", "ms_quantise_mean", "ms_matching_mean")
    assert all(s[k] >= 0 for k in stages) and s["ms_extract_mean"] > 0
    assert s["ms_features_mean"] == pytest.approx(s["ms_decode_mean"] + s["ms_extract_mean"]
                                                  + s["ms_quantise_mean"], abs=0.02)
    # Methods that quantise report it apart from the extraction; the others spend nothing on it.
    assert (s["ms_quantise_mean"] > 0) == (voc is not None)


def test_a_bad_prefetch_is_refused_by_name(tiny_route: dict[str, Any], tmp_path: Path) -> None:
    m = Map.build(method="seqslam", tours=[tiny_route["map"]], params={"ds": 3}, cache_dir=tmp_path / "cache")
    with pytest.raises(ParameterError, match="prefetch"):
        m.localizer(prefetch=-2)
    with pytest.raises(ParameterError, match="prefetch"):
        m.localizer(prefetch=np.float64(2.0))  # type: ignore[arg-type]


def test_a_frame_is_described_once_when_a_method_asks_for_features_and_words(tiny_route: dict[str, Any],
                                                                              tmp_path: Path,
                                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    from topoloc.features import FeatureExtractor

    m = Map.build(method="coocmap", tours=[tiny_route["map"]], params={"top_k": 3},
                  vocabulary=tiny_route["vocabulary"], cache_dir=tmp_path / "cache")
    calls = [0]
    extract = FeatureExtractor.extract_image

    def counted(self: FeatureExtractor, image: np.ndarray) -> Any:
        calls[0] += 1
        return extract(self, image)

    monkeypatch.setattr(FeatureExtractor, "extract_image", counted)
    frames = tiny_route["query_frames"][:4]
    lines = m.localize_many(frames)  # Cooc-Map takes each frame's keypoints and its words
    assert calls[0] == len(frames) == len(lines)
