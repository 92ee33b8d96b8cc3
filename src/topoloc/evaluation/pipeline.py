"""``topoloc evaluate``: run one method on map and query traverses and score it.

This is the single door of ``docs/protocol.md``.  Outputs under ``out``:

``S.npy``
    float32 (n_places, n_queries), higher = more similar; with ``top_k`` instead
    ``S_topk.npz`` (``rows``, ``scores`` of shape (n_queries, K), best first, and
    ``shape``; see :mod:`topoloc.evaluation.topk`) and no dense ground truth.
``places.npy`` / ``queries.npy``
    place id of each row / true place id of each column.
``metrics.json``
    the metrics of the protocol plus a ``run`` block describing what ran.
``pr.png``, ``pr.csv``
    the precision-recall curve (``pr.csv``: columns precision,recall).
``report.md``
    the table and what was run, including the vocabulary's provenance.

With ``pairs_out`` (and ``top_k``) the K best places of each query are also written
there as retrieval pairs in hloc's format (:mod:`topoloc.evaluation.pairs`).
"""

from __future__ import annotations

import io
import json
import logging
import os
import platform
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.cluster import Executor
from topoloc.datasets.groundtruth import GroundTruth
from topoloc.datasets.traverse import Traverse, check_distinct_tours
from topoloc.errors import ParameterError, TopolocError
from topoloc.evaluation.metrics import Scores, compute_metrics
from topoloc.evaluation.pairs import first_images, image_names, place_names, retrieval_pairs, write_pairs
from topoloc.evaluation.plots import plot_pr_curves
from topoloc.evaluation.report import render_run_report, run_title
from topoloc.evaluation.timing import apply_sequence, peak_rss_mb, score_queries
from topoloc.evaluation.topk import TopK, compute_metrics_top_k, score_top_k, top_k_of
from topoloc.io.container import atomic_write_bytes
from topoloc.io.dirs import staged_dir
from topoloc.io.paths import is_discard
from topoloc.methods.base import PlaceRecognizer, map_place_ids
from topoloc.progress import ProgressFactory, no_progress
from topoloc.progress import stage as progress_stage
from topoloc.resources import CachedResources
from topoloc.spec import EvaluateSpec, FeatureSpec, parse_recall_at, spec_from_flat, spec_to_dict
from topoloc.spec.parts import choose_verify
from topoloc.spec.setup import build_method, build_verifier, make_resources, unverifiable
from topoloc.verification import VerifiedBlock, Verifier, confirmed, demote_unconfirmed

log = logging.getLogger(__name__)


def _save_npy(path: Path, arr: np.ndarray) -> None:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    atomic_write_bytes(path, buf.getvalue())


def evaluate(
    spec: EvaluateSpec | None = None, *, progress: ProgressFactory | None = None,
    executor: Executor | None = None, **options: Any
) -> dict[str, Any]:
    """Run ``spec.method`` and write every output file of ``docs/protocol.md`` under ``spec.out``.

    Parameters
    ----------
    spec : EvaluateSpec, optional
        What to run; or give flat options as keyword arguments, as the command
        line names them (:data:`topoloc.spec.FLAT_NAMES`), e.g.
        ``evaluate(method="bow", maps=[...], query=..., out=..., vocab_train=[...])``.
    progress : ProgressFactory, optional
        Progress bars (the CLI passes rich's).
    executor : Executor, optional
        Where feature extraction and quantisation of image files run
        (:func:`topoloc.cluster.connect`: a Dask cluster, or by default this
        process's threads); the caller closes it.  Default: ``spec.execution``'s,
        opened and closed here.  S is the same either way.

    Returns
    -------
    dict
        The content of ``metrics.json``; ``run.spec`` is the specification,
        from which ``topoloc evaluate --config metrics.json`` runs it again.
    """
    if spec is None:
        try:
            spec = spec_from_flat(EvaluateSpec, options)
        except TypeError as exc:
            raise TopolocError(f"evaluate: {exc}") from None
    elif options:
        raise TopolocError("evaluate: pass either an EvaluateSpec or keyword options, not both")
    if executor is None:
        with spec.execution.connect() as own:
            return _evaluate(spec, progress, own)
    return _evaluate(spec, progress, executor)


