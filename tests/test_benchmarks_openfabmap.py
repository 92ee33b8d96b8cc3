"""The openFABMAP driver of the side-by-side benchmark (benchmarks/openfabmap.py) scores what topoloc scores.

openFABMAP is compiled from a clone of its public repository named by ``$OPENFABMAP_SRC`` (the
repository and commit in ``benchmarks/openfabmap.py``); where none is given (or OpenCV's headers are
missing) the test is skipped with the reason, which says how to get it.  Where it runs, the exported Chow-Liu
tree and detector must make openFABMAP's per-image log-likelihood (relative to the empty place)
equal to topoloc's FAB-MAP 2.0 one, or the timings would not be on the same model.
"""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType

import numpy as np
import pytest

from topoloc.fabmap.inverted_index import InvertedIndex
from topoloc.fabmap.model import FabMapModel
from topoloc.fabmap.normaliser import log_mean_exp
from topoloc.fabmap.observation import ObservationModel
from topoloc.synth.words import revisit_queries, zipf_occurrence


@pytest.fixture(scope="module")
def ofm(benchmark_module: Callable[[str], ModuleType]) -> ModuleType:
    mod = benchmark_module("openfabmap")
    try:
        mod.build_openfabmap()
    except mod.OpenFabMapUnavailable as e:
        pytest.skip(str(e))
    return mod


def test_openfabmap_scores_equal_topoloc_fabmap2(ofm: ModuleType) -> None:
    v = 300
    model = FabMapModel.train(zipf_occurrence(60, n_words=v, words_per_image=30, seed=1, permutation_seed=0),
                              n_words=v)
    places = zipf_occurrence(20, n_words=v, words_per_image=30, seed=2, permutation_seed=0)
    queries, truth = revisit_queries(places, 10, words_per_image=30, permutation_seed=0, seed=3)
    words = [places.indices[places.indptr[i]:places.indptr[i + 1]].astype(np.int64) for i in range(20)]
    training = model.training_words()
    out = ofm.run_openfabmap(model, training, words, queries, reps=1, likelihoods=True)
    om = ObservationModel(model)
    index, samples = InvertedIndex(om, words), InvertedIndex(om, training)
    for k, q in enumerate(queries):
        obs = om.observe(q)
        rel = index.relative_log_likelihood(obs)
        assert out["best"][k] == int(np.argmax(rel))
        assert out["log_lik_best"][k] == pytest.approx(rel.max(), rel=1e-9, abs=1e-9)
        np.testing.assert_allclose(out["log_lik"][:, k], rel, rtol=1e-9, atol=1e-9)
        # openFABMAP's p(new place) without a motion model: the likelihoods normalised over the map
        # images and the sampled new place (no location prior), then its smoothing 0.99
        joint = np.append(rel, log_mean_exp(samples.relative_log_likelihood(obs)))
        post = np.exp(joint - joint.max()) / np.exp(joint - joint.max()).sum()
        smoothed = 0.99 * post + 0.01 / post.size
        assert out["p_new"][k] == pytest.approx(smoothed[-1], rel=1e-6, abs=1e-12)
    assert np.mean(out["best"] == np.asarray(truth)) > 0.5  # revisits are found


def test_no_machine_path_is_assumed(benchmark_module: Callable[[str], ModuleType],
                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """Without ``$OPENFABMAP_SRC`` the sources are not looked for on one machine's path (issue #41)."""
    mod = benchmark_module("openfabmap")
    monkeypatch.delenv("OPENFABMAP_SRC", raising=False)
    assert not hasattr(mod, "DEFAULT_SRC")
    with pytest.raises(mod.OpenFabMapUnavailable, match=r"git clone https://github\.com/arrenglover/openfabmap"):
        mod.build_openfabmap()
