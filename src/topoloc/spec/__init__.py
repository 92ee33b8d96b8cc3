"""Run specifications: what a command runs, validated once, recorded, and made again from the record.

:mod:`~topoloc.spec.parts` holds the parts (features, vocabulary, inputs,
ground truth, sequence matching, execution, verification), :mod:`~topoloc.spec.runs` the
specification of each command, :mod:`~topoloc.spec.config` their plain-data
forms and configuration files, :mod:`~topoloc.spec.setup` the one function
that turns them into a recogniser's resources.
"""

from topoloc.spec.config import FLAT_NAMES, load_config, merge, nest, spec_from_dict, spec_from_flat, spec_to_dict
from topoloc.spec.parts import (
    SEQUENCE_MODES,
    ExecutionSpec,
    FeatureSpec,
    GroundTruthSpec,
    InputSpec,
    SequenceSpec,
    VerificationSpec,
    VocabularySpec,
    parse_max_side,
    parse_recall_at,
)
from topoloc.spec.runs import EvaluateSpec, LocalizeSpec, MapBuildSpec, NodeSpec, VocabTrainSpec

__all__ = [
    "FLAT_NAMES", "SEQUENCE_MODES", "EvaluateSpec", "ExecutionSpec", "FeatureSpec", "GroundTruthSpec",
    "InputSpec", "LocalizeSpec", "MapBuildSpec", "NodeSpec", "SequenceSpec", "VerificationSpec", "VocabTrainSpec",
    "VocabularySpec", "load_config",
    "merge", "nest", "parse_max_side", "parse_recall_at", "spec_from_dict", "spec_from_flat", "spec_to_dict",
]
