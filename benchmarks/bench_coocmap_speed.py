"""Regenerate docs/results/coocmap_speed.md: Cooc-Map localisation time on real features at the paper's size.

    .venv/bin/python -m benchmarks.bench_coocmap_speed              # every part, about 15 min on 2 idle cores
    .venv/bin/python -m benchmarks.bench_coocmap_speed --tail-only  # part 5 only (the rest of the page kept)
    .venv/bin/python -m benchmarks.bench_coocmap_speed --tail-only --real DIR [DIR ...] \
        --vocab-train DIR --out OUTDIR                           # part 5 on other images, written elsewhere

Five parts, all in this one process (timings are ratios within it; 2 shared cores):

1. `topoloc bench coocmap --real` on gardens_point + rtabmap_loop (2,200 locations x 5 tours, 500
   queries; vocabulary trained on webcam_daynight) -> coocmap_speed_real.json; the synthetic
   benchmark (`topoloc bench coocmap`) -> coocmap_speed.json.
2. gardens_point with two map tours (100 places), the `coocmap` method fitted as `topoloc evaluate`
   fits it (preprocessing auto = the default, none and CLAHE): ms per query of the previous default
   matcher (`schedule="lazy"`) and of the new one (`"compiled"`), alternated query by query.
3. Agreement with the exact reference (every J built, every location eliminated to completion,
   `match_sequential`) on 500 real queries: best location, exact scores, top-10 ranks.
4. Where the time goes: per-phase split on gardens_point and the counters of the real benchmark.
5. The tail (issue #38): the real benchmark's map and queries (or those of ``--real``), every query
   matched by the matcher before the issue (``compiled.py`` at git revision ``--before``, imported
   under another name) and by today's, alternated query by query, with the same scores checked
   bit for bit; the distribution of per-query time (a histogram, coocmap_speed_tail.png), what the
   slowest 5 % have in common (:func:`topoloc.bench.coocmap_speed.query_profile`), today's matcher
   paced at 10 Hz quiet and beside 3 busy processes (``benchmarks.bench_load``), and the
   gardens_point two-tour pairs before and after.  -> coocmap_speed_tail.json.

The Cooc-Map row of performance.md is rewritten from the JSON files (between its markers).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import re
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from numba import njit

from benchmarks.bench_load import busy, paced
from benchmarks.common import DATA, GP, REPO, RESULTS, VOCAB_FOR_GP, require_data
from topoloc.bench.coocmap_speed import bench_coocmap, bench_coocmap_real, query_profile, real_map
from topoloc.coocmap.compiled import (
    _PAIRWISE_MAX,
    _PARTNERS_MAX,
    _cell_tables,
    _column_bound,
    _match_location,
    _new_scratch,
    _partner_bound,
    _query_table,
    _translation_bound,
    _triple_capacity,
    _triple_rows,
    _triples,
    match_compiled,
)
from topoloc.coocmap.matching import consistency_graphs, match_lazy, match_sequential
from topoloc.datasets.traverse import load_traverse
from topoloc.features import FeatureConfig
from topoloc.methods.cooc_map import CoocMap
from topoloc.spec import FeatureSpec, VocabularySpec
from topoloc.spec.setup import make_resources

COMMAND = ".venv/bin/python -m benchmarks.bench_coocmap_speed"
#: Preprocessings timed on the two-tour gardens_point pairs (the single-tour pair: CLAHE only).
PREPROCESSINGS = ("auto", "none", "clahe")
REAL_DIRS = [GP, DATA / "rtabmap_loop"]
TWO_TOUR = [(("day_left", "night_right"), "day_right"), (("day_left", "day_right"), "night_right")]
ONE_TOUR = [(("day_left",), "night_right")]
#: The matcher before issue #38 (main at that time): part 5 times it beside today's.
BEFORE_REV = "f55e3dd"
#: Camera rate of the paced runs of part 5 (``benchmarks.bench_load``): 10 Hz.
PACED_HZ = 10.0
#: Busy processes beside the loaded paced run of part 5.
BUSY = 3


def fitted(maps: tuple[str, ...], query: str, preprocess: str, features: str = "sift") -> tuple[CoocMap, list[Any]]:
    """The `coocmap` method with its defaults, fitted and encoded as `topoloc evaluate` does.

    ``features="sift"``: SIFT with the vocabulary trained on webcam_daynight (parts 2-5, as before
    learned features); ``"xfeat"``: XFeat and the vocabulary `evaluate` trains on the map's own tours
    when given none, i.e. `topoloc evaluate`'s defaults where the ``learned`` extra is installed.
    """
    mp = [load_traverse(GP / m) for m in maps]
    qt = load_traverse(GP / query)
    config = FeatureSpec(method=features, preprocess=preprocess).config()
    vocab = VocabularySpec(train=tuple(VOCAB_FOR_GP)) if features == "sift" else VocabularySpec()
    res, _ = make_resources(config, vocab, needs_vocabulary="coocmap", tours=mp)
    method = CoocMap().fit(mp, resources=res)
    return method, method.encode(qt, resources=res)


def gardens_timing(method: CoocMap, items: list[Any]) -> dict[str, Any]:
    """ms per query of the previous default (lazy) and the new one (compiled), alternated; same answers?"""
    m = method.model_
    kw: dict[str, Any] = {"top_k": method.top_k, "interpolate": method.interpolate, "seed": method.seed,
                          "spatial_tolerance": method.spatial_tolerance}
    match_compiled(m, *items[0], **kw)
    old, new, same = [], [], []
    for w, xy in items:
        t = time.perf_counter()
        a = match_lazy(m, w, xy, **kw)
        old.append(1e3 * (time.perf_counter() - t))
        t = time.perf_counter()
        b, _ = match_compiled(m, w, xy, **kw)
        new.append(1e3 * (time.perf_counter() - t))
        k = method.top_k
        same.append(a.best == b.best and np.array_equal(np.sort(a.scores)[::-1][:k], np.sort(b.scores)[::-1][:k]))
    return {"ms_old_median": float(np.median(old)), "ms_old_p95": float(np.percentile(old, 95)),
            "ms_new_median": float(np.median(new)), "ms_new_p95": float(np.percentile(new, 95)),
            "speedup_median": float(np.median(old) / np.median(new)), "same_top_k": float(np.mean(same)),
            "n_queries": len(items), "features_median": float(np.median([len(w) for w, _ in items]))}


def agreement(method: CoocMap, items: list[Any]) -> dict[str, int]:
    """Compiled matcher vs the exact reference (all J, every location to completion)."""
    m = method.model_
    kw: dict[str, Any] = {"interpolate": method.interpolate, "seed": method.seed,
                          "spatial_tolerance": method.spatial_tolerance}
    out = {"queries": 0, "same_best": 0, "same_exact_scores": 0, "same_top10": 0, "same_group": 0}
    for w, xy in items:
        g = consistency_graphs(m, w, xy, **kw)
        ref = match_sequential(g)
        res, group = match_compiled(m, w, xy, top_k=method.top_k, **kw)
        out["queries"] += 1
        out["same_best"] += int(res.best == ref.best)
        out["same_exact_scores"] += int(np.array_equal(res.scores[res.exact], ref.scores[res.exact]))
        out["same_top10"] += int(np.array_equal(np.sort(res.scores)[::-1][:10], np.sort(ref.scores)[::-1][:10]))
        out["same_group"] += int(np.array_equal(group, ref.group(g, ref.best)))
    return out


@njit(cache=True)
def _phases(L, thr, tb_prune, bounds_only, loc_ptr, word, xy, groups, qptr, qf, qx, qy, tol, gx, gy, cap, shift, ctab):
    """Every location of the map in turn: its bounds from the translations only, or matched against ``thr``."""
    stamp, cand, cof, U, t_f, t_a, t_b, t_x, t_y, P, hist, keep = _new_scratch(len(qx), cap, gx, gy)
    total = 0.0
    for loc in range(L):
        if bounds_only:
            n, nt = _triples(loc_ptr[loc], loc_ptr[loc + 1], word, xy, qptr, qf, qx, gx, loc, stamp, cand, cof,
                             t_f, t_a, t_x)
            if n:
                _triple_rows(nt, t_f, t_a, t_x, xy, qy, gy, t_y, t_b)
                total += _column_bound(n, nt, cand, t_f, t_x, U, P, hist, gx, tol + 1)
                total += _translation_bound(n, nt, cand, t_f, t_x, t_y, U, P, hist, gx, gy, tol + 1, _PAIRWISE_MAX)
                total += _partner_bound(n, nt, cand, cof, t_f, t_a, t_x, t_y, groups, U, hist, gx, tol + 1)
        else:
            total += _match_location(loc, thr, loc_ptr, word, xy, groups, qptr, qf, qx, qy, tol, gx, gy, 0, loc,
                                     stamp, cand, cof, U, t_f, t_a, t_b, t_x, t_y, P, hist, keep, tb_prune,
                                     _PAIRWISE_MAX, _PARTNERS_MAX, shift, ctab)[0]
            keep[:] = False
    return total


def phase_split(method: CoocMap, items: list[Any]) -> dict[str, float]:
    """ms per query, over all locations: triples + the bounds before J, J, elimination (each location alone)."""
    m = method.model_
    groups = m.group_masks(method.interpolate)
    acc = np.zeros(3)
    for qi, (w, xy) in enumerate(items):
        qptr, qf, qx, qy = _query_table(m, np.asarray(w, np.int64), xy)
        args = (m.loc_ptr, m.word, m.xy, groups, qptr, qf, qx, qy, int(method.spatial_tolerance), int(m.grid_x),
                int(m.grid_y), _triple_capacity(m.loc_ptr, qptr), *_cell_tables(m))
        t0 = time.process_time()
        _phases(m.n_locations, 0.0, True, True, *args)
        t1 = time.process_time()
        _phases(m.n_locations, 1e9, False, False, *args)  # up to the bound after J (never reached: 1e9)
        t2 = time.process_time()
        _phases(m.n_locations, -1.0, False, False, *args)  # to completion
        t3 = time.process_time()
        if qi:  # the first query compiles
            acc += [t1 - t0, t2 - t1, t3 - t2]
    acc = 1e3 * acc / max(len(items) - 1, 1)
    return {"triples_and_translation_bound_ms": acc[0], "J_ms": acc[1] - acc[0], "elimination_ms": acc[2] - acc[1]}


def counters(method: CoocMap, items: list[Any]) -> dict[str, float]:
    m = method.model_
    rows = []
    for w, xy in items:
        r, _ = match_compiled(m, w, xy, top_k=method.top_k, interpolate=method.interpolate, seed=method.seed,
                              spatial_tolerance=method.spatial_tolerance)
        rows.append((r.locations_built, r.translation_pruned, r.pair_tests, r.steps))  # type: ignore[attr-defined]
    a = np.median(np.array(rows, float), axis=0)
    return {"locations_built": a[0], "translation_pruned": a[1], "pair_tests": a[2], "elimination_steps": a[3]}


def patch_performance(real: dict[str, Any], synth: dict[str, Any]) -> None:
    """Rewrite the Cooc-Map rows of performance.md's "Methods at scale" table from the JSON files."""
    perf = RESULTS / "performance.md"
    if not perf.is_file():
        return
    rows = [
        f"| Cooc-Map, real features: {real['locations']} locations x {real['tours']} tours, median "
        f"{real['n_features_median']:.0f} SIFT features per image ([coocmap_speed.md](coocmap_speed.md), "
        f"`topoloc bench coocmap --real`) | median {real['ms_per_query_median']:.1f}, p95 "
        f"{real['ms_per_query_p95']:.1f} ms per localisation; map {real['map_bytes'] / 1e6:.1f} MB | paper: 82 ms |",
        f"| Cooc-Map, synthetic: {synth['locations']} locations x {synth['tours']} tours, {synth['features']} "
        f"features (`topoloc bench coocmap`) | median {synth['ms_per_query_median']:.1f}, p95 "
        f"{synth['ms_per_query_p95']:.1f} ms per localisation; map {synth['map_bytes'] / 1e6:.1f} MB | paper: 82 ms |",
    ]
    lines = [ln for ln in perf.read_text().splitlines() if not ln.startswith("| Cooc-Map, ")]
    at = next((i for i, ln in enumerate(lines) if ln.startswith("| FAB-MAP 2.0")), None)
    if at is None:
        return
    lines[at + 1:at + 1] = rows
    perf.write_text("\n".join(lines) + "\n")


