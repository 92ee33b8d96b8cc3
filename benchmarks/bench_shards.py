"""A map built from shards against the map built in one piece, on real data (gardens_point).

For each method: build the map of ``day_left`` + ``day_right`` (2 x 100 images) in one
piece and from ``--shards`` shards (local threads), then compare the saved state array by
array (dtype and bytes) and ``S`` of the first ``--queries`` ``night_right`` images.  Prints
one JSON line per method: ``state_equal``, ``S_equal``, ``max_abs_S_diff`` and both build
times (seconds; noisy on a shared machine, and the one-piece build runs first so it pays for
any feature extraction not yet cached).

Usage::

    .venv/bin/python -m benchmarks.bench_shards --vocab VOCAB.tlv [--shards 4] [--queries 30] [--methods bow,coocmap]

``VOCAB.tlv`` should be trained apart from gardens_point (``VOCAB_FOR_GP`` in
``benchmarks/common.py``: webcam_daynight's map tours), e.g. with
``topoloc vocab train ../shared/data/webcam_daynight/map --out VOCAB.tlv``; FAB-MAP learns
its word statistics from the folders recorded in it.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from benchmarks.common import GP, require_data
from topoloc.cluster import LocalExecutor
from topoloc.datasets.traverse import Traverse, load_traverse
from topoloc.maps import Map

DEFAULT_METHODS = "bow,coocmap,fabmap2,landmarks,seqslam,voting"


def _head(t: Traverse, n: int) -> Traverse:
    return t.take(np.arange(min(n, len(t))))


def compare(method: str, vocab: Path, shards: int, n_queries: int) -> dict[str, object]:
    tours = [load_traverse(GP / "day_left"), load_traverse(GP / "day_right")]
    query = _head(load_traverse(GP / "night_right"), n_queries)
    kw: dict[str, object] = {"method": method, "tours": tours, "vocabulary": vocab}
    t0 = time.perf_counter()
    one = Map.build(**kw)  # type: ignore[arg-type]
    t1 = time.perf_counter()
    sharded = Map.build(**kw, shards=shards, executor=LocalExecutor(n_jobs=2))  # type: ignore[arg-type]
    t2 = time.perf_counter()
    meta_a, arrays_a = one.recognizer.get_state()
    meta_b, arrays_b = sharded.recognizer.get_state()
    same = meta_a == meta_b and sorted(arrays_a) == sorted(arrays_b) and all(
        arrays_a[k].dtype == arrays_b[k].dtype and arrays_a[k].tobytes() == arrays_b[k].tobytes() for k in arrays_a)
    S_a, S_b = one.similarity(query), sharded.similarity(query)
    return {"method": method, "shards": shards, "places": len(one.place_ids), "queries": n_queries,
            "state_equal": bool(same), "S_equal": bool(np.array_equal(S_a, S_b)),
            "max_abs_S_diff": float(np.max(np.abs(S_a - S_b))) if S_a.shape == S_b.shape else None,
            "seconds_one_piece": round(t1 - t0, 2), "seconds_shards": round(t2 - t1, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vocab", type=Path, required=True)
    ap.add_argument("--shards", type=int, default=4)
    ap.add_argument("--queries", type=int, default=30)
    ap.add_argument("--methods", default=DEFAULT_METHODS)
    args = ap.parse_args()
    require_data()
    for method in args.methods.split(","):
        print(json.dumps(compare(method, args.vocab, args.shards, args.queries)), flush=True)


if __name__ == "__main__":
    main()
