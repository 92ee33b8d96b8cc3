"""``topoloc evaluate``: run one method on map and query traverses and score it.

This is the single door of ``PROTOCOL.md``.  Outputs under ``out``:

``S.npy``
    float32 (n_places, n_queries), higher = more similar.
``places.npy`` / ``queries.npy``
    place id of each row / true place id of each column.
``metrics.json``
    the metrics of the protocol plus a ``run`` block describing what ran.
``pr.png``, ``pr.csv``
    the precision-recall curve (``pr.csv``: columns precision,recall).
``report.md``
    the table and what was run, including the vocabulary's provenance.
"""

from __future__ import annotations

import inspect
import io
import json
import logging
import os
import platform
import resource
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.datasets.groundtruth import (
    GroundTruth,
    ground_truth_from_file,
    ground_truth_from_places,
    ground_truth_from_xy,
    parse_tolerance,
    place_positions,
)
from topoloc.datasets.traverse import Traverse, find_images, load_traverse, read_image
from topoloc.errors import TopolocError
from topoloc.evaluation.metrics import Scores, compute_metrics
from topoloc.evaluation.plots import plot_pr_curves
from topoloc.io.container import atomic_write_bytes
from topoloc.methods import get_method
from topoloc.methods.base import PlaceRecognizer, ProgressFactory, Resources, parse_param

log = logging.getLogger(__name__)


@dataclass
class EvaluateOptions:
    """Everything ``topoloc evaluate`` takes (see ``PROTOCOL.md``)."""

    method: str
    maps: list[Path]
    query: Path
    out: Path
    vocab: Path | None = None
    vocab_train: list[Path] = field(default_factory=list)
    vocab_words: int = 10000
    tolerance: str = "0:8"
    tolerance_m: str | None = None
    ground_truth: Path | None = None
    sequence: int = 0
    params: dict[str, str] = field(default_factory=dict)
    features: str = "sift"
    max_features: int = 1000
    max_side: str = "auto"
    preprocess: str = "none"
    cache_dir: Path | None = None
    seed: int = 0


def _save_npy(path: Path, arr: np.ndarray) -> None:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    atomic_write_bytes(path, buf.getvalue())


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, in MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def build_method(name: str, params: dict[str, str]) -> PlaceRecognizer:
    """Instantiate method ``name`` with ``--param`` strings converted to their types."""
    cls = get_method(name)
    kwargs = {k: parse_param(cls, k, v) for k, v in params.items()}
    return cls(**kwargs)