def matcher_at(rev: str) -> ModuleType:
    """``topoloc.coocmap.compiled`` as it was at git revision ``rev``, imported as a module of its own.

    The source is kept under the cache (``<cache>/bench/``), named by the commit, so that numba's cache of
    its compiled kernels (beside it) serves the next run.  Exits (status 2) with a one-line message when
    the revision cannot be read.
    """
    from topoloc.features.cache import default_cache_dir

    rel = "src/topoloc/coocmap/compiled.py"
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short=12", f"{rev}^{{commit}}"],
                            capture_output=True, text=True)
    got = subprocess.run(["git", "-C", str(REPO), "show", f"{rev}:{rel}"], capture_output=True, text=True)
    if commit.returncode != 0 or got.returncode != 0:
        sys.exit(f"bench_coocmap_speed: cannot read {rel} at revision {rev} (--before): "
                 f"{(commit.stderr or got.stderr).strip()}")
    name = f"coocmap_compiled_{commit.stdout.strip()}"
    path = default_cache_dir() / "bench" / f"{name}.py"
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.is_file() or path.read_text() != got.stdout:
        path.write_text(got.stdout)
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def _same(a: Any, b: Any) -> bool:
    """Same S bit for bit: scores, which are exact, the best location's group."""
    return bool(np.array_equal(a[0].scores, b[0].scores) and np.array_equal(a[0].exact, b[0].exact)
                and np.array_equal(a[1], b[1]))


