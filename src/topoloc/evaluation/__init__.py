"""Evaluation: metrics of docs/protocol.md, the evaluate pipeline, reports."""

from topoloc.evaluation.metrics import Scores, compute_metrics

__all__ = ["Scores", "compute_metrics"]
