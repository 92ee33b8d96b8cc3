"""Local runs with the feature store against the per-image cache it replaced: time and disk, one JSON line.

    .venv/bin/python -m benchmarks.bench_feature_store [--repeats 2]

On the gardens_point day traverses (2 x 100 images, 960 x 540, SIFT, 1,000 features):

* ``per_image``: ``FeatureExtractor.extract_paths`` (one cache file per image, a thread
  per image: what ``CachedResources`` did before the store);
* ``store``: ``CachedResources.features`` (blocks of the feature store, filled through
  the local executor);

each cold (empty cache) and warm (everything cached, a new run), repeated and
interleaved so that both see the same machine load; plus the bytes each cache
holds, and quantisation of the same features with a 1,000-word vocabulary
(trained on the same descriptors: this measures speed only) as one loop in this
thread versus the executor's blocks.  Prints medians in seconds.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import GP, require_data
from topoloc.datasets.traverse import Traverse, load_traverse
from topoloc.features import FeatureExtractor
from topoloc.resources import CachedResources
from topoloc.vocabulary import Vocabulary


def _bytes(root: Path) -> int:
    return sum(f.stat().st_size for f in root.rglob("*") if f.is_file())


def _per_image(trav: Traverse, cache: Path) -> list[Any]:
    return FeatureExtractor(cache_dir=cache).extract_paths(trav.images)


def _store(trav: Traverse, cache: Path) -> list[Any]:
    return CachedResources(extractor=FeatureExtractor(cache_dir=cache)).features(trav)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    require_data()
    travs = [load_traverse(GP / name) for name in ("day_left", "day_right")]
    images = [p for t in travs for p in t.images]
    trav = Traverse(root=GP, images=tuple(images), places=np.arange(len(images)), name="gardens_point day")
    times: dict[str, list[float]] = {k: [] for k in ("per_image_cold", "store_cold", "per_image_warm", "store_warm")}
    disk: dict[str, int] = {}
    feats: list[Any] = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            order = [("per_image", _per_image), ("store", _store)]
            for name, fn in order if r % 2 == 0 else order[::-1]:
                cache = Path(tmp) / f"{name}{r}"
                t0 = time.perf_counter()
                feats = fn(trav, cache)
                times[f"{name}_cold"].append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                fn(trav, cache)
                times[f"{name}_warm"].append(time.perf_counter() - t0)
                disk[name] = _bytes(cache)
    desc = np.vstack([f.descriptors for f in feats])
    voc = Vocabulary(n_words=1000, seed=0).fit(desc[:: max(1, len(desc) // 50_000)], descriptor_kind="sift-128-float32")
    q: dict[str, list[float]] = {"quantise_loop": [], "quantise_executor": []}
    res = CachedResources(vocabulary=voc)
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        loop = [voc.quantize(f.descriptors) for f in feats]
        q["quantise_loop"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        blocks = res._quantize(Traverse.from_features(feats, name="bench"), False)
        q["quantise_executor"].append(time.perf_counter() - t0)
        assert all(np.array_equal(a, b) for a, b in zip(loop, blocks, strict=True))
    out = {"images": len(images), "repeats": args.repeats,
           **{k: round(float(np.median(v)), 3) for k, v in {**times, **q}.items()},
           "bytes_per_image_cache": disk["per_image"], "bytes_store": disk["store"],
           "files_per_image_cache": len(images)}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