def before_after(before: ModuleType, model: Any, items: list[tuple[np.ndarray, np.ndarray]],
                 kw: dict[str, Any]) -> dict[str, Any]:
    """Every query by the matcher before and today's, alternated (which goes first alternates too).

    Returns per-query ms of each, the profiles (:func:`query_profile`) of each, and how many queries got
    the same S (bit for bit) and the same top-k.
    """
    before.match_compiled(model, *items[0], **kw)
    match_compiled(model, *items[0], **kw)
    ms: dict[str, list[float]] = {"before": [], "after": []}
    cpu: dict[str, list[float]] = {"before": [], "after": []}
    prof: dict[str, list[dict[str, float]]] = {"before": [], "after": []}
    same = same_top = 0
    best: list[int] = []
    for qi, (w, xy) in enumerate(items):
        got = {}
        for name in (("before", "after") if qi % 2 == 0 else ("after", "before")):
            fn = before.match_compiled if name == "before" else match_compiled
            t, c = time.perf_counter(), time.process_time()
            got[name] = fn(model, w, xy, **kw)
            ms[name].append(1e3 * (time.perf_counter() - t))
            cpu[name].append(1e3 * (time.process_time() - c))
            prof[name].append(query_profile(model, w, got[name][0]))
        best.append(int(got["after"][0].best))
        same += _same(got["before"], got["after"])
        k = int(kw["top_k"])
        same_top += bool(np.array_equal(np.sort(got["before"][0].scores)[::-1][:k],
                                        np.sort(got["after"][0].scores)[::-1][:k])
                         and got["before"][0].best == got["after"][0].best)
    return {"ms": ms, "cpu_ms": cpu, "profiles": prof, "same_S": same, "same_top_k": same_top, "n": len(items),
            "best": best}


def _summary(ms: list[float] | np.ndarray) -> dict[str, float]:
    a = np.asarray(ms, float)
    return {"median": float(np.median(a)), "p95": float(np.percentile(a, 95)), "p99": float(np.percentile(a, 99)),
            "max": float(a.max()), "mean": float(a.mean())}


