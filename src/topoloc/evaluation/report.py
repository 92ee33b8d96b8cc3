"""Reports of ``evaluate`` runs: labels, markdown tables, ``report.md`` and side-by-side reports.

A run's label names the method with the parameters that differ from its
defaults, non-default features and preprocessing, and the sequence length, so
that two rows of a table that differ in how they were run never look alike.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from topoloc._params import keyword_defaults
from topoloc.errors import TopolocError
from topoloc.evaluation.columns import uses_local_features
from topoloc.evaluation.plots import plot_pr_curves
from topoloc.features import FeatureConfig
from topoloc.io.container import atomic_write_bytes
from topoloc.io.paths import check_kind
from topoloc.methods import get_method

#: Photometric preprocessing of ``evaluate`` when none is asked for (the feature default).
DEFAULT_PREPROCESS = FeatureConfig.preprocess


def _short(path: str) -> str:
    p = Path(path)
    return f"{p.parent.name}/{p.name}" if p.parent.name else p.name


def _maps_label(maps: list[str], sep: str) -> str:
    names = [_short(x) for x in maps]
    if len(names) > 3:
        return f"{len(names)} traverses {names[0]}{sep}...{sep}{names[-1]}"
    return sep.join(names)


def _method_label(m: dict[str, Any]) -> str:
    """Method name with the parameters that differ from its defaults, e.g. ``seqslam (search=acceleration)``."""
    params = dict(m.get("params", {}))
    seq = params.pop("sequence", 0)
    verified = params.pop("verify", False)
    tags = []
    try:
        cls = get_method(m["method"])
        defaults = keyword_defaults(cls)
        tags = [f"{k}={v}" for k, v in cls.upgrade_params(params).items() if k in defaults and defaults[k] != v]
    except TopolocError:
        pass  # a method this installation does not know: show the bare name
    # Feature settings say nothing of a method that reads no local features (SeqSLAM, descriptors).
    feats = m.get("run", {}).get("features", {}) if uses_local_features(m) else {}
    if feats.get("method", "sift") != "sift":
        tags.append(feats["method"])
    # Runs written before preprocessing existed had none.
    if feats and feats.get("preprocess", "none") != DEFAULT_PREPROCESS:
        tags.append(f"preprocess={feats['preprocess']}")
    mode = params.pop("sequence_mode", "constant")
    if seq:
        tags.append(f"seq {seq}" + (f" {mode}" if mode != "constant" else ""))
    if verified:
        tags.append("verified")
    return m["method"] + (f" ({', '.join(tags)})" if tags else "")




def run_title(m: dict[str, Any]) -> str:
    run = m.get("run", {})
    return f"{_method_label(m)}: {_maps_label(run.get('map', []), '+')} -> {_short(run.get('query', '?'))}"


TABLE_HEADER = (
    "| method | map | query | AUC | R@100P | R@1 | R@5 | R@10 | ms/query | ms features | peak MiB |\n"
    "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n"
)


def table_row(m: dict[str, Any]) -> str:
    """One markdown table row for a run's metrics."""
    run = m.get("run", {})
    maps = _maps_label(run.get("map", []), " + ")
    method = _method_label(m)
    return (
        f"| {method} | {maps} | {_short(run.get('query', '?'))} | {m['auc']:.3f} | "
        f"{m['recall_at_100_precision']:.3f} | {m['recall_at_1']:.3f} | {m['recall_at_5']:.3f} | "
        f"{m['recall_at_10']:.3f} | {m['ms_per_query']:.2f} | {m['ms_features']:.1f} | "
        f"{m['peak_rss_mb']:.0f} |\n"
    )


#: What the report says of a setting the run did not record (written by an older version): not a default.
UNKNOWN = "unknown (not recorded)"


def _features_line(f: dict[str, Any]) -> str:
    if "max_side" not in f:
        resize = f"image size {UNKNOWN}"
    else:
        side = int(f["max_side"] or 0)
        resize = (f"images longer than {side} px downscaled to a longer side of {side} px" if side
                  else "images at full size")
    if "max_side_option" in f:
        resize += f" (--max-side {f['max_side_option']})"
    cap = f"at most {f['max_features']} per image" if "max_features" in f else f"features per image {UNKNOWN}"
    return (f"{f.get('method', UNKNOWN)}, {cap}, {resize}, "
            f"photometric preprocessing {f.get('preprocess', UNKNOWN)}")


