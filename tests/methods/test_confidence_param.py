"""Every recogniser's ``confidence`` parameter: ``"margin"`` by default, ``"raw"`` its own scores."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from topoloc.confidence import peak_margin
from topoloc.errors import TopolocError
from topoloc.methods import available_methods, get_method
from topoloc.resources import InMemoryResources

# Small parameter changes so that each method runs in well under a second on 10 places.
FAST: dict[str, dict[str, Any]] = {"fabmap": {"n_samples": 20}, "fabmap2": {"n_samples": 20},
                                   "seqslam": {"ds": 3, "enhance_window": 0}, "seqslam-single": {"enhance_window": 0}}


RAW_BY_DEFAULT = ("landmarks", "descriptors", "seqslam-single")


def _fit(name: str, route: dict[str, Any], **params: Any) -> Any:
    p = {**FAST.get(name, {}), **params}
    if name == "descriptors":
        p["query"] = str(route["query"].root / "descriptors.npy")
    res = InMemoryResources(vocabulary=route["vocabulary"], training=route["training"])
    return get_method(name)(**p).fit(route["map"], resources=res)


@pytest.mark.parametrize("name", available_methods())
def test_margin_is_the_margin_of_the_raw_scores(name: str, tiny_route: dict[str, Any]) -> None:
    # Raw by default where the method's own score already thresholds across queries (see its docstring).
    expected = "raw" if name in RAW_BY_DEFAULT else "margin"
    assert get_method(name).default_params()["confidence"] == expected
    raw = _fit(name, tiny_route, confidence="raw").similarity(tiny_route["query"])
    default = _fit(name, tiny_route, confidence="margin").similarity(tiny_route["query"])
    np.testing.assert_allclose(default, peak_margin(raw), rtol=1e-6, atol=1e-6)
    # Same ranking in every column: R@N cannot change.
    assert np.array_equal(np.argsort(-default, axis=0, kind="stable"), np.argsort(-raw, axis=0, kind="stable"))
    assert (default.max(axis=0) >= 0).all()


@pytest.mark.parametrize("name", available_methods())
def test_a_bad_confidence_is_a_one_line_error(name: str, tiny_route: dict[str, Any]) -> None:
    with pytest.raises(TopolocError, match=r"confidence must be one of 'margin', 'raw', got 'ratio'") as err:
        _fit(name, tiny_route, confidence="ratio")
    assert "\n" not in str(err.value)



def test_fabmap_keeps_its_posterior(tiny_route: dict[str, Any]) -> None:
    # A posterior is FAB-MAP's own confidence (a probability): the margin leaves it as it is.
    raw = _fit("fabmap2", tiny_route, output="posterior", confidence="raw").similarity(tiny_route["query"])
    default = _fit("fabmap2", tiny_route, output="posterior").similarity(tiny_route["query"])
    np.testing.assert_array_equal(default, raw)