def slowest_share(ms: list[float], profiles: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Medians of every profile field over the slowest 5 % of the queries and over the rest."""
    a = np.asarray(ms)
    slow = a >= np.percentile(a, 95)
    keys = list(profiles[0])
    col = {k: np.array([p[k] for p in profiles]) for k in keys}
    return {"slow": {k: float(np.median(col[k][slow])) for k in keys},
            "rest": {k: float(np.median(col[k][~slow])) for k in keys}, "n_slow": int(slow.sum())}


def tail_part(before: ModuleType, dirs: list[Path], vocab: list[Path], quick: bool, out_dir: Path,
              rev: str, locations: int = 2200, n_words: int = 10000) -> dict[str, Any]:
    """Part 5 (see the module docstring)."""
    t0 = time.time()
    n_q = 100 if quick else 500
    model, data, _ = real_map(dirs, locations=locations, tours=5, n_queries=500, vocab_train=vocab, n_words=n_words)
    items = list(zip(data["query_words"], data["query_xy"], strict=True))[:n_q]
    kw: dict[str, Any] = {"top_k": 1, "seed": 0, "spatial_tolerance": 1}
    out: dict[str, Any] = {"before_rev": rev, "dirs": [str(d) for d in dirs], "vocab_train": [str(v) for v in vocab],
                           "locations": model.n_locations, "tours": 5, "load_before": os.getloadavg()[0]}
    ba = before_after(before, model, items, kw)
    correct = np.asarray(data["query_loc"][:n_q])
    out["real"] = {
        "n": ba["n"], "same_S": ba["same_S"], "same_top_k": ba["same_top_k"],
        "before": _summary(ba["ms"]["before"]), "after": _summary(ba["ms"]["after"]),
        "cpu_before": _summary(ba["cpu_ms"]["before"]), "cpu_after": _summary(ba["cpu_ms"]["after"]),
        "recall_at_1": float(np.mean(np.asarray(ba["best"]) == correct)),
        "slowest_before": slowest_share(ba["ms"]["before"], ba["profiles"]["before"]),
        "slowest_after": slowest_share(ba["ms"]["after"], ba["profiles"]["after"]),
        "ms_before": ba["ms"]["before"], "ms_after": ba["ms"]["after"],
    }
    # Today's matcher paced at camera rate, quiet and beside busy processes (as benchmarks.bench_load).
    paced_items = items[:min(len(items), 100 if quick else 300)]

    def one(item: tuple[np.ndarray, np.ndarray]) -> None:
        match_compiled(model, *item, **kw)

    load: dict[str, Any] = {"hz": PACED_HZ, "busy": BUSY, "n": len(paced_items)}
    load["load_quiet"] = os.getloadavg()[0]
    load["quiet"] = _summary(paced(one, paced_items, PACED_HZ))
    with busy(BUSY):
        load["load_busy"] = os.getloadavg()[0]
        load["loaded"] = _summary(paced(one, paced_items, PACED_HZ))
    load["p95_ratio"] = load["loaded"]["p95"] / load["quiet"]["p95"]
    out["paced"] = load
    # gardens_point, the two-tour pairs as `topoloc evaluate` fits them (default preprocessing).
    gardens = []
    if dirs == REAL_DIRS:  # the development data's pairs; other --real folders have no such pairs
        from topoloc.features import learned

        for features in ("sift", "xfeat") if learned.is_installed() else ("sift",):
            for maps, q in TWO_TOUR:
                method, gitems = fitted(maps, q, FeatureConfig().preprocess, features)
                if quick:
                    gitems = gitems[::5]
                gkw = {"top_k": method.top_k, "interpolate": method.interpolate, "seed": method.seed,
                       "spatial_tolerance": method.spatial_tolerance}
                g = before_after(before, method.model_, gitems, gkw)
                gardens.append({"features": features, "maps": "+".join(maps), "query": q, "n": g["n"],
                                "same_S": g["same_S"], "same_top_k": g["same_top_k"],
                                "before": _summary(g["ms"]["before"]), "after": _summary(g["ms"]["after"]),
                                "cpu_before": _summary(g["cpu_ms"]["before"]),
                                "cpu_after": _summary(g["cpu_ms"]["after"]),
                                "built_before": float(np.median([p["J_built"] for p in g["profiles"]["before"]])),
                                "built_after": float(np.median([p["J_built"] for p in g["profiles"]["after"]])),
                                "features_median": float(np.median([len(w) for w, _ in gitems]))})
    out["gardens"] = gardens
    out["load_after"] = os.getloadavg()[0]
    out["date"] = datetime.now(UTC).isoformat(timespec="seconds")
    out["seconds"] = time.time() - t0
    histogram(out, out_dir / "coocmap_speed_tail.png")
    return out


def histogram(o: dict[str, Any], path: Path) -> None:
    """Per-query time before and after, log-spaced bins, the p95 of each and the issue's bound marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = o["real"]
    both = np.r_[r["ms_before"], r["ms_after"]]
    bins = np.geomspace(max(both.min(), 0.05) * 0.9, both.max() * 1.1, 60)
    fig, ax = plt.subplots(figsize=(8, 4))
    for key, colour, label in (("ms_before", "tab:red", f"before ({o['before_rev']})"),
                               ("ms_after", "tab:blue", "after")):
        ax.hist(r[key], bins=bins, histtype="step", color=colour, linewidth=1.5, label=label)
        p95 = float(np.percentile(r[key], 95))
        ax.axvline(p95, color=colour, linestyle="--", linewidth=1)
        ax.text(p95, ax.get_ylim()[1] * 0.9, f" p95 {p95:.1f} ms", color=colour, fontsize=8)
    ax.axvline(41.0, color="black", linestyle=":", linewidth=1, label="41 ms (half the paper's 82 ms)")
    ax.set_xscale("log")
    ax.set_xlabel("ms per query (matching only, features excluded)")
    ax.set_ylabel("queries")
    ax.set_title(f"Cooc-Map, {o['locations']} locations x {o['tours']} tours, {r['n']} real queries")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.bench_coocmap_speed",
                                 description="Regenerate docs/results/coocmap_speed.md (see the module docstring).")
    ap.add_argument("--quick", action="store_true", help="fewer queries (a check, not a result)")
    ap.add_argument("--page-only", action="store_true", help="rewrite the page from the JSON files, measure nothing")
    ap.add_argument("--tail-only", action="store_true", help="part 5 only; the other parts' numbers are kept")
    ap.add_argument("--real", nargs="+", type=Path, default=None, metavar="DIR",
                    help="part 5 on the images under these folders (default: gardens_point and rtabmap_loop)")
    ap.add_argument("--vocab-train", nargs="+", type=Path, default=None, metavar="DIR",
                    help="with --real: folders to train the vocabulary on (default: webcam_daynight/map)")
    ap.add_argument("--locations", type=int, default=2200,
                    help="with --tail-only: locations of part 5's map (default 2200, the paper's size)")
    ap.add_argument("--words", type=int, default=10000, help="with --tail-only: vocabulary size (default 10000)")
    ap.add_argument("--before", default=BEFORE_REV, help=f"git revision of the matcher before (default {BEFORE_REV})")
    ap.add_argument("--out", type=Path, default=RESULTS, help="folder of the results (default docs/results)")
    args = ap.parse_args(argv)
    out_dir: Path = args.out
    if args.real and not args.tail_only:
        sys.exit("bench_coocmap_speed: --real goes with --tail-only (parts 1-4 are the development data's)")
    for d in (args.real or []) + (args.vocab_train or []):
        if not d.is_dir():
            sys.exit(f"bench_coocmap_speed: no such folder: {d}")
    for flag, value in (("--locations", args.locations), ("--words", args.words)):
        if value < 1:
            sys.exit(f"bench_coocmap_speed: {flag} must be at least 1, got {value}")
    out_dir.mkdir(parents=True, exist_ok=True)
    details = out_dir / "coocmap_speed_details.json"
    if args.page_only or args.tail_only:
        if not details.is_file() and not args.tail_only:
            sys.exit(f"bench_coocmap_speed: {details} is missing: run the whole benchmark first")
        # --tail-only into a folder without parts 1-4 (other images): a page of the tail section alone.
        out = json.loads(details.read_text()) if details.is_file() else {"seconds": 0.0, "date": "?"}
        if "seconds" not in out:  # written before the JSON kept them: the date and duration the page states
            found = re.search(r"; ([0-9T:+-]+); (\d+) min\.", (out_dir / "coocmap_speed.md").read_text())
            out["date"], out["seconds"] = (found.group(1), 60.0 * int(found.group(2))) if found else ("?", float("nan"))
        tail_file = out_dir / "coocmap_speed_tail.json"
        if args.tail_only:
            before = matcher_at(args.before)
            if not args.real:
                require_data()
            tail = tail_part(before, args.real or REAL_DIRS, args.vocab_train or VOCAB_FOR_GP, args.quick,
                             out_dir, args.before, args.locations, args.words)
            tail_file.write_text(json.dumps(tail, indent=1, default=float) + "\n")
        if tail_file.is_file():
            out["tail"] = json.loads(tail_file.read_text())
        write_markdown(out, out["seconds"], out_dir)
        return
    require_data()
    before = matcher_at(args.before)
    quick = args.quick
    t_start = time.time()
    real = bench_coocmap_real(REAL_DIRS, locations=2200, tours=5, n_queries=500, vocab_train=VOCAB_FOR_GP,
                              compare=3 if quick else 20)
    synth = bench_coocmap(locations=300 if quick else 2200, tours=5)
    (out_dir / "coocmap_speed_real.json").write_text(json.dumps(real, indent=1, default=float) + "\n")
    (out_dir / "coocmap_speed.json").write_text(json.dumps(synth, indent=1, default=float) + "\n")

    gardens: list[dict[str, Any]] = []
    agree = {"queries": 0, "same_best": 0, "same_exact_scores": 0, "same_top10": 0, "same_group": 0}
    split: dict[str, float] = {}
    gp_counts: dict[str, float] = {}
    for maps, q in TWO_TOUR + ONE_TOUR:
        for pre in PREPROCESSINGS:
            if len(maps) == 1 and pre != "clahe":
                continue
            method, items = fitted(maps, q, pre)
            if quick:
                items = items[::10]
            row = {"maps": "+".join(maps), "query": q, "preprocess": pre, **gardens_timing(method, items)}
            row["map_bytes"] = method.model_.nbytes
            gardens.append(row)
            for k, v in agreement(method, items).items():
                agree[k] += v
            if (maps, q, pre) == (TWO_TOUR[0][0], TWO_TOUR[0][1], "clahe"):
                split = phase_split(method, items[:40])
                gp_counts = counters(method, items)
            print(f"{row['maps']} -> {q} ({pre}): {row['ms_old_median']:.1f} -> {row['ms_new_median']:.1f} ms",
                  flush=True)
    tail = tail_part(before, REAL_DIRS, VOCAB_FOR_GP, quick, out_dir, args.before)
    (out_dir / "coocmap_speed_tail.json").write_text(json.dumps(tail, indent=1, default=float) + "\n")
    out = {"real": real, "synthetic": synth, "gardens_point": gardens, "agreement": agree, "phase_split": split,
           "gardens_counters": gp_counts}
    out["seconds"] = time.time() - t_start
    out["date"] = datetime.now(UTC).isoformat(timespec="seconds")
    details.write_text(json.dumps(out, indent=1, default=float) + "\n")
    if out_dir.resolve() == RESULTS.resolve():
        patch_performance(real, synth)
    out["tail"] = tail
    write_markdown(out, out["seconds"], out_dir)