def render_run_report(m: dict[str, Any]) -> str:
    """``report.md`` of one run."""
    run = m["run"]
    voc = run.get("vocabulary")
    lines = [
        f"# {run_title(m)}\n\n",
        TABLE_HEADER,
        table_row(m),
        "\n## What was run\n\n",
        f"- method `{m['method']}`, parameters `{json.dumps(m['params'], default=str)}`\n",
        f"- map: {', '.join(f'`{x}`' for x in run['map'])}\n",
        f"- query: `{run['query']}` ({m['n_queries']} queries, {m['n_places']} map places)\n",
        f"- ground truth: {run['ground_truth']}\n",
        f"- local features: {_features_line(run.get('features') or {})}\n" if uses_local_features(m)
        else "- local features: none (this method does not use them; no feature settings or preprocessing apply)\n",
    ]
    if not isinstance(voc, dict) or "used" not in voc:
        lines.append(f"- vocabulary: {UNKNOWN}\n")
    elif voc.get("used"):
        prov = {k: v for k, v in voc.items() if k not in {"used"}}
        lines.append(f"- vocabulary: `{json.dumps(prov, default=str)}`\n")
    else:
        lines.append("- vocabulary: none (this method does not use one)\n")
    lines += [
        f"- fit time {run['fit_seconds']:.2f} s"
        + (f" (vocabulary loaded or trained apart: {run['vocabulary_seconds']:.1f} s)"
           if "vocabulary_seconds" in run else "")
        + f"; ms/query median {m['ms_per_query']:.2f}, "
        f"95th percentile {run['ms_per_query_p95']:.2f} (feature extraction excluded)\n",
    ]
    ver = m.get("verification")
    if isinstance(ver, dict):
        lines.append(f"- verification: {ver['verified_fraction']:.0%} of the answers verified (the best places of "
                     f"{ver['candidates']} distinct peaks per query checked); its ms/query median "
                     f"{ver['ms_per_query']:.2f}, 95th percentile {ver['ms_per_query_p95']:.2f}, included above\n")
    lines += [
        f"- machine: {run['machine']}; date {run['date']}\n",
    ]
    return "".join(lines)


def load_run(run_dir: Path) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
    """Metrics and PR curve (precision, recall) of an ``evaluate`` output folder."""
    mpath = run_dir / "metrics.json"
    check_kind(run_dir, "folder", "evaluate output folder")
    if not mpath.is_file():
        raise TopolocError(f"not an evaluate output folder (no metrics.json): {run_dir}")
    try:
        m = json.loads(mpath.read_text())
        pr = np.loadtxt(run_dir / "pr.csv", delimiter=",", skiprows=1, ndmin=2)
    except (ValueError, OSError) as exc:
        raise TopolocError(f"corrupt evaluate output ({exc.__class__.__name__}): {run_dir}") from None
    problem = _metrics_problem(m)
    if problem:
        raise TopolocError(f"metrics.json is not the metrics of an evaluate run ({problem}): {mpath}")
    if pr.shape[1] < 2:
        raise TopolocError(f"pr.csv needs columns precision,recall: {run_dir / 'pr.csv'}")
    return m, pr[:, 0], pr[:, 1]


#: What a report reads of each run's metrics.json, as numbers.
REPORT_NUMBERS = ("auc", "recall_at_100_precision", "recall_at_1", "recall_at_5", "recall_at_10", "ms_per_query",
                  "ms_features", "peak_rss_mb")


def _metrics_problem(m: Any) -> str:
    """What keeps ``m`` from being a run's metrics as reports read them ("" when nothing does)."""
    if not isinstance(m, dict):
        return f"a JSON {type(m).__name__}, not an object"
    if not isinstance(m.get("method"), str):
        return "no method name"
    if not isinstance(m.get("run", {}), dict) or not isinstance(m.get("params", {}), dict):
        return "'run' and 'params' must be objects"
    for key in REPORT_NUMBERS:
        value = m.get(key)
        if isinstance(value, bool) or not isinstance(value, int | float):
            return f"{key!r} is {'missing' if value is None else 'not a number'}"
    return ""


def build_report(run_dirs: list[Path], out: Path, title: str = "Results") -> Path:
    """Side-by-side table (``README.md``-style markdown) and one PNG of all PR curves."""
    runs = [load_run(Path(d)) for d in run_dirs]
    out.mkdir(parents=True, exist_ok=True)
    from topoloc.evaluation.columns import distinct_labels, markdown_table

    metrics = [m for m, _, _ in runs]
    rows = []
    for d, m in zip(run_dirs, metrics, strict=True):
        try:
            rows.append(table_row(m))
            markdown_table([m])
            run_title(m)
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            # A metrics.json of another version or edited by hand: name it rather than a traceback.
            raise TopolocError(f"metrics.json has another shape ({type(exc).__name__}: {exc}): "
                               f"{Path(d) / 'metrics.json'}") from None
    md = [f"# {title}\n\n", TABLE_HEADER, *rows]
    md.append("\nHow each run was made (rows are comparable where these agree):\n\n" + markdown_table(metrics))
    # Relative to the report, so that a report kept beside its runs (docs/results) names no machine's folders.
    md.append("\nRuns: " + ", ".join(f"`{os.path.relpath(Path(d).resolve(), out.resolve())}`" for d in run_dirs)
              + "\n\n![PR curves](pr_curves.png)\n")
    labels = distinct_labels(metrics, [run_title(m) for m in metrics])
    curves = [(f"{i + 1}. {label} (AUC {m['auc']:.2f})", p, r)
              for i, (label, (m, p, r)) in enumerate(zip(labels, runs, strict=True))]
    plot_pr_curves(curves, out / "pr_curves.png", title=title)
    path = out / "report.md"
    atomic_write_bytes(path, "".join(md).encode("utf-8", "surrogateescape"))
    return path

