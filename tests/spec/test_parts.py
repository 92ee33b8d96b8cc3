"""Each part of a run specification checks its values once, naming the parameter."""

from __future__ import annotations

from pathlib import Path

import pytest

from topoloc.errors import ParameterError
from topoloc.spec import (
    EvaluateSpec,
    ExecutionSpec,
    FeatureSpec,
    GroundTruthSpec,
    InputSpec,
    LocalizeSpec,
    MapBuildSpec,
    SequenceSpec,
    VocabularySpec,
    parse_recall_at,
)


@pytest.mark.parametrize(("make", "param"), [
    (lambda: FeatureSpec(max_side="big"), "features.max_side"),
    (lambda: FeatureSpec(max_side=-1), "features.max_side"),
    (lambda: VocabularySpec(file=Path("v.tlv"), train=(Path("d"),)), "vocabulary"),
    (lambda: VocabularySpec(words=0), "vocabulary.words"),
    (lambda: InputSpec(every_s=0.0), "inputs.every_s"),
    (lambda: InputSpec(every_m=float("nan")), "inputs.every_m"),
    (lambda: InputSpec(every_s=float("inf")), "inputs.every_s"),
    (lambda: GroundTruthSpec(tolerance="3"), "ground_truth.tolerance"),
    (lambda: GroundTruthSpec(tolerance="0:nan"), "ground_truth.tolerance"),
    (lambda: GroundTruthSpec(tolerance="0:inf"), "ground_truth.tolerance"),
    (lambda: GroundTruthSpec(tolerance_m="5:1"), "ground_truth.tolerance_m"),
    (lambda: GroundTruthSpec(file=Path("/no/such/gt.npy")), "ground_truth.file"),
    (lambda: SequenceSpec(length=-1), "sequence.length"),
    (lambda: SequenceSpec(mode="sideways"), "sequence.mode"),
    (lambda: ExecutionSpec(scheduler_timeout=0), "execution.scheduler_timeout"),
    (lambda: ExecutionSpec(scheduler_timeout=float("nan")), "execution.scheduler_timeout"),
    (lambda: ExecutionSpec(scheduler="http://127.0.0.1:8787"), "execution.scheduler"),
    (lambda: ExecutionSpec(scheduler="tcp://"), "execution.scheduler"),
    (lambda: parse_recall_at("0"), "recall_at"),
    (lambda: EvaluateSpec(method="bow", query=Path("q"), out=Path("o")), "maps"),
    (lambda: EvaluateSpec(maps=(Path("m"),), query=Path("q"), out=Path("o")), "method"),
    (lambda: EvaluateSpec(method="bow", maps=(Path("m"),), out=Path("o")), "query"),
    (lambda: EvaluateSpec(method="bow", maps=(Path("m"),), query=Path("q"), out=Path("o"), top_k=-1), "top_k"),
    (lambda: EvaluateSpec(method="bow", maps=(Path("m"),), map_file=Path("m.tlm"), query=Path("q"),
                          out=Path("o")), "maps/map_file"),
    (lambda: EvaluateSpec(map_file=Path("m.tlm"), query=Path("q"), out=Path("o"),
                          vocabulary=VocabularySpec(train=(Path("d"),))), "map_file"),
    (lambda: MapBuildSpec(method="bow", maps=(Path("m"),), shards=0), "shards"),
    (lambda: LocalizeSpec(map_file=Path("m.tlm"), images=(Path("i"),), out=Path("o"), top_k=0), "top_k"),
])
def test_a_bad_value_names_its_parameter_in_one_line(make, param) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ParameterError) as info:
        make()
    assert info.value.param == param
    assert "\n" not in str(info.value) and str(info.value).startswith(param)


def test_good_values_are_normalised() -> None:
    assert FeatureSpec(max_side=" AUTO ").max_side == "auto" and FeatureSpec(max_side="640").max_side == 640
    v = VocabularySpec(train=["a", Path("b")])  # type: ignore[arg-type]
    assert v.train == (Path("a"), Path("b")) and v.given and not VocabularySpec().given
    assert EvaluateSpec(method="bow", maps=["m"], query="q", out="o").maps == (Path("m"),)  # type: ignore[arg-type]
    for address in ("tcp://10.0.0.5:8786", "TLS://host:8786", "127.0.0.1:8786", ""):  # no scheme: Dask's tcp
        assert ExecutionSpec(scheduler=address).scheduler == address


def test_feature_spec_auto_is_one_rule_per_image() -> None:
    from topoloc.spec.parts import AUTO_MAX_SIDE

    # Whatever tours a run or a map holds: the scale never depends on them (issue 27).
    assert FeatureSpec().config().max_side == AUTO_MAX_SIDE
    assert FeatureSpec(max_side=50).config().max_side == 50
    assert FeatureSpec(max_side="0").config().max_side == 0