#: The rows of the "slowest 5 %" table: profile field, label, format.
PROFILE_ROWS = [
    ("features", "query features", "{:.0f}"),
    ("repeated_word_share", "query features whose word recurs in the query", "{:.0%}"),
    ("best_score", "best location's score (group size)", "{:.0f}"),
    ("best_candidates", "best location's candidates", "{:.0f}"),
    ("best_triples_per_candidate", "best location's triples per candidate", "{:.1f}"),
    ("visited", "locations whose candidate count reached the threshold", "{:.0f}"),
    ("pruned_before_J", "of them dropped by the bounds before J", "{:.0f}"),
    ("J_built", "locations whose J was built", "{:.0f}"),
    ("pair_tests", "pair tests (building J)", "{:.0f}"),
    ("steps", "elimination steps", "{:.0f}"),
]


def tail_markdown(t: dict[str, Any]) -> list[str]:
    """The tail section of the page, from coocmap_speed_tail.json."""
    r, pc = t["real"], t["paced"]
    b, a = r["before"], r["after"]
    sb, sa = r["slowest_before"], r["slowest_after"]
    dirs = " ".join(Path(d).name for d in t["dirs"])
    L = [
        "\n## The tail: per-query time (issue #38)\n\n",
        f"Part 5 of the benchmark (`{COMMAND} --tail-only` redoes it alone; `--tail-only --real DIR ... --vocab-train "
        "DIR --out OUTDIR` runs it on other images), "
        f"{t['date']}, {t['seconds'] / 60:.0f} min, 1-minute load average {t['load_before']:.2f} before and "
        f"{t['load_after']:.2f} after. Map: the real benchmark's ({dirs}, {t['locations']} locations x "
        f"{t['tours']} tours, vocabulary trained on {' '.join(Path(v).name for v in t['vocab_train'])}), "
        f"`top_k=1`; {r['n']} queries, each matched by the matcher before (`topoloc/coocmap/compiled.py` at "
        f"revision `{t['before_rev']}`) and by today's, alternated query by query, default threads (one per core). "
        f"Same S (every score, which are exact, the best location's group) bit for bit on "
        f"{r['same_S']}/{r['n']} queries, same best location and top-1 score on {r['same_top_k']}/{r['n']}; "
        f"R@1 {r['recall_at_1']:.3f}.\n\n",
        "The CPU columns are the process's CPU time per query (all its threads): on a machine shared with other "
        "work the wall clock also counts the time a query waited for a core.\n\n",
        "| matcher | ms median | ms p95 | ms p99 | ms max | ms mean | CPU ms median | CPU ms p95 |\n"
        "| --- | --- | --- | --- | --- | --- | --- | --- |\n",
        f"| before (`{t['before_rev']}`) | {b['median']:.1f} | {b['p95']:.1f} | {b['p99']:.1f} | {b['max']:.0f} | "
        f"{b['mean']:.1f} | {r['cpu_before']['median']:.1f} | {r['cpu_before']['p95']:.1f} |\n",
        f"| after | **{a['median']:.1f}** | **{a['p95']:.1f}** | {a['p99']:.1f} | {a['max']:.0f} | "
        f"{a['mean']:.1f} | {r['cpu_after']['median']:.1f} | {r['cpu_after']['p95']:.1f} |\n\n",
        "![per-query time before and after](coocmap_speed_tail.png)\n\n",
        f"**What the slowest 5 % have in common** (medians over the slowest {sb['n_slow']} queries of each matcher "
        "and over the rest; `topoloc.bench.coocmap_speed.query_profile`):\n\n",
        "| per query | before: slowest 5 % | before: rest | after: slowest 5 % | after: rest |\n"
        "| --- | --- | --- | --- | --- |\n",
    ]
    for key, label, fmt in PROFILE_ROWS:
        L.append(f"| {label} | {fmt.format(sb['slow'][key])} | {fmt.format(sb['rest'][key])} | "
                 f"{fmt.format(sa['slow'][key])} | {fmt.format(sa['rest'][key])} |\n")
    def differ(sh: dict[str, Any]) -> str:
        ratios = sorted(((sh["slow"][k] / max(sh["rest"][k], 1e-9), lab) for k, lab, _ in PROFILE_ROWS
                         if k != "repeated_word_share"), reverse=True)
        return "; ".join(f"{lab} {x:.1f}x" for x, lab in ratios if x >= 1.5)

    L.append("\nBefore, the slowest 5 % differ from the rest most in (ratio of medians): " + differ(sb) +
             ". Their queries have more features and their best locations many triples per candidate (a word "
             "that recurs in the query and in the stored images: texture, foliage, repeated structure), so "
             "the translation bound, which counts every triple, stays above the best score for many "
             "locations whose J is then built; and each such J, of hundreds of candidates with tens of "
             "triples each, costs millions of pair tests. After: " + differ(sa) +
             f". J is built for {sa['slow']['J_built']:.0f} locations (median of the slowest 5 %): what remains is "
             f"the J of the best location itself ({sa['slow']['best_candidates']:.0f} candidates, "
             f"{sa['slow']['best_triples_per_candidate']:.1f} triples each), which no bound may skip, and the "
             f"bounds of the {sa['slow']['visited']:.0f} locations whose candidate count reached the threshold.\n\n")
    L.append(
        "What changed (`topoloc.coocmap.compiled`, exact: the same J and the same elimination wherever one is "
        "needed): (1) before a J is built, a bound from the *distinct* candidates near each candidate's "
        "translations (`_window_bound`: bitsets of candidates per translation bucket, dilated by the "
        "tolerance; then peeling the candidates that cannot be in a group as large as the threshold), "
        "computed where a location has at least 2 triples per candidate, where the translation bound is "
        "loosest; (2) in J, a candidate's triples within a translation bucket are one run, skipped at once "
        "when its pair is already known consistent, and each triple's partners are swept as contiguous "
        "ranges; (3) the signed cells of an offset between two points of the position lattice from a table; "
        "(4) with helper threads, one location a claim until `top_k` locations have finished: before, each "
        "thread claimed 8 at once, and with no threshold until `top_k` had finished (10 on the gardens_point "
        "maps below) both built every J of their first chunks (the J-built columns below); (5) the "
        "elimination keeps the candidates left compact, so a step is a sweep without a test per candidate "
        "(the same steps); (6) where a location's triples crowd into few translation buckets (a place that "
        "matches, with XFeat: most of its triples in a few buckets), J is swept a bucket at a time through bitsets of "
        "the candidates in each bucket and of those each candidate is already known consistent with, and "
        "pairs of candidates sharing a bucket are set without a test where its stored features and groups "
        "allow (two translations in one bucket are less than a square apart), chosen per location from how "
        "the buckets are filled (`_bucket_sweep_pays`).\n\n")
    L += [
        f"**Beside busy processes** (today's matcher, {pc['n']} queries paced at {pc['hz']:.0f} Hz as "
        "`benchmarks.bench_load` paces them):\n\n",
        "| | 1-min load | ms median | ms p95 | ms max |\n| --- | --- | --- | --- | --- |\n",
        f"| quiet | {pc['load_quiet']:.2f} | {pc['quiet']['median']:.1f} | {pc['quiet']['p95']:.1f} | "
        f"{pc['quiet']['max']:.0f} |\n",
        f"| {pc['busy']} busy processes | {pc['load_busy']:.2f} | {pc['loaded']['median']:.1f} | "
        f"{pc['loaded']['p95']:.1f} | {pc['loaded']['max']:.0f} |\n\n",
        f"p95 beside {pc['busy']} busy processes / quiet: **{pc['p95_ratio']:.2f}x**.\n",
    ]
    if t["gardens"]:
        L += [
            "\n**gardens_point, two map tours** (100 places, the method as `topoloc evaluate` fits it: `top_k=10`, "
            "default preprocessing), before and after alternated query by query. Features: SIFT with the "
            "vocabulary trained on webcam_daynight (as parts 2-4), and XFeat with the vocabulary trained on the "
            "map's own tours, which is what `topoloc evaluate` uses when given neither (the defaults where the "
            "`learned` extra is installed). J built: locations whose J was built, median per query.\n\n",
            "| features | map tours -> query | features / query (median) | queries | before ms median / p95 "
            "| after ms median / p95 | before CPU ms median / p95 | after CPU ms median / p95 | J built before / "
            "after | same S |\n"
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n",
        ]
        for g in t["gardens"]:
            L.append(f"| {FEATURE_LABEL.get(g.get('features', 'sift'), g.get('features', 'sift'))} | {g['maps']} -> "
                     f"{g['query']} | {g['features_median']:.0f} | {g['n']} | "
                     f"{g['before']['median']:.1f} / {g['before']['p95']:.1f} | **{g['after']['median']:.1f}** / "
                     f"{g['after']['p95']:.1f} | {g['cpu_before']['median']:.1f} / {g['cpu_before']['p95']:.1f} | "
                     f"{g['cpu_after']['median']:.1f} / {g['cpu_after']['p95']:.1f} | "
                     f"{g.get('built_before', float('nan')):.0f} / {g.get('built_after', float('nan')):.0f} | "
                     f"{g['same_S']}/{g['n']} |\n")
    L += ["\n**Issue #38's targets** (2 cores; each from the rows above):\n\n",
          "| target | measured | met |\n| --- | --- | --- |\n"]
    for label, value, ok in targets(t):
        L.append(f"| {label} | {value} | {'yes' if ok else '**no**'} |\n")
    return L