def _evaluate(spec: EvaluateSpec, progress: ProgressFactory | None, executor: Executor) -> dict[str, Any]:
    assert spec.query is not None and spec.out is not None  # EvaluateSpec refuses a spec without them
    prog: ProgressFactory = progress or no_progress
    out = spec.out
    # Validate every cheap option before any expensive work starts; the run folder is replaced
    # whole, so it must hold nothing of the user's (nor an input, nor the working folder).
    spec.check_outputs()
    recall_at = parse_recall_at(spec.recall_at)
    seq = spec.sequence
    # Folders, or bags and videos (their keyframes in memory: topoloc.datasets.sources).
    loaded = spec.inputs.load([*spec.maps, spec.query])
    maps, query = loaded[:-1], loaded[-1]
    check_distinct_tours(maps)  # as map build and map add refuse a tour given twice (issue #49)
    if seq.length >= len(query):
        raise ParameterError("sequence.length", f"{seq.length} needs more than {seq.length} queries; "
                                                f"{spec.query} has {len(query)}")
    query_fingerprint = query.fingerprint()
    _warn_if_trained_on_query(spec, query_fingerprint, maps)
    map_xy = None
    place_images: list[str] | None = None
    calibration: dict[str, Any] | None = None
    saved: Any = None
    early_gt: GroundTruth | None = None
    early_ids = np.zeros(0, np.int64)
    if spec.map_file is not None:
        saved, resources, vocab_info = _saved_map(
            spec, progress, executor, query_fingerprint=query_fingerprint)
        method, map_xy, place_images, calibration = (saved.recognizer, saved.place_xy, saved.place_image_names(),
                                                     saved.calibration)
        max_side, fit_s = resources.extractor.config.max_side, 0.0
        map_labels = [str(spec.map_file)]
    else:
        method = build_method(spec.method, spec.params)
        # The ground truth (a file of the wrong shape...) is checked before the fit's work (issue #41); the
        # rows of S are the maps' sorted place ids whatever the method.
        early_ids = map_place_ids(maps)
        early_gt = spec.ground_truth.make(early_ids, query, maps=maps, map_xy=map_xy)
        if not method.uses_vocabulary and spec.vocabulary.given:
            log.warning("method %s uses no visual vocabulary: the vocabulary given is ignored", method.name)
        config = spec.features.config()
        max_side = config.max_side
        resources, vocab_info = make_resources(
            config, spec.vocabulary, cache_dir=spec.execution.cache_dir,
            needs_vocabulary=f"method {method.name!r}" if method.uses_vocabulary else "", progress=progress,
            executor=executor, tours=maps,
        )
        t0 = time.perf_counter()
        with progress_stage(prog, f"fit {method.name} on {sum(len(m) for m in maps)} map images"):
            method.fit(maps, resources=resources)
        # The vocabulary is loaded or trained lazily inside fit: its time is reported apart.
        fit_s = time.perf_counter() - t0 - float(vocab_info.get("seconds_this_run", 0.0))
        map_labels = [str(m) for m in spec.maps]
    place_ids = method.place_ids_
    gt = (early_gt if early_gt is not None and np.array_equal(place_ids, early_ids)
          else spec.ground_truth.make(place_ids, query, maps=maps, map_xy=map_xy))
    check_overlap(gt, query, place_ids)
    verifier = _verifier(spec, method, maps, saved, resources, prog)
    items = method.encode(query, resources=resources)
    top: TopK | None = None
    S: np.ndarray | None = None
    ver: VerifiedBlock | None = None
    if spec.top_k and not seq.length:
        # Each block of whole columns is verified before its K best rows are kept: the answers of the dense S.
        blocks: list[VerifiedBlock] = []
        qfeats = resources.features(query, timed=False) if verifier is not None else []
        previous: list[int] = []

        def transform(Sb: np.ndarray, first: int) -> np.ndarray:
            if verifier is not None:
                blocks.append(verifier.verify(Sb, qfeats[first:first + Sb.shape[1]]))
                Sb = blocks[-1].S
            if spec.verification.confirm:
                ok = confirmed(Sb, previous[-1] if previous else None) if first else confirmed(Sb)
                previous.append(int(np.argmax(Sb[:, -1])))
                Sb = demote_unconfirmed(Sb, ok)
            return Sb

        top, ms_each = score_top_k(method, items, spec.top_k, prog,
                                   transform=transform if verifier is not None or spec.verification.confirm else None)
        del items
        if blocks:
            ver = VerifiedBlock.concat(blocks)
            ms_each = ms_each + ver.ms
    else:
        S, ms_each = score_queries(method, items, prog)
        if seq.length:
            S, seq_ms = apply_sequence(S, seq.length, seq.mode)
            ms_each = ms_each + seq_ms
        S = np.asarray(S, dtype=np.float32)
        if verifier is not None:
            with progress_stage(prog, f"verify {S.shape[1]} queries"):
                ver = verifier.verify(S, resources.features(query, timed=False))
            S = ver.S
            ms_each = ms_each + ver.ms
        if spec.verification.confirm:
            S = demote_unconfirmed(S, confirmed(S))
        if spec.top_k:  # sequence matching needs neighbouring columns: the dense S is formed first
            top = TopK(*top_k_of(S, spec.top_k), n_places=S.shape[0])
            S = None
    if top is not None:
        scores = compute_metrics_top_k(top, gt, recall_at)
        shape = (top.n_places, top.n_queries)
    else:
        assert S is not None
        scores = compute_metrics(S, gt, recall_at)
        shape = S.shape

    metrics: dict[str, Any] = {
        "method": method.name,
        **scores.as_dict(),
        "ms_per_query": float(np.median(ms_each)) if len(ms_each) else 0.0,
        "ms_features": resources.ms_features_median(),
        "peak_rss_mb": peak_rss_mb(),
        "n_places": int(shape[0]),
        "n_queries": int(shape[1]),
        **({"top_k": top.k} if top is not None else {}),
        "params": {**method.get_params(), "sequence": seq.length,
                   **({"sequence_mode": seq.mode} if seq.length else {}), "verify": ver is not None,
                   **({"confirm": True} if spec.verification.confirm else {})},
        **({"verification": verification_record(ver, verifier)} if ver is not None and verifier is not None else {}),
        "run": {
            "map": map_labels,
            "query": str(spec.query),
            "ground_truth": gt.description,
            "features": {
                "method": resources.extractor.config.method, "max_features": resources.extractor.config.max_features,
                "max_side": max_side, "max_side_option": "map file" if spec.map_file else str(spec.features.max_side),
                "preprocess": resources.extractor.config.preprocess,
            },
            "vocabulary": vocab_info,
            # The saved map's acceptance threshold, where it has one (the HTML slider opens there).
            **({"calibration": calibration} if calibration is not None else {}),
            # The saved map's tours, each as its folder and fingerprint: the HTML page shows their images where
            # the folder still holds exactly what the map was built from (issue #49: "no image" for every place).
            **({"map_tours": [{k: t.get(k) for k in ("name", "root", "fingerprint")} for t in saved.tours
                              if not t.get("source") and not str(t.get("root", "")).startswith("<")]}
               if saved is not None else {}),
            # "local", or the Dask scheduler the features were extracted and quantised on.
            "executor": resources.executor.name if isinstance(resources, CachedResources) else "local",
            "fit_seconds": fit_s,
            "vocabulary_seconds": float(vocab_info.get("seconds_this_run", 0.0)),
            "ms_per_query_p95": float(np.percentile(ms_each, 95)) if len(ms_each) else 0.0,
            "date": datetime.now(UTC).isoformat(timespec="seconds"),
            "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
            "spec": spec_to_dict(spec),
        },
    }
    # All files of the run appear together, replacing an earlier run's whole (never a mixture).
    with staged_dir(out) as stage:
        write_outputs(stage, S, place_ids, query.places, metrics, scores, None if top is not None else gt, top=top)
        if ver is not None and verifier is not None:
            atomic_write_bytes(stage / "verification.npz", _npz(**verification_arrays(ver, verifier)))
        if spec.html is not None and is_discard(out):  # the run is discarded: its page is drawn before
            from topoloc.evaluation.html import build_html_report

            build_html_report([stage], Path(spec.html), progress=prog)
    if spec.pairs_out is not None:
        assert top is not None  # EvaluateSpec refuses pairs_out without top_k
        if place_images is None:
            place_images = place_names(place_ids, (first_images(m) for m in maps))
        write_pairs(spec.pairs_out, retrieval_pairs(image_names(query), top.rows, place_images))
    if spec.html is not None and not is_discard(out):
        from topoloc.evaluation.html import build_html_report

        build_html_report([out], Path(spec.html), progress=prog)
    return metrics


