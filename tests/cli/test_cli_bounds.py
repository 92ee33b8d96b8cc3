"""Bombs at the command line: one line, exit 2, before the memory or time is spent."""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from topoloc.maps import Map

if TYPE_CHECKING:
    from conftest import Cli

sys.path.insert(0, str(Path(__file__).parents[1] / "datasets"))
from test_input_bounds import bomb_png


def test_sequence_of_a_million_frames(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    tlm = tmp_path / "m.tlm"
    cli.ok(["map", "build", "--method", "seqslam", "--param", "ds=2", "--map", str(rf["map"]), "--out", str(tlm),
            "--quiet"])
    t0 = time.perf_counter()
    cli.error(["localize", str(tlm), str(rf["query"]), "--out", str(tmp_path / "r.jsonl"), "--sequence", "1000000"],
              "--sequence 1000000 is too long")
    cli.error(["evaluate", "--method", "seqslam", "--map", str(rf["map"]), "--query", str(rf["query"]),
               "--out", str(tmp_path / "o"), "--sequence", "1000000", "--sequence-mode", "acceleration"],
              "--sequence 1000000 is too long")
    cli.error(["evaluate", "--method", "seqslam", "--map", str(rf["map"]), "--query", str(rf["query"]),
               "--out", str(tmp_path / "o"), "--param", "ds=1000000"], "ds must be a length whose constant search")
    assert time.perf_counter() - t0 < 10


def test_image_bomb_in_a_tour(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    query = tmp_path / "query"
    shutil.copytree(rf["query"], query)
    first = sorted(query.glob("*.jpg"))[0]
    first.write_bytes(bomb_png(32000, 32000))  # a PNG under a .jpg name: both readers go by the content
    t0 = time.perf_counter()
    err = cli.error(["evaluate", "--method", "seqslam", "--map", str(rf["map"]), "--query", str(query),
                     "--out", str(tmp_path / "o"), "--quiet"], "image is too large to decode")
    assert first.name in err and time.perf_counter() - t0 < 10


def test_map_add_refuses_positions_that_are_not_finite(cli: Cli, rf: dict[str, Path], tmp_path: Path) -> None:
    tlm = tmp_path / "m.tlm"
    cli.ok(["map", "build", "--method", "seqslam", "--param", "ds=2", "--map", str(rf["map"]), "--out", str(tlm),
            "--quiet"])
    before = tlm.read_bytes()
    tour = tmp_path / "tour"
    shutil.copytree(rf["query"], tour)
    images = sorted(p.name for p in tour.glob("*.jpg"))
    (tour / "places.csv").write_text("image,place,x,y\n" + "".join(
        f"{name},{i},{'nan' if i == 2 else i},{'-inf' if i == 4 else 0}\n" for i, name in enumerate(images)))
    cli.error(["map", "add", str(tlm), str(tour), "--quiet"], "places.csv:4: x,y must be finite numbers")
    assert tlm.read_bytes() == before
    assert np.isfinite(Map.load(tlm).xy_sums).all()