#: How the gardens_point rows name their features.
FEATURE_LABEL = {"sift": "SIFT", "xfeat": "XFeat (default)"}

#: Issue #38's bounds (ms): the real map's median and p95, the gardens_point rows' median and p95, and the
#: p95 beside busy processes over the quiet p95 (a ratio).
TARGET_REAL_MS = (5.0, 41.0)
TARGET_GARDENS_MS = (10.0, 25.0)
TARGET_BUSY_RATIO = 3.0


def targets(t: dict[str, Any]) -> list[tuple[str, str, bool]]:
    """``(target, measured, met)`` of each of issue #38's bounds that part 5 measures."""
    a, pc = t["real"]["after"], t["paced"]
    out = [(f"real {t['locations']} x {t['tours']}: median < {TARGET_REAL_MS[0]:g} ms, p95 < {TARGET_REAL_MS[1]:g} ms",
            f"{a['median']:.1f} / {a['p95']:.1f} ms", a["median"] < TARGET_REAL_MS[0] and a["p95"] < TARGET_REAL_MS[1]),
           (f"paced at {pc['hz']:.0f} Hz: p95 beside {pc['busy']} busy processes within {TARGET_BUSY_RATIO:g}x "
            "of quiet",
            f"{pc['p95_ratio']:.2f}x", pc["p95_ratio"] <= TARGET_BUSY_RATIO)]
    for g in t["gardens"]:
        ga = g["after"]
        out.append((f"gardens_point {FEATURE_LABEL.get(g.get('features', 'sift'), 'SIFT')} {g['maps']} -> "
                    f"{g['query']}: median < {TARGET_GARDENS_MS[0]:g} ms, p95 < {TARGET_GARDENS_MS[1]:g} ms",
                    f"{ga['median']:.1f} / {ga['p95']:.1f} ms",
                    ga["median"] < TARGET_GARDENS_MS[0] and ga["p95"] < TARGET_GARDENS_MS[1]))
    return out