def _npz(**arrays: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, allow_pickle=False, **arrays)
    return buf.getvalue()


def verification_arrays(ver: VerifiedBlock, verifier: Verifier) -> dict[str, np.ndarray]:
    """``verification.npz``: per query its answer row, whether it is verified, its support (``inliers``), strength and
    confidence, the candidates' rows and support, the stage's ms, and the supporting matches of each answer
    (``match_xy`` rows ``match_offsets[j]`` .. ``match_offsets[j + 1]``: query x, y, map x, y in pixels) with the
    map image they are in (``match_image``) and both images' (height, width) (``match_shapes``)."""
    pairs = ver.matches
    offsets = np.zeros(len(pairs) + 1, np.int64)
    offsets[1:] = np.cumsum([len(p) for p in pairs])
    names = [verifier.match_image_name(int(ver.answer[j]), ver.match_images[j]) for j in range(len(pairs))]
    return {"answer": ver.answer, "verified": ver.verified, "inliers": ver.support, "strength": ver.strength,
            "confidence": ver.confidence, "candidates": ver.candidates, "candidate_support": ver.candidate_support,
            "ms": ver.ms, "match_xy": np.concatenate(pairs) if pairs else np.zeros((0, 4), np.float32),
            "match_offsets": offsets, "match_image": np.array(names, dtype=str), "match_shapes": ver.match_shapes}


