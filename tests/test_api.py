"""The public API: the names importable from ``topoloc``, lazy loading, and the README's example."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import topoloc

README = Path(__file__).resolve().parents[1] / "README.md"

# Pinned: adding a public name is a decision, removing one breaks users.
PUBLIC = {
    "BagOfWords", "CachedResources", "CoocMap", "EvaluateSpec", "ExecutionSpec", "FabMap", "FabMap2", "FeatureConfig",
    "FeatureExtractor", "FeatureSet", "GlobalDescriptors", "GroundTruth", "ImageVoting", "InMemoryResources",
    "LandmarkMap", "LocalizeSpec", "Localizer", "Map", "MapBuildSpec", "FeatureSpec", "GroundTruthSpec", "InputSpec",
    "SequenceSpec", "VocabularySpec", "load_config",
    "NotFittedError", "PlaceRecognizer", "Resources", "Scores", "SeqSLAM", "SingleImageSeqSLAM", "TopolocError",
    "Traverse", "Vocabulary", "__version__", "available_methods", "compute_metrics", "evaluate",
    "extract_features", "get_method", "ground_truth_from_file", "ground_truth_from_places",
    "ground_truth_from_xy", "load_traverse", "read_image", "sequence_similarity", "spill_to", "train_vocabulary",
}


def test_public_names_are_pinned_and_resolve() -> None:
    assert set(topoloc.__all__) == PUBLIC
    for name in topoloc.__all__:
        assert getattr(topoloc, name) is not None, name
    assert set(PUBLIC) <= set(dir(topoloc))
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        topoloc.nope  # noqa: B018


def test_every_registered_method_is_public_by_class_name() -> None:
    for name in topoloc.available_methods():
        cls = topoloc.get_method(name)
        assert getattr(topoloc, cls.__name__) is cls
        assert issubclass(cls, topoloc.PlaceRecognizer)


def test_import_is_lazy() -> None:
    # The CLI imports the package first: it must not pull in OpenCV, faiss or matplotlib.
    code = "import sys, topoloc; print(sorted(m for m in ('cv2', 'faiss', 'matplotlib') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("marker", ["python-example", "map-example"])
def test_readme_example_runs(marker: str, tmp_path: Path) -> None:
    text = README.read_text()
    match = re.search(rf"<!-- {marker} -->\n```python\n(.*?)```", text, re.S)
    assert match, f"README lost its {marker}"
    script = tmp_path / "example.py"
    script.write_text(match.group(1))
    env = {**os.environ, "TOPOLOC_CACHE_DIR": str(tmp_path / "cache")}
    run = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, env=env,
                         timeout=300)
    assert run.returncode == 0, run.stderr
    if marker == "python-example":
        frames, share = re.search(r"(\d+) frames, (\d+)% within one place", run.stdout).groups()  # type: ignore[union-attr]
        assert int(frames) >= 30 and int(share) >= 80
        # In memory means in memory: the example never wrote a feature cache.
        assert not (tmp_path / "cache").exists()
    else:
        place, accepted = run.stdout.split()[:2]
        # The example localises frame 9 of the dusk tour; the route generator recorded its true place.
        truth = (tmp_path / "route" / "dusk" / "places.csv").read_text().splitlines()[1 + 9].split(",")[1]
        # An uncalibrated map accepts a verified answer, and every answer where it does not verify (here
        # TOPOLOC_VERIFY=0, as the test suite sets it).
        assert int(place) == int(truth) and accepted == "True"
        assert (tmp_path / "route.tlm").is_file()
