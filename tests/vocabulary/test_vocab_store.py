"""The vocabulary sample is drawn from the feature store: each training image is described and stored once."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

import topoloc.features.store as store_mod
from topoloc.datasets.traverse import load_traverse
from topoloc.features import FeatureConfig, FeatureExtractor
from topoloc.resources import CachedResources
from topoloc.vocabulary.vocab import train_vocabulary


def test_training_fills_the_store_a_map_then_reads(tiny_route: dict[str, Any], tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    folder = Path(tiny_route["map"].root)
    cache = tmp_path / "cache"
    config = FeatureConfig(max_features=200)
    extracted: list[str] = []
    real = store_mod._extract_one

    def counted(path: str, cfg: FeatureConfig) -> Any:
        extracted.append(Path(path).name)
        return real(path, cfg)

    monkeypatch.setattr(store_mod, "_extract_one", counted)
    voc = train_vocabulary([folder], extractor=FeatureExtractor(config, cache_dir=cache), n_words=20)
    trav = load_traverse(folder)
    assert sorted(extracted) == sorted(p.name for p in trav.images)  # every image described once
    # Nothing went through the per-image cache: the images are stored once, in the store's blocks.
    assert not list(cache.rglob("*.tlf")) and list(cache.rglob("*.tlb"))
    extracted.clear()
    res = CachedResources(extractor=FeatureExtractor(config, cache_dir=cache), vocabulary=voc)
    assert len(res.words(trav)) == len(trav) and extracted == []  # the map's features come from that store