def verification_record(ver: VerifiedBlock, verifier: Verifier) -> dict[str, Any]:
    """What ``metrics.json`` says of the verification stage: its settings, how many answers passed, its time."""
    r = verifier.rule
    return {"candidates": verifier.candidates, "max_iters": r.max_iters, "min_support": r.min_support,
            "ratio": r.ratio, "climb": r.climb, "confusion": verifier.confusable is not None,
            "look_alikes": verifier.look_alikes is not None,
            "confidence_model": verifier.confidence_model.to_dict(),
            "verified_fraction": float(ver.verified.mean()) if len(ver.verified) else 0.0,
            "ms_per_query": float(np.median(ver.ms)) if len(ver.ms) else 0.0,
            "ms_per_query_p95": float(np.percentile(ver.ms, 95)) if len(ver.ms) else 0.0}


def _verifier(spec: EvaluateSpec, method: PlaceRecognizer, maps: Sequence[Traverse], saved: Any,
              resources: CachedResources, progress: ProgressFactory) -> Verifier | None:
    """The run's verification stage, chosen as every run chooses (:func:`topoloc.spec.parts.choose_verify`).

    A saved map is verified as ``localize`` verifies it (its record, its tours read again, its confusion); tours
    given as folders are verified with the confusion learned from them now (:mod:`topoloc.maps.confusion`).
    A run that cannot verify and was not asked to goes on unverified with one warning line.
    """
    from topoloc.maps import verify_policy

    if saved is not None:
        return saved.verifier_for(spec.verification.enabled, resources=resources, sequence=spec.sequence.length,
                                  spec=spec.verification)
    choice = choose_verify(spec.verification.enabled, checks_geometry=method.tags.verifies_geometry)
    if not verify_policy.settle(choice, unverifiable(maps), where="the map"):
        if choice.enabled is None and method.tags.verifies_geometry:
            log.info("%s checks the geometry of its candidates itself: answers are not verified again (--verify "
                     "does)", method.name)
        return None
    from topoloc.maps.confusion import learn_confusion

    verifier = build_verifier(spec.verification, method.place_ids_, maps, resources, sequence=spec.sequence.length)
    with progress_stage(progress, "learn the map's look-alike places"):
        learn_confusion(method, maps, resources, verifier, progress=progress).install(verifier)
    return verifier


def check_overlap(gt: GroundTruth, query: Traverse, place_ids: np.ndarray) -> None:
    """Refuse ground truth that gives no query a correct map place; warn (one line) when some have none.

    Such queries count in no recall (they have nothing to find), so a run
    where most queries show places the map lacks would report recall over a
    handful of queries without a word.
    """
    has = np.diff(gt.hard_sparse.indptr) > 0 if gt.is_sparse else np.asarray(gt.hard.any(axis=0))
    if not has.any():
        raise TopolocError(
            f"no query of {query.root} has a correct place in the map (query places "
            f"{int(query.places.min())}..{int(query.places.max())}, map places {int(place_ids.min())}.."
            f"{int(place_ids.max())}): check places.csv and the tolerance")
    if not has.all():
        log.warning("%d of %d queries have no correct place in the map; recall is computed over the other %d",
                    int((~has).sum()), int(has.size), int(has.sum()))


