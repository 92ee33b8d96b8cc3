"""VerificationSpec: each bad value is one ParameterError naming the setting."""

from __future__ import annotations

import pytest

from topoloc.errors import ParameterError
from topoloc.spec import EvaluateSpec, VerificationSpec, spec_from_flat


@pytest.mark.parametrize("kwargs,name", [
    ({"enabled": "yes"}, "verification.enabled"), ({"candidates": 0}, "verification.candidates"),
    ({"candidates": True}, "verification.candidates"), ({"candidates": 2.5}, "verification.candidates"),
    ({"confirm": 1}, "verification.confirm"),
])
def test_bad_values_name_the_setting(kwargs: dict, name: str) -> None:
    with pytest.raises(ParameterError, match=name.replace(".", r"\.")):
        VerificationSpec(**kwargs)


def test_flat_names_reach_the_part(tmp_path: object) -> None:
    spec = spec_from_flat(EvaluateSpec, {"method": "bow", "maps": ["a"], "query": "b", "out": "c", "verify": False,
                                         "verify_candidates": 2, "confirm": True})
    assert spec.verification == VerificationSpec(enabled=False, candidates=2, confirm=True)
    assert VerificationSpec() == VerificationSpec(enabled=None, candidates=None, confirm=False)
