"""Shared fixtures: one tiny generated route (three tours of a synthetic street), read once per session."""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

if TYPE_CHECKING:
    from topoloc.fabmap.model import FabMapModel

# The suite's fixtures (vocabularies, maps, expected scores) are SIFT's: the default features ("auto": XFeat where
# the learned extra is installed) are pinned to SIFT for every test, subprocesses included. The learned default is
# tested on its own (tests/spec/test_feature_default.py), XFeat explicitly (tests/features/test_learned.py).
os.environ["TOPOLOC_FEATURES"] = "sift"
# Likewise their expected scores are unverified ones: verification (on by default, issue 40) is off unless a test
# asks for it (tests/verification/, and the tests that unset TOPOLOC_VERIFY to check the default).
os.environ["TOPOLOC_VERIFY"] = "0"


@pytest.fixture(scope="session")
def tiny_route(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A 10-place street at noon (map), at dusk (queries) and in the morning (vocabulary training).

    Returns a dict with the three file traverses (``map``, ``query``,
    ``training``), the query frames as BGR arrays (``query_frames``) and a
    300-word SIFT vocabulary trained on the morning tour (``vocabulary``).
    """
    from topoloc.datasets.traverse import load_traverse
    from topoloc.features import FeatureExtractor
    from topoloc.synth import RouteConfig, generate_route
    from topoloc.vocabulary import Vocabulary

    root = tmp_path_factory.mktemp("tiny_route")
    dirs = generate_route(root, config=RouteConfig(n_places=10, width=192, height=144, seed=3),
                          tours=[("noon", 12.0), ("dusk", 18.0), ("morning", 9.0)])
    noon, dusk, morning = (load_traverse(d) for d in dirs)
    ex = FeatureExtractor(use_cache=False)
    desc = np.vstack([ex.extract_path(p).descriptors for p in morning.images])
    voc = Vocabulary(n_words=300, seed=0).fit(desc, descriptor_kind=ex.config.descriptor_kind,
                                              provenance={"folders": [str(Path(dirs[2]))]})
    frames = [dusk.read(i, gray=False) for i in range(len(dusk))]
    for trav in (noon, dusk, morning):  # global descriptors "computed elsewhere", for --method descriptors
        np.save(trav.root / "descriptors.npy", np.stack([thumbnail_descriptor(trav.read(i)) for i in range(len(trav))]))
    return {"map": noon, "query": dusk, "training": morning, "query_frames": frames, "vocabulary": voc}


@pytest.fixture(scope="session")
def tiny_route_map(tiny_route: dict[str, Any], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A bag-of-words map file of the tiny route's noon tour (its 300-word vocabulary), built once per session."""
    from typer.testing import CliRunner

    from topoloc.cli.main import app

    root = tmp_path_factory.mktemp("tiny_route_map")
    voc = root / "vocab.tlv"
    tiny_route["vocabulary"].save(voc)
    map_file = root / "map.tlm"
    r = CliRunner().invoke(app, ["map", "build", "--method", "bow", "--map", str(tiny_route["map"].root),
                                 "--vocab", str(voc), "--out", str(map_file), "--cache-dir", str(root / "cache"),
                                 "-q"])
    assert r.exit_code == 0, r.output + repr(r.exception)
    return map_file


@pytest.fixture(scope="session")
def xfeat_route(tiny_route: dict[str, Any]) -> dict[str, Any]:
    """The tiny route described with XFeat: ``tiny_route``'s entries, its ``features`` and an XFeat ``vocabulary``.

    ``features`` is ``FeatureConfig(method="xfeat")`` (the default cap, as
    ``--features xfeat`` gives); ``vocabulary`` is 300 words of k-means on the
    XFeat descriptors of the morning tour (its folder recorded, as FAB-MAP
    needs), replacing the SIFT one.  XFeat runs on ONNX Runtime, a core dependency: nothing to skip.
    """
    from topoloc.features import FeatureConfig, FeatureExtractor
    from topoloc.vocabulary import Vocabulary

    config = FeatureConfig(method="xfeat")
    morning = tiny_route["training"]
    ex = FeatureExtractor(config, use_cache=False)
    desc = np.vstack([ex.extract_path(p).descriptors for p in morning.images])
    voc = Vocabulary(n_words=300, seed=0).fit(desc, descriptor_kind=config.descriptor_kind,
                                              provenance={"folders": [str(morning.root)]})
    return {**tiny_route, "features": config, "vocabulary": voc}


def thumbnail_descriptor(gray: np.ndarray) -> np.ndarray:
    """A 192-D global descriptor of a grey image: a 16 x 12 thumbnail with zero mean and unit variance."""
    import cv2

    small = cv2.resize(gray, (16, 12), interpolation=cv2.INTER_AREA).astype(np.float32).ravel()
    return (small - small.mean()) / max(float(small.std()), 1e-6)


@pytest.fixture(scope="session")
def fabmap_loop_model() -> FabMapModel:
    """A FAB-MAP model trained on 300 Zipf-distributed images of a 400-word vocabulary (online SLAM tests)."""
    from topoloc.fabmap.model import FabMapModel
    from topoloc.synth.words import zipf_occurrence

    x = zipf_occurrence(300, n_words=400, words_per_image=40, seed=21, permutation_seed=0)
    return FabMapModel.train(x, n_words=400)


@pytest.fixture(scope="session")
def dask_scheduler() -> Any:
    """The address of a real Dask cluster on localhost: a scheduler and 2 worker processes (1 thread each).

    Skips when the ``distributed`` extra is not installed.  Started once per
    test session (a few seconds) and closed at its end.
    """
    distributed = pytest.importorskip("distributed")
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                       host="127.0.0.1", silence_logs=40)
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()


@pytest.fixture(scope="session")
def benchmark_module() -> Callable[[str], ModuleType]:
    """Import ``benchmarks.<name>`` from this checkout (benchmarks/ is not an installed package)."""
    root = str(Path(__file__).resolve().parents[1])
    if root not in sys.path:
        sys.path.insert(0, root)
    return lambda name: importlib.import_module(f"benchmarks.{name}")