def _warn_if_trained_on_query(spec: EvaluateSpec, query_fingerprint: str, maps: Sequence[Traverse]) -> None:
    """One warning line when the query is a map tour, or a vocabulary is trained on folders holding it.

    Neither is wrong to run (a sanity check, an upper bound), but the scores
    then measure the method on its own training images.
    """
    for path, m in zip(spec.maps, maps, strict=True):
        if m.fingerprint() == query_fingerprint:
            log.warning("query %s is the map tour %s (same images and places): the scores are measured on the "
                        "map's own images", spec.query, path)
            break
    assert spec.query is not None
    query = spec.query.resolve()
    for folder in spec.vocabulary.train:
        if query.is_relative_to(folder.resolve()):
            log.warning("vocabulary training folder %s holds the query %s: the vocabulary is trained on the "
                        "query images, which flatters the scores", folder, spec.query)
            break


def _saved_map(
    spec: EvaluateSpec, progress: ProgressFactory | None, executor: Executor | None = None, *,
    query_fingerprint: str = "",
) -> tuple[Any, CachedResources, dict[str, Any]]:
    """The map of a map file, its resources and its vocabulary record.

    A saved map fixes the method, its parameters, the features and the
    vocabulary: options that would change them are refused, not ignored.
    """
    from topoloc.maps import Map

    assert spec.map_file is not None and spec.query is not None
    saved = Map.load(spec.map_file)
    rec = saved.recognizer
    if any(t.get("fingerprint") == query_fingerprint for t in saved.tours):
        log.warning("query %s is a tour of the map %s (same images and places): the scores are measured on the "
                    "map's own images", spec.query, spec.map_file)
    if spec.method and spec.method != rec.name:
        raise ParameterError("method", f"{spec.method} differs from the map file's, a {rec.name} map: {spec.map_file}")
    if rec.uses_local_features:
        # Feature options left at their defaults take the map's; one given otherwise must be the map's: the
        # queries are described with the map's features, and ``--features xfeat`` against a SIFT map was ignored.
        default = FeatureSpec()
        keys = ("method", "max_features", "preprocess")
        given = {k: getattr(spec.features, k) for k in keys if getattr(spec.features, k) != getattr(default, k)
                 or (k == "method" and spec.features.method_named)}
        if given:
            saved.check_compatible(features=FeatureSpec(**{**{k: getattr(saved.features, k) for k in keys}, **given}))
    res = saved.resources(cache_dir=spec.execution.cache_dir, progress=progress, executor=executor)
    voc: dict[str, Any] = {"used": saved.vocabulary is not None}
    if saved.vocabulary is not None:
        # n_words as a run that trained or loaded the vocabulary records it: one vocabulary, one name (issue #49).
        voc.update({"file": f"embedded in {spec.map_file}", "n_words": saved.vocabulary.n_words,
                    **saved.vocabulary.provenance_})
    return saved, res, voc


def write_outputs(
    out: Path, S: np.ndarray | None, place_ids: np.ndarray, query_places: np.ndarray,
    metrics: dict[str, Any], scores: Scores, gt: GroundTruth | None = None, *, top: TopK | None = None,
) -> None:
    """Write S, ids, metrics, PR curve and report under ``out`` (each file atomically).

    With ``gt``, also ``gt_hard.npy`` / ``gt_soft.npy`` (boolean, the shape of S) for the HTML page.
    With ``top``, ``S_topk.npz`` is written instead of ``S.npy``.
    """
    out.mkdir(parents=True, exist_ok=True)
    if gt is not None:
        _save_npy(out / "gt_hard.npy", np.asarray(gt.hard, dtype=bool))
        _save_npy(out / "gt_soft.npy", np.asarray(gt.soft, dtype=bool))
    if top is not None:
        top.save(out / "S_topk.npz")
    if S is not None:
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
                   title=run_title(metrics))
    atomic_write_bytes(out / "report.md", render_run_report(metrics).encode("utf-8", "surrogateescape"))


