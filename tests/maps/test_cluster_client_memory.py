"""On a Dask cluster no step gathers the route's per-image features on the client.

Vocabulary training, ``map build --shards``, a one-piece build, ``map add`` and batch
``localize`` run on a real local cluster (2 worker processes); on the client, reading
feature blocks or per-image features of a file traverse fails the test, and every
task result that comes back is inspected for descriptors.  What may come back is
small per image (word ids and keypoint positions, 12 bytes a feature) or per place
(the shards' models, the score columns of query frames).  Verification (off here) reads the
map images' features on the client by design: it runs after the sequence search, in frame order.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from topoloc.features import FeatureConfig, FeatureExtractor
from topoloc.features.local import FeatureSet


def _descriptor_like(obj: Any, dim: int, seen: list[str], where: str = "result", *, allow_rows: int = 0) -> None:
    """Record in ``seen`` every FeatureSet, or array of ``dim`` columns (descriptors) of more than
    ``allow_rows`` rows (the vocabulary sample's bound per task), inside a task result."""
    if isinstance(obj, FeatureSet):
        seen.append(f"{where}: FeatureSet")
    elif isinstance(obj, np.ndarray):
        if obj.ndim == 2 and obj.shape[1] == dim and obj.shape[0] > allow_rows:
            seen.append(f"{where}: array {obj.shape}")
    elif isinstance(obj, dict):
        for k, v in obj.items():
            _descriptor_like(v, dim, seen, f"{where}[{k!r}]", allow_rows=allow_rows)
    elif isinstance(obj, list | tuple):
        for k, v in enumerate(obj):
            _descriptor_like(v, dim, seen, f"{where}[{k}]", allow_rows=allow_rows)
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for f in dataclasses.fields(obj):
            _descriptor_like(getattr(obj, f.name), dim, seen, f"{where}.{f.name}", allow_rows=allow_rows)


def test_no_step_gathers_per_image_features_on_the_client(tiny_route: dict[str, Any], tmp_path: Path,
                                                          dask_scheduler: str,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    import topoloc.features.store as store_mod
    from topoloc.cluster import DaskExecutor, connect
    from topoloc.maps.batch import localize_on
    from topoloc.maps.map import Map
    from topoloc.resources import CachedResources
    from topoloc.vocabulary.vocab import cached_vocabulary

    cache = tmp_path / "cache"
    config = FeatureConfig(max_features=300)
    dim = config.descriptor_dim
    gathered: list[str] = []

    def refuse(*args: Any, **kw: Any) -> Any:
        gathered.append("per-image features read on the client")
        raise AssertionError("per-image features read on the client")

    monkeypatch.setattr(store_mod, "read_block", refuse)  # the workers' own module is not patched
    monkeypatch.setattr(CachedResources, "_file_features", refuse)
    real_result = DaskExecutor._result
    returned = [0]
    sample = 200

    def inspected(self: DaskExecutor, fut: Any) -> Any:
        out = real_result(self, fut)
        returned[0] += 1
        # The vocabulary's sample is descriptors, at most max_descriptors from each block; nothing else is.
        _descriptor_like(out, dim, gathered, allow_rows=sample)
        return out

    monkeypatch.setattr(DaskExecutor, "_result", inspected)
    map_dir, add_dir = Path(tiny_route["map"].root), Path(tiny_route["training"].root)
    with connect(dask_scheduler, timeout_s=30) as ex:
        voc, _ = cached_vocabulary([map_dir], extractor=FeatureExtractor(config, cache_dir=cache), n_words=50,
                                   max_descriptors=sample, executor=ex)
        for shards in (3, 1):
            m = Map.build(method="coocmap", tours=[map_dir], vocabulary=voc, features=config, cache_dir=cache,
                          shards=shards, executor=ex)
            # The shards read the map tour's store that the vocabulary filled: no image is stored twice.
            assert len(list((cache / "features" / config.key() / "store").iterdir())) == 1
        m.save(tmp_path / "route.tlm")
        m = Map.load(tmp_path / "route.tlm")
        m.add_tour(add_dir, cache_dir=cache, executor=ex).save(tmp_path / "route.tlm")
        loc = Map.load(tmp_path / "route.tlm").localizer(top_k=1, verify=False)
        frames = ((f"q{k}", None, f) for k, f in enumerate(tiny_route["query_frames"]))
        lines = [line for line, _ in localize_on(ex, loc, frames)]
    assert len(lines) == len(tiny_route["query_frames"])
    assert returned[0] > 0 and gathered == []
    monkeypatch.undo()
    # The same map as built here in one piece from the same tours, without a cluster.
    local = Map.build(method="coocmap", tours=[map_dir], vocabulary=voc, features=config,
                      cache_dir=tmp_path / "local_cache").add_tour(add_dir, cache_dir=tmp_path / "local_cache")
    _, arrays_a = m.recognizer.get_state()
    _, arrays_b = local.recognizer.get_state()
    assert sorted(arrays_a) == sorted(arrays_b)
    assert all(arrays_a[k].tobytes() == arrays_b[k].tobytes() for k in arrays_a)


@pytest.fixture(autouse=True)
def _pickle_by_value() -> None:
    cloudpickle = pytest.importorskip("cloudpickle")
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
