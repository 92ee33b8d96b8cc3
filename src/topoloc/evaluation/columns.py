"""What makes two ``evaluate`` runs comparable: one short text per aspect of how a run was made.

``report`` (markdown) and the HTML page both show these columns beside the
scores, so that two rows of the same method that were run differently (another
tolerance, ground-truth file, vocabulary, preprocessing or feature setting) are
told apart at a glance.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from topoloc._params import keyword_defaults
from topoloc.errors import TopolocError
from topoloc.methods import get_method

#: (key, heading) of the columns of :func:`run_columns`, in table order.
COLUMNS: tuple[tuple[str, str], ...] = (
    ("method", "method and parameters"),
    ("map", "map"),
    ("query", "query"),
    ("ground_truth", "ground truth"),
    ("vocabulary", "vocabulary"),
    ("preprocess", "preprocessing"),
    ("features", "features"),
    ("sequence", "sequence"),
    ("verification", "verification"),
)


def _short(path: str) -> str:
    p = Path(path)
    return f"{p.parent.name}/{p.name}" if p.parent.name else p.name


def _params_text(m: dict[str, Any]) -> str:
    """The method with the parameters that differ from its defaults (all of them for an unknown method)."""
    params = {k: v for k, v in m.get("params", {}).items() if k not in ("sequence", "verify")}
    try:
        cls = get_method(str(m.get("method")))
        defaults = keyword_defaults(cls)
        # Runs of an earlier version under today's names, as saved maps are read (renamed and removed parameters).
        params = {k: v for k, v in cls.upgrade_params(params).items() if k not in defaults or defaults[k] != v}
    except TopolocError:
        pass
    body = ", ".join(f"{k}={json.dumps(v, default=str)}" for k, v in params.items())
    return f"{m.get('method', '?')} ({body})" if body else str(m.get("method", "?"))


#: A setting the run did not record (written by an older version): said so, not shown as a default (issue #41).
UNKNOWN = "unknown"


def _vocabulary_text(voc: dict[str, Any] | None) -> str:
    if not isinstance(voc, dict) or "used" not in voc:
        return UNKNOWN
    if not voc.get("used"):
        return "none" if not voc.get("train_folders") else "not trained"
    words = voc.get("n_words") or voc.get("words")
    if words is None and isinstance(voc.get("centers_shape"), list):
        words = voc["centers_shape"][0]
    source = voc.get("folders") or voc.get("train_folders")
    where = ", ".join(_short(str(f)) for f in source) if source else _short(str(voc.get("file", "?")))
    if voc.get("source") == "map tours":  # the default vocabulary (#27)
        where = "the map tours"
    n_img = f", {voc['n_images']} images" if voc.get("n_images") else ""
    size = f"{words} words, " if words else ""
    return f"{size}trained on {where}{n_img}"


#: The text of the feature and preprocessing cells of a method that reads no local features (its tags).
NOT_USED = "-"


def uses_local_features(m: dict[str, Any]) -> bool:
    """Whether the run's method reads local features, so that its feature settings and preprocessing matter.

    From the method's tags (:class:`~topoloc.methods.base.RecognizerTags`); a
    method this installation does not know is taken to use them (shown rather than hidden).
    """
    try:
        return get_method(str(m.get("method"))).tags.uses_local_features
    except TopolocError:
        return True


def uses_vocabulary(m: dict[str, Any]) -> bool:
    """Whether the run used a visual vocabulary (its record, else its method's tags)."""
    voc = m.get("run", {}).get("vocabulary", {})
    if isinstance(voc, dict) and "used" in voc:
        return bool(voc["used"])
    try:
        return get_method(str(m.get("method"))).tags.uses_vocabulary
    except TopolocError:
        return True


def _features_text(f: dict[str, Any]) -> str:
    if not f:
        return UNKNOWN
    side = f.get("max_side")
    side_text = f"max side {UNKNOWN}" if side is None else f"max side {side}" if side else "full size"
    return f"{f.get('method', UNKNOWN)}, <= {f.get('max_features', '?')} per image, {side_text}"


def run_columns(m: dict[str, Any]) -> dict[str, str]:
    """``{key: text}`` for each of :data:`COLUMNS` of one run's ``metrics.json``."""
    run = m.get("run", {})
    feats = run.get("features", {})
    maps = [_short(str(x)) for x in run.get("map", [])]
    seq = int(m.get("params", {}).get("sequence", 0) or 0)
    local = uses_local_features(m)
    return {
        "method": _params_text(m),
        "map": " + ".join(maps) if len(maps) <= 3 else f"{len(maps)} traverses {maps[0]} ... {maps[-1]}",
        "query": _short(str(run.get("query", "?"))),
        "ground_truth": str(run.get("ground_truth", "?")),
        "vocabulary": _vocabulary_text(run.get("vocabulary")),
        "preprocess": str(feats.get("preprocess", UNKNOWN)) if local else NOT_USED,
        "features": _features_text(feats) if local else NOT_USED,
        "sequence": str(seq) if seq > 1 else "off",
        # Runs written before verification existed were not verified.
        "verification": "on" if m.get("params", {}).get("verify") else "off",
    }


def differing_columns(runs: list[dict[str, Any]]) -> list[str]:
    """Keys of :data:`COLUMNS` whose text differs between ``runs`` (the method column excluded)."""
    cols = [run_columns(m) for m in runs]
    return [k for k, _ in COLUMNS if k != "method" and len({c[k] for c in cols}) > 1]


def distinct_labels(runs: list[dict[str, Any]], labels: list[str]) -> list[str]:
    """``labels`` made unique: where two are equal, append the columns in which their runs differ."""
    out = list(labels)
    cols = [run_columns(m) for m in runs]
    for label in set(labels):
        idx = [i for i, x in enumerate(labels) if x == label]
        if len(idx) < 2:
            continue
        diff = [k for k, _ in COLUMNS if len({cols[i][k] for i in idx}) > 1]
        for i in idx:
            extra = "; ".join(f"{k.replace('_', ' ')} {cols[i][k]}" for k in diff)
            out[i] = f"{label} [{extra or f'run {i + 1}'}]"
    return out


def shown_columns(runs: list[dict[str, Any]]) -> list[tuple[str, str]]:
    """The :data:`COLUMNS` a table of ``runs`` shows: those that say something of at least one run.

    The feature and preprocessing columns are left out when no run's method
    reads local features (a table of SeqSLAM runs), the vocabulary column when
    no run used a vocabulary, the verification column when no run was
    verified; in a mixed table the rows of the other methods
    show :data:`NOT_USED` there ("none" for the vocabulary).
    """
    hidden: set[str] = set()
    if not any(uses_local_features(m) for m in runs):
        hidden |= {"features", "preprocess"}
    if not any(uses_vocabulary(m) for m in runs):
        hidden.add("vocabulary")
    if not any(m.get("params", {}).get("verify") for m in runs):
        hidden.add("verification")
    return [(k, h) for k, h in COLUMNS if k not in hidden]


def markdown_table(runs: list[dict[str, Any]], names: list[str] | None = None) -> str:
    """A markdown table: run number (or ``names``) and the :func:`shown_columns`, plus timings."""
    columns = shown_columns(runs)
    vocab_s = any(k == "vocabulary" for k, _ in columns)
    head = "| run | " + " | ".join(h for _, h in columns) + " | fit s |" + (" vocabulary s |" if vocab_s else "") + "\n"
    rule = "| --- " * (len(columns) + 2 + vocab_s) + "|\n"
    rows = []
    for i, m in enumerate(runs):
        c = run_columns(m)
        name = names[i] if names else str(i + 1)
        run = m.get("run", {})
        fit = run.get("fit_seconds")
        voc_s = run.get("vocabulary_seconds")
        cells = [name, *(c[k].replace("|", "/") for k, _ in columns),
                 f"{fit:.2f}" if isinstance(fit, int | float) else "?"]
        if vocab_s:
            cells.append(f"{voc_s:.1f}" if isinstance(voc_s, int | float) and uses_vocabulary(m) else NOT_USED)
        rows.append("| " + " | ".join(cells) + " |\n")
    return head + rule + "".join(rows)