def resolve_max_side(
    spec: str | int, traverses: Sequence[Traverse], *, images: Sequence[Path] = ()
) -> int:
    """The ``max_side`` to extract features at: ``spec`` itself, or for ``"auto"`` a common scale.

    SIFT and its kin are scale-invariant only up to their sampling of scale space:
    the same scene imaged at 960 and at 640 pixels yields different keypoints, which
    costs matches between traverses taken with different cameras or settings (on
    gardens_point the night traverse is 640 x 360, the day traverses 960 x 540).
    ``"auto"`` therefore returns the smallest longer image side found in
    ``traverses`` when they differ (every traverse is then extracted at that size),
    and 0 (no resizing) when all sizes agree.  The first, middle and last image
    of each traverse, and every file in ``images``, are read to find the sizes.

    Raises
    ------
    TopolocError
        If ``spec`` is neither ``"auto"`` nor a non-negative integer, or a sampled
        image cannot be read.
    """
    text = str(spec).strip().lower()
    if text != "auto":
        try:
            value = int(text)
        except ValueError:
            raise TopolocError(f"--max-side must be 'auto' or a number of pixels, got {spec!r}") from None
        if value < 0:
            raise TopolocError(f"--max-side must be >= 0 (0 = no resizing), got {value}")
        return value
    probe = list(images)
    for trav in traverses:
        n = len(trav.images)
        probe += [trav.images[i] for i in sorted({0, n // 2, n - 1})] if n else []
    sides = {max(read_image(path).shape[:2]) for path in probe}
    return min(sides) if len(sides) > 1 else 0


def make_resources(
    *,
    vocab: Path | None = None,
    vocab_train: list[Path] | None = None,
    vocab_words: int = 10000,
    features: str = "sift",
    max_features: int = 1000,
    max_side: int = 0,
    preprocess: str = "none",
    cache_dir: Path | None = None,
    seed: int = 0,
    needs_vocabulary: str = "",
    progress: ProgressFactory | None = None,
) -> tuple[Resources, dict[str, Any]]:
    """Feature extractor and vocabulary for a run, with the vocabulary's provenance.

    ``needs_vocabulary`` names the user of the vocabulary (a method, a command);
    when set, a missing ``vocab``/``vocab_train`` is an error.
    """
    from topoloc.features import FeatureConfig, FeatureExtractor

    config = FeatureConfig(method=features, max_features=max_features, max_side=max_side, preprocess=preprocess)
    extractor = FeatureExtractor(config, cache_dir=cache_dir)
    vocab_info: dict[str, Any] = {"used": False}
    vocabulary: Any = None
    training_images: list[Path] = []
    if vocab is not None:
        from topoloc.vocabulary import Vocabulary

        vocabulary = Vocabulary.load(vocab)
        vocabulary.check_compatible(extractor.config.descriptor_kind, source=vocab)
        vocab_info = {"used": True, "file": str(vocab), **vocabulary.provenance_}
    elif vocab_train:
        from topoloc.vocabulary import cached_vocabulary

        training_images = find_images(vocab_train)
        folders = list(vocab_train)

        def provide() -> Any:
            voc, path = cached_vocabulary(
                folders, extractor=extractor, n_words=vocab_words, seed=seed, cache_dir=cache_dir,
                progress=progress,
            )
            vocab_info.update({"used": True, "file": str(path), **voc.provenance_})
            return voc

        vocabulary = provide
        vocab_info = {"used": False, "train_folders": [str(f) for f in folders]}
    elif needs_vocabulary:
        raise TopolocError(f"{needs_vocabulary} needs a vocabulary: pass --vocab FILE or --vocab-train DIR")
    res = Resources(extractor=extractor, vocabulary=vocabulary, progress=progress, training_images=training_images)
    return res, vocab_info


def make_ground_truth(
    opts: EvaluateOptions, maps: list[Traverse], query: Traverse, place_ids: np.ndarray
) -> GroundTruth:
    """Ground truth from ``--ground-truth``, ``--tolerance-m`` or ``--tolerance``."""
    if opts.ground_truth is not None:
        return ground_truth_from_file(
            opts.ground_truth, map_traverse=maps[0], place_ids=place_ids, n_queries=len(query)
        )
    if opts.tolerance_m is not None:
        hard, soft = parse_tolerance(opts.tolerance_m)
        if query.xy is None:
            raise TopolocError(f"--tolerance-m needs x,y columns in places.csv: {query.root}")
        return ground_truth_from_xy(place_positions(maps, place_ids), query.xy, hard, soft)
    hard, soft = parse_tolerance(opts.tolerance)
    return ground_truth_from_places(place_ids, query.places, hard, soft)


def score_queries(
    method: PlaceRecognizer, items: list[Any], progress: ProgressFactory
) -> tuple[np.ndarray, np.ndarray]:
    """Score every query; returns ``S`` and the milliseconds of each query.

    Methods that need the whole sequence are timed once and the total is
    divided evenly over the queries.
    """
    if method.scores_whole_sequence:
        t0 = time.perf_counter()
        S = method.score(items)
        ms = 1e3 * (time.perf_counter() - t0) / max(len(items), 1)
        return S, np.full(len(items), ms)
    cols = []
    ms_each = np.empty(len(items))
    advance = progress(f"matching ({method.name})", len(items))
    for j, item in enumerate(items):
        t0 = time.perf_counter()
        cols.append(method.score([item]))
        ms_each[j] = 1e3 * (time.perf_counter() - t0)
        advance(1)
    S = np.concatenate(cols, axis=1) if cols else np.zeros((len(method.place_ids_), 0))
    return S, ms_each


def apply_sequence(S: np.ndarray, n: int) -> tuple[np.ndarray, float]:
    """Sequence matching (SeqSLAM search, ``ds = n``: the query and the ``n`` before it).

    Returns the sequence-matched S and the added milliseconds per query.
    """
    from topoloc.sequence import sequence_similarity

    t0 = time.perf_counter()
    out = sequence_similarity(S, ds=n)
    return out, 1e3 * (time.perf_counter() - t0) / max(S.shape[1], 1)


def evaluate(opts: EvaluateOptions, *, progress: ProgressFactory | None = None) -> dict[str, Any]:
    """Run ``opts.method`` and write every output file of ``PROTOCOL.md`` under ``opts.out``.

    Returns
    -------
    dict
        The content of ``metrics.json``.
    """
    prog: ProgressFactory = progress or (lambda d, t: (lambda n: None))
    if not opts.maps:
        raise TopolocError("evaluate needs at least one --map traverse")
    # Validate every cheap option before any expensive work starts.
    parse_tolerance(opts.tolerance)
    if opts.tolerance_m is not None:
        parse_tolerance(opts.tolerance_m)
    if opts.ground_truth is not None and not Path(opts.ground_truth).is_file():
        raise TopolocError(f"ground-truth file not found: {opts.ground_truth}")
    maps = [load_traverse(m) for m in opts.maps]
    query = load_traverse(opts.query)
    method = build_method(opts.method, opts.params)
    max_side = resolve_max_side(opts.max_side, [*maps, query])
    resources, vocab_info = make_resources(
        vocab=opts.vocab, vocab_train=opts.vocab_train, vocab_words=opts.vocab_words, features=opts.features,
        max_features=opts.max_features, max_side=max_side, preprocess=opts.preprocess,
        cache_dir=opts.cache_dir, seed=opts.seed,
        needs_vocabulary=f"method {method.name!r}" if method.uses_vocabulary else "", progress=progress,
    )

    t0 = time.perf_counter()
    method.fit(maps, resources=resources)
    fit_s = time.perf_counter() - t0
    place_ids = method.place_ids_
    gt = make_ground_truth(opts, maps, query, place_ids)
    items = method.encode(query, resources=resources)
    S, ms_each = score_queries(method, items, prog)
    if opts.sequence and opts.sequence > 1:
        S, seq_ms = apply_sequence(S, opts.sequence)
        ms_each = ms_each + seq_ms
    S = np.asarray(S, dtype=np.float32)
    scores = compute_metrics(S, gt)

    metrics: dict[str, Any] = {
        "method": method.name,
        **scores.as_dict(),
        "ms_per_query": float(np.median(ms_each)) if len(ms_each) else 0.0,
        "ms_features": resources.ms_features_median(),
        "peak_rss_mb": peak_rss_mb(),
        "n_places": int(S.shape[0]),
        "n_queries": int(S.shape[1]),
        "params": {**method.get_params(), "sequence": opts.sequence},
        "run": {
            "map": [str(m) for m in opts.maps],
            "query": str(opts.query),
            "ground_truth": gt.description,
            "features": {
                "method": opts.features, "max_features": opts.max_features, "max_side": max_side,
                "max_side_option": str(opts.max_side), "preprocess": resources.extractor.config.preprocess,
            },
            "vocabulary": vocab_info,
            "fit_seconds": fit_s,
            "ms_per_query_p95": float(np.percentile(ms_each, 95)) if len(ms_each) else 0.0,
            "date": datetime.now(UTC).isoformat(timespec="seconds"),
            "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
        },
    }
    write_outputs(opts.out, S, place_ids, query.places, metrics, scores)
    return metrics


def write_outputs(
    out: Path, S: np.ndarray, place_ids: np.ndarray, query_places: np.ndarray,
    metrics: dict[str, Any], scores: Scores,
) -> None:
    """Write S, ids, metrics, PR curve and report under ``out`` (each file atomically)."""
    out.mkdir(parents=True, exist_ok=True)
    _save_npy(out / "S.npy", S.astype(np.float32))
    _save_npy(out / "places.npy", np.asarray(place_ids, dtype=np.int64))
    _save_npy(out / "queries.npy", np.asarray(query_places, dtype=np.int64))
    atomic_write_bytes(out / "metrics.json", (json.dumps(metrics, indent=2, default=str) + "\n").encode())
    pr = "precision,recall\n" + "".join(
        f"{p:.6f},{r:.6f}\n" for p, r in zip(scores.precision, scores.recall, strict=True)
    )
    atomic_write_bytes(out / "pr.csv", pr.encode())
    label = f"{metrics['method']} (AUC {metrics['auc']:.2f})"
    plot_pr_curves([(label, scores.precision, scores.recall)], out / "pr.png",
                   title=_run_title(metrics))
    atomic_write_bytes(out / "report.md", render_run_report(metrics).encode())


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
    tags = []
    try:
        cls = get_method(m["method"])
        defaults = {k: v.default for k, v in inspect.signature(cls.__init__).parameters.items()
                    if v.kind is v.KEYWORD_ONLY}
        tags = [f"{k}={v}" for k, v in params.items() if k in defaults and defaults[k] != v]
    except TopolocError:
        pass  # a method this installation does not know: show the bare name
    feats = m.get("run", {}).get("features", {})
    if feats.get("method", "sift") != "sift":
        tags.append(feats["method"])
    # Runs written before preprocessing existed had none.
    if feats.get("preprocess", "none") != _DEFAULT_PREPROCESS:
        tags.append(f"preprocess={feats['preprocess']}")
    if seq and seq > 1:
        tags.append(f"seq {seq}")
    return m["method"] + (f" ({', '.join(tags)})" if tags else "")


_DEFAULT_PREPROCESS = EvaluateOptions.preprocess


def _run_title(m: dict[str, Any]) -> str:
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


def _features_line(f: dict[str, Any]) -> str:
    side = int(f.get("max_side", 0))
    resize = f"images downscaled to a longer side of {side} px" if side else "images at full size"
    if "max_side_option" in f:
        resize += f" (--max-side {f['max_side_option']})"
    return (f"{f['method']}, at most {f['max_features']} per image, {resize}, "
            f"photometric preprocessing {f.get('preprocess', 'none')}")


def render_run_report(m: dict[str, Any]) -> str:
    """``report.md`` of one run."""
    run = m["run"]
    voc = run["vocabulary"]
    lines = [
        f"# {_run_title(m)}\n\n",
        TABLE_HEADER,
        table_row(m),
        "\n## What was run\n\n",
        f"- method `{m['method']}`, parameters `{json.dumps(m['params'], default=str)}`\n",
        f"- map: {', '.join(f'`{x}`' for x in run['map'])}\n",
        f"- query: `{run['query']}` ({m['n_queries']} queries, {m['n_places']} map places)\n",
        f"- ground truth: {run['ground_truth']}\n",
        f"- local features: {_features_line(run['features'])}\n",
    ]
    if voc.get("used"):
        prov = {k: v for k, v in voc.items() if k not in {"used"}}
        lines.append(f"- vocabulary: `{json.dumps(prov, default=str)}`\n")
    else:
        lines.append("- vocabulary: none (this method does not use one)\n")
    lines += [
        f"- fit time {run['fit_seconds']:.2f} s; ms/query median {m['ms_per_query']:.2f}, "
        f"95th percentile {run['ms_per_query_p95']:.2f} (feature extraction excluded)\n",
        f"- machine: {run['machine']}; date {run['date']}\n",
    ]
    return "".join(lines)


def load_run(run_dir: Path) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
    """Metrics and PR curve (precision, recall) of an ``evaluate`` output folder."""
    mpath = run_dir / "metrics.json"
    if not mpath.is_file():
        raise TopolocError(f"not an evaluate output folder (no metrics.json): {run_dir}")
    try:
        m = json.loads(mpath.read_text())
        pr = np.loadtxt(run_dir / "pr.csv", delimiter=",", skiprows=1, ndmin=2)
    except (ValueError, OSError) as exc:
        raise TopolocError(f"corrupt evaluate output ({exc.__class__.__name__}): {run_dir}") from None
    return m, pr[:, 0], pr[:, 1]


def build_report(run_dirs: list[Path], out: Path, title: str = "Results") -> Path:
    """Side-by-side table (``README.md``-style markdown) and one PNG of all PR curves."""
    runs = [load_run(Path(d)) for d in run_dirs]
    out.mkdir(parents=True, exist_ok=True)
    md = [f"# {title}\n\n", TABLE_HEADER, *(table_row(m) for m, _, _ in runs)]
    md.append("\nRuns: " + ", ".join(f"`{d}`" for d in run_dirs) + "\n\n![PR curves](pr_curves.png)\n")
    curves = [(f"{_run_title(m)} (AUC {m['auc']:.2f})", p, r) for m, p, r in runs]
    plot_pr_curves(curves, out / "pr_curves.png", title=title)
    path = out / "report.md"
    atomic_write_bytes(path, "".join(md).encode())
    return path

