"""Run tables show only the inputs a method uses, and read runs of earlier versions under today's names."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.evaluation.columns import NOT_USED, markdown_table, run_columns, shown_columns
from topoloc.evaluation.report import build_report, render_run_report, run_title, table_row


def _metrics(method: str, params: dict[str, Any] | None = None, *, vocabulary: bool = False,
             preprocess: str = "auto") -> dict[str, Any]:
    """A run's metrics.json as ``evaluate`` writes it (the parts the tables read)."""
    voc: dict[str, Any] = ({"used": True, "n_words": 500, "train_folders": ["x/train"], "n_images": 9}
                           if vocabulary else {"used": False})
    return {
        "method": method, "params": {**(params or {}), "sequence": 0},
        "auc": 0.5, "recall_at_100_precision": 0.1, "recall_at_1": 0.6, "recall_at_5": 0.7, "recall_at_10": 0.8,
        "ms_per_query": 1.0, "ms_features": 2.0, "peak_rss_mb": 100.0, "n_queries": 10, "n_places": 10,
        "run": {"map": ["data/day"], "query": "data/night", "ground_truth": "place ids, tolerance 0:2",
                "features": {"method": "sift", "max_features": 1000, "max_side": 640, "preprocess": preprocess},
                "vocabulary": voc, "fit_seconds": 0.5, "vocabulary_seconds": 3.0 if vocabulary else 0.0,
                "ms_per_query_p95": 1.5, "machine": "test", "date": "today"},
    }


def test_rows_of_methods_without_local_features_show_no_feature_settings() -> None:
    seq = _metrics("seqslam", preprocess="clahe")
    bow = _metrics("bow", vocabulary=True)
    c = run_columns(seq)
    assert c["features"] == NOT_USED and c["preprocess"] == NOT_USED and c["vocabulary"] == "none"
    assert "sift" in run_columns(bow)["features"] and run_columns(bow)["preprocess"] == "auto"
    # A preprocessing the method never applied is no part of its label either.
    assert "preprocess" not in table_row(seq) and "preprocess=clahe" in table_row(_metrics("bow", preprocess="clahe"))
    # A table of SeqSLAM runs has no feature, preprocessing or vocabulary column at all.
    only = markdown_table([seq, _metrics("seqslam-single")])
    head = only.splitlines()[0]
    assert "features" not in head and "preprocessing" not in head and "vocabulary" not in head
    assert [k for k, _ in shown_columns([seq])] == ["method", "map", "query", "ground_truth", "sequence"]
    # A mixed table has the columns; the SeqSLAM row says it uses none of them.
    mixed = markdown_table([bow, seq]).splitlines()
    assert "| features |" in mixed[0] and "| vocabulary s |" in mixed[0]
    row = [x.strip() for x in mixed[3].split("|")]
    assert row.count(NOT_USED) == 3 and "sift" not in mixed[3]
    assert "does not use them" in render_run_report(seq) and "sift, at most 1000" in render_run_report(bow)
    # A method this installation does not know shows everything it recorded.
    assert "sift" in run_columns(_metrics("someone_elses_method"))["features"]


def test_runs_of_earlier_versions_read_under_todays_parameter_names() -> None:
    # coocmap's max_features is max_words_per_image now, and model_path is gone: at their defaults, not shown.
    old = _metrics("coocmap", {"max_features": 0, "model_path": "", "top_k": 10}, vocabulary=True)
    assert run_columns(old)["method"] == "coocmap" and run_title(old).startswith("coocmap:")
    changed = _metrics("coocmap", {"max_features": 300}, vocabulary=True)
    assert run_columns(changed)["method"] == "coocmap (max_words_per_image=300)"


def test_report_names_its_runs_relative_to_itself(tmp_path: Path) -> None:
    runs = []
    for name, m in (("seq", _metrics("seqslam")), ("bow", _metrics("bow", vocabulary=True))):
        d = tmp_path / "runs" / name
        d.mkdir(parents=True)
        (d / "metrics.json").write_text(json.dumps(m))
        np.savetxt(d / "pr.csv", np.array([[1.0, 0.0], [0.5, 0.6]]), delimiter=",", header="precision,recall")
        runs.append(d)
    text = build_report(runs, tmp_path / "report", title="T").read_text()
    assert "Runs: `../runs/seq`, `../runs/bow`" in text and str(tmp_path) not in text
