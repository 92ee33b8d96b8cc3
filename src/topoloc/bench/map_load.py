"""Opening a saved map of the Cooc-Map paper's size: file size, load time, first localisation.

The map is :func:`~topoloc.bench.coocmap_speed.synthetic_map` (2,200 locations x
5 tours by default, 500 features per image, 10,000 words) wrapped as a fitted
:class:`~topoloc.methods.cooc_map.CoocMap` with a random 10,000-word SIFT
vocabulary, saved with :meth:`topoloc.maps.Map.save` and opened with
:meth:`topoloc.maps.Map.load` (arrays memory-mapped) in a fresh Python process
each time, so that the time includes reading the header, checking the CRC-32
of every byte and restoring the recogniser, but not importing topoloc.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.bench.coocmap_speed import synthetic_map
from topoloc.features import FeatureConfig
from topoloc.maps import Map
from topoloc.methods.cooc_map import CoocMap
from topoloc.vocabulary import Vocabulary

_LOAD = """
import json, sys, time
import numpy as np
from topoloc.maps import Map
from topoloc.methods.cooc_map import CoocMap  # imported before timing: not part of opening a map
t0 = time.perf_counter()
m = Map.load(sys.argv[1])
t1 = time.perf_counter()
q = json.loads(sys.argv[2])
item = (np.array(q["words"]), np.array(q["xy"], dtype=np.uint16))
S = m.recognizer.score([item])
t2 = time.perf_counter()
m.recognizer.score([item])
t3 = time.perf_counter()
print(json.dumps({"load_s": t1 - t0, "first_query_ms": 1e3 * (t2 - t1), "second_query_ms": 1e3 * (t3 - t2),
                  "best": int(S[:, 0].argmax())}))
"""


def bench_map_load(out: Path, *, locations: int = 2200, tours: int = 5, features: int = 500,
                   n_words: int = 10000, repeats: int = 5, seed: int = 0) -> dict[str, Any]:
    """Build, save and reopen a Cooc-Map map of the paper's size; median of ``repeats`` fresh processes.

    Returns
    -------
    dict
        ``locations``, ``tours``, ``map_bytes``, ``save_s``, ``load_s_median``,
        ``load_s_max``, ``first_query_ms_median`` (pages of the map read on
        demand, and any one-off compilation), ``second_query_ms_median``,
        ``best_is_true`` (the query's best location is its own).
    """
    model, queries = synthetic_map(locations=locations, tours=tours, features=features, n_words=n_words,
                                   n_queries=1, seed=seed)
    rec = CoocMap()
    rec.model_ = model
    rec.place_ids_ = np.arange(locations, dtype=np.int64)
    rec.tour_order_ = list(model.tour_names)
    words = np.random.default_rng(seed).random((n_words, 128)).astype(np.float32)
    voc = Vocabulary.from_words(words, descriptor_kind="sift-128-float32")
    model.vocabulary = {}
    m = Map(rec, features=FeatureConfig(), vocabulary=voc, tours=[{"name": t} for t in model.tour_names],
            xy_sums=np.zeros((locations, 3)))
    t0 = time.perf_counter()
    m.save(out)
    save_s = time.perf_counter() - t0
    loc, qw, qxy = queries[0]
    q = json.dumps({"words": qw.tolist(), "xy": qxy.tolist()})
    runs = []
    for _ in range(repeats):
        res = subprocess.run([sys.executable, "-c", _LOAD, str(out), q], capture_output=True, text=True, check=True)
        runs.append(json.loads(res.stdout))
    return {
        "locations": locations, "tours": tours, "features_per_image": features, "map_bytes": out.stat().st_size,
        "save_s": round(save_s, 3),
        "load_s_median": round(float(np.median([r["load_s"] for r in runs])), 4),
        "load_s_max": round(float(np.max([r["load_s"] for r in runs])), 4),
        "first_query_ms_median": round(float(np.median([r["first_query_ms"] for r in runs])), 2),
        "second_query_ms_median": round(float(np.median([r["second_query_ms"] for r in runs])), 2),
        "best_is_true": all(r["best"] == loc for r in runs),
    }