def write_markdown(o: dict[str, Any], seconds: float, out_dir: Path = RESULTS) -> None:
    if "real" not in o:  # the tail section alone (--tail-only on other images)
        (out_dir / "coocmap_speed.md").write_text(
            "# Cooc-Map localisation time: the tail\n\n"
            f"Generated by `{COMMAND} --tail-only`; do not edit by hand. Machine: {platform.machine()}, "
            f"{os.cpu_count()} cores, Python {platform.python_version()}.\n" + "".join(tail_markdown(o["tail"])))
        return
    r, s, a, sp, gc = o["real"], o["synthetic"], o["agreement"], o["phase_split"], o["gardens_counters"]
    L = [
        "# Cooc-Map localisation time\n\n",
        f"Generated by `{COMMAND}` (raw numbers in `coocmap_speed_real.json`, `coocmap_speed.json`, "
        "`coocmap_speed_details.json`); do not edit by hand. Machine: "
        f"{platform.machine()}, 2 cores shared with other work, Python {platform.python_version()}; "
        f"{o['date']}; {seconds / 60:.0f} min. "
        "Feature extraction excluded, as in the paper (Sec. IV: 82 ms per localisation, 2,200 locations).\n\n",
        "## At the paper's size\n\n",
        "| benchmark | locations x tours | features / image (median) | queries | ms median | ms p95 | R@1 | map | "
        "peak RSS |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n",
        f"| real (`topoloc bench coocmap --real {' '.join(str(Path(d).name) for d in r['dirs'])} --vocab-train "
        f"webcam_daynight/map`) | {r['locations']} x {r['tours']} | {r['n_features_median']:.0f} | "
        f"{r['n_queries']} | **{r['ms_per_query_median']:.1f}** | **{r['ms_per_query_p95']:.1f}** | "
        f"{r['recall_at_1']:.3f} | {r['map_bytes'] / 1e6:.1f} MB ({r['bytes_per_location'] / 1e3:.1f} kB per "
        f"location) | {r['peak_rss_mb']:.0f} MiB |\n",
        f"| synthetic (`topoloc bench coocmap`) | {s['locations']} x {s['tours']} | {s['features']} | "
        f"{s['n_queries']} | {s['ms_per_query_median']:.1f} | {s['ms_per_query_p95']:.1f} | "
        f"{s['recall_at_1']:.3f} | {s['map_bytes'] / 1e6:.1f} MB ({s['bytes_per_location'] / 1e3:.1f} kB per "
        "location) | |\n\n",
        "Before (the previous default matcher, `match_lazy`, same map, same process): real "
        f"median {r['ms_lazy_median']:.0f} ms, p95 {r['ms_lazy_p95']:.0f} ms on its first {r['compare']} queries "
        f"(R@1 {r['recall_at_1_lazy']:.3f} there, new matcher {r['recall_at_1_compiled_same_queries']:.3f}, same "
        f"best location on {r['lazy_agree']:.0%}); synthetic median {s['ms_lazy_median']:.1f} ms, p95 "
        f"{s['ms_lazy_p95']:.1f} ms.\n\n",
        "The real benchmark: every image under the folders (gardens_point's three traverses and rtabmap_loop, "
        f"{r['n_images']} images) gives distinct crops of half its width and height (2 rows, columns evenly "
        "spaced; neighbouring crops overlap by up to half), one per location; each of a location's 5 tours and "
        "its query is a seeded re-observation of the crop resampled to 640 px: viewpoint (scale 0.9-1.1, "
        "rotation +-3 deg, shift +-5 %), brightness x0.7-1.3, gamma 0.7-1.4, blur sigma 0-1.5 px, noise sigma "
        "0-6 grey levels (`topoloc.bench.coocmap_speed.image_variant`). Features are `topoloc evaluate`'s "
        f"defaults (SIFT, at most 1,000, preprocessing `{FeatureConfig().preprocess}`), quantised with 10,000 "
        "words trained on webcam_daynight/map. Map and "
        "matcher are the `coocmap` method's defaults with `top_k=1` (pure localisation, the paper's bound). "
        "Crops of one image and the same place in the three gardens_point traverses look alike, which is what "
        "keeps R@1 below 1.\n\n",
        "## gardens_point, two map tours, 100 places (`topoloc evaluate --method coocmap`)\n\n",
        "The method as `evaluate` fits it (defaults: `top_k=10`, so ranks 1-10 exact), vocabulary trained on "
        "webcam_daynight; the features column is the preprocessing (`--preprocess`) and the median "
        "feature count per query image; ms per query of the matcher alone, previous default "
        "(`schedule=lazy`) and new default "
        "(`schedule=compiled`) alternated query by query.\n\n",
        "| map tours -> query | features | queries | before ms median / p95 | after ms median / p95 | speed-up | "
        "same top-10 |\n| --- | --- | --- | --- | --- | --- | --- |\n",
    ]
    for g in o["gardens_point"]:
        label = g["preprocess"] + (" (default)" if g["preprocess"] == FeatureConfig().preprocess else "")
        L.append(f"| {g['maps']} -> {g['query']} | {label}, "
                 f"{g['features_median']:.0f} | {g['n_queries']} | {g['ms_old_median']:.1f} / {g['ms_old_p95']:.1f} | "
                 f"**{g['ms_new_median']:.1f}** / {g['ms_new_p95']:.1f} | {g['speedup_median']:.1f}x | "
                 f"{g['same_top_k']:.0%} |\n")
    L += [
        "\n## Exactness\n\n",
        "The new matcher (`topoloc.coocmap.compiled.match_compiled`) computes nothing approximately: it builds "
        "the same J_i (same enumeration, same tests), eliminates with the same floating-point keys and "
        "tie-breaking as the reference `eliminate`, and only skips locations whose upper bound is below the "
        "top_k-th best finished score. Measured against the exact reference (every J_i built, every location "
        f"eliminated to completion, `match_sequential`) on {a['queries']} real gardens_point queries (the runs "
        f"above and day_left -> night_right): same best location {a['same_best']}/{a['queries']}, same scores "
        f"of every location it finished {a['same_exact_scores']}/{a['queries']}, same top-10 scores "
        f"{a['same_top10']}/{a['queries']}, same final group of the best location "
        f"{a['same_group']}/{a['queries']}. The previous matchers stay available: `--param schedule=lazy`, "
        "`best_first`, `rounds`, and `simultaneous=false` (every place to completion).\n\n",
        "## Where the time goes now\n\n",
        "gardens_point day_left+night_right -> day_right (CLAHE), per query, every location processed alone "
        "(CPU time, 40 queries): candidates and the bounds before J (translations, partners) "
        f"{sp.get('triples_and_translation_bound_ms', float('nan')):.1f} ms, building J "
        f"{sp.get('J_ms', float('nan')):.1f} ms, elimination to completion "
        f"{sp.get('elimination_ms', float('nan')):.1f} ms. In the real run (median per query): J built for "
        f"{gc.get('locations_built', float('nan')):.0f} of 100 places, "
        f"{gc.get('translation_pruned', float('nan')):.0f} dropped by the translation bound, "
        f"{gc.get('pair_tests', float('nan')):.0f} pair tests, {gc.get('elimination_steps', float('nan')):.0f} "
        "elimination steps. Across day and night the bounds of Sec. II-D cannot drop places before their J "
        "(a wrong place's bound is 2-4x the 10th best score), so building J for all 100 places dominates.\n\n",
        f"Real benchmark (median per query): J built for {r['locations_built_median']:.0f} of {r['locations']} "
        f"locations (p95 {r['locations_built_p95']:.0f}), {r['translation_pruned_median']:.0f} dropped by the "
        f"translation bound, {r['pair_tests_median']:.0f} pair tests; the rest never get past the candidate "
        "count of the inverted file.\n",
    ]
    if "tail" in o:
        L += tail_markdown(o["tail"])
    (out_dir / "coocmap_speed.md").write_text("".join(L))


if __name__ == "__main__":
    main()
