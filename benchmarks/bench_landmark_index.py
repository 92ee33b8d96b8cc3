"""Regenerate docs/results/landmark_index.md (+ .json): where landmarks' ``index="auto"`` goes from flat to HNSW.

    .venv/bin/python -m benchmarks.bench_landmark_index [--queries 20] [--repeats 3] [--max-landmarks 65536]
    .venv/bin/python -m benchmarks.bench_landmark_index --page-only     # the page again from its .json

Two measurements, then the rule that places the switch
(:data:`topoloc.landmarks.model.AUTO_FLAT_MAX_LANDMARKS`) is applied to them:

1. The development maps (:data:`DEV_MAPS`): every landmark map that ``../shared/scorecard`` and
   the results pages build from the shared data, with ``LandmarkMap``'s defaults and the
   features those runs use, built as ``topoloc evaluate`` builds them (``Map.build``), plus the
   largest maps the data gives (all three gardens_point traverses, all twelve webcam tours),
   which no page reports.  Each map's landmark count and the index ``"auto"`` resolves to for it.
2. The look-up of one query as a function of the number of landmarks ``N`` (a doubling grid
   from 256): the faiss search of a query's features for their ``n_candidates`` nearest landmark
   means, exactly as ``LandmarkModel.match_pairs`` makes it (the model's own index,
   ``landmark_index``, on the calling thread), with the exact flat index and with HNSW.  The
   means are real: the distinct landmark means of the development maps, a random ``N`` of them;
   a size beyond their number adds copies with a little noise (flat search costs the same
   whatever the values; HNSW is then timed on near-duplicates, said on the page).  The queries
   are gardens_point ``day_right`` images (the scorecard's ``landmarks_day`` queries, default
   features); each is timed ``--repeats`` times with each index, alternately, the fastest kept
   (the machine is shared: the fastest of a few is the least disturbed), the median over queries.
3. What HNSW would change on a development map: the scorecard's ``landmarks_day`` map
   (gardens_point ``day_left``) built with each index, its ``day_right`` scores compared.

The rule (:func:`choose_switch`): the smallest measured size at which flat search costs more
than :data:`FEW_MS` per query *and* that leaves :data:`ROOM` times the largest development map
below it, so that every development result stays that of the exact index.  The page says
which of the two decided, and whether the constant in the code still agrees.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_localize_100k import TARGET_MS
from benchmarks.common import DATA, GP, RESULTS, WEBCAM_TOURS, machine_line, require_data

FEW_MS = TARGET_MS["landmarks"] / 10
"""Flat search per query that counts as "more than a few ms": a tenth of the 50 ms a landmark query may take
at camera rate (``benchmarks.bench_localize_100k.TARGET_MS``), so the look-up alone stays a small part of it."""

ROOM = 0.0
"""How many times the largest development map the switch must be at least.  It was 1.5, so that every
development map kept the exact index and the results pages' numbers; with XFeat (1,000 features of a query,
64-D) the flat look-up of the scorecard's ``landmarks_day`` map took most of the 50 ms a landmark frame may take
with verification (issue #47), while HNSW gives that map the same metrics (section 3 of the page), so the time
alone decides now."""

# (label, map tours, features' max_side, the pages that report a run on that map; "" for none)
DEV_MAPS: list[tuple[str, list[Path], int | str, str]] = [
    ("gardens_point day_left", [GP / "day_left"], "auto",
     "scorecard `landmarks_day`; landmarks.md, confidence.md, daynight.md, maps.md, performance.md"),
    ("gardens_point day_right", [GP / "day_right"], "auto", "landmarks.md, confidence.md, daynight.md"),
    ("gardens_point day_left + day_right", [GP / "day_left", GP / "day_right"], "auto",
     "landmarks.md, confidence.md, daynight.md, sequence_confidence.md"),
    ("gardens_point day_left + night_right", [GP / "day_left", GP / "night_right"], "auto",
     "landmarks.md (ablation), confidence.md, maps.md"),
    ("corridor ref", [DATA / "corridor" / "ref"], "auto", "landmarks.md"),
    ("gardens_point day_left, full resolution", [GP / "day_left"], 0, "performance.md (feature scale)"),
    ("gardens_point day_left + day_right, full resolution", [GP / "day_left", GP / "day_right"], 0,
     "performance.md (feature scale)"),
    ("gardens_point, all three traverses", [GP / "day_left", GP / "day_right", GP / "night_right"], "auto", ""),
    ("webcam_daynight, all 12 map tours", list(WEBCAM_TOURS), "auto", ""),
]


def dev_maps(cache_dir: Path | None) -> tuple[list[dict[str, Any]], np.ndarray, list[np.ndarray]]:
    """Every map of :data:`DEV_MAPS`: its row, the distinct landmark means of all, and the query descriptors.

    The queries are gardens_point ``day_right``'s images described as the first map describes its own (the
    scorecard's ``landmarks_day``), unit-normalised as ``match_pairs`` searches them.
    """
    from topoloc.datasets.traverse import load_traverse
    from topoloc.geometry import normalise_descriptors
    from topoloc.maps import Map
    from topoloc.spec.parts import FeatureSpec

    rows, means = [], []
    queries: list[np.ndarray] = []
    for label, tours, side, reported in DEV_MAPS:
        t0 = time.perf_counter()
        m = Map.build(method="landmarks", tours=tours, features=FeatureSpec(max_side=side), cache_dir=cache_dir)
        rec = m.recognizer
        model = rec.model_
        rows.append({"label": label, "tours": [str(Path(t).relative_to(DATA)) for t in tours],
                     "max_side": side, "reported": reported, "nodes": int(model.n_nodes_),
                     "landmarks": int(model.n_landmarks_), "index": rec.index, "index_kind": model.index_kind_,
                     "features_per_image_median": float(np.median(model.node_features_)),
                     "build_s": time.perf_counter() - t0})
        print(json.dumps(rows[-1]), flush=True)
        means.append(np.asarray(model.mean_, np.float32))
        if not queries:
            items = rec.encode(load_traverse(GP / "day_right"))
            queries = [np.ascontiguousarray(normalise_descriptors(f.descriptors), np.float32) for f in items]
    return rows, np.unique(np.concatenate(means), axis=0), queries


def hnsw_change(cache_dir: Path | None) -> dict[str, Any]:
    """The scorecard's ``landmarks_day`` map built with the flat and the HNSW index: how its scores differ."""
    from topoloc.datasets.traverse import load_traverse
    from topoloc.maps import Map

    query = load_traverse(GP / "day_right")
    S = {}
    for kind in ("flat", "hnsw"):
        m = Map.build(method="landmarks", tours=[GP / "day_left"], params={"index": kind}, cache_dir=cache_dir)
        S[kind] = m.similarity(query)
    best = {k: np.argmax(v, axis=0) for k, v in S.items()}
    return {"map": "gardens_point/day_left", "query": "gardens_point/day_right", "queries": int(S["flat"].shape[1]),
            "max_abs_score_difference": float(np.abs(S["flat"] - S["hnsw"]).max()),
            "same_best_place": float(np.mean(best["flat"] == best["hnsw"]))}


def means_of_size(pool: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """``n`` landmark means: a random ``n`` of ``pool``, or all of it and noisy copies; returns them and the copies.

    A copy is a pool mean plus Gaussian noise of norm about 0.05, renormalised (landmark radii are at least
    ``radius_floor``, 0.6, so a copy matches what its original matches), so HNSW is not timed on exact duplicates.
    """
    if n <= len(pool):
        return pool[rng.permutation(len(pool))[:n]], 0
    extra = n - len(pool)
    src = pool[rng.integers(0, len(pool), extra)]
    noisy = src + rng.standard_normal(src.shape).astype(np.float32) * np.float32(0.05 / np.sqrt(pool.shape[1]))
    noisy /= np.maximum(np.linalg.norm(noisy, axis=1, keepdims=True), 1e-12)
    return np.vstack([pool, noisy.astype(np.float32)]), extra


def time_lookups(means: np.ndarray, queries: Sequence[np.ndarray], n_candidates: int, repeats: int
                 ) -> dict[str, Any]:
    """Per-query look-up times (ms, fastest of ``repeats``) with the flat and the HNSW index over ``means``.

    Returns medians over the queries (wall and CPU), HNSW's build time, and HNSW's recall: the share of the
    flat index's nearest means (the exact ones) that HNSW also returns.
    """
    from topoloc._parallel import search_threads
    from topoloc.landmarks.model import landmark_index

    t0 = time.perf_counter()
    indexes = {"flat": landmark_index("flat", means, n_candidates)}
    t1 = time.perf_counter()
    indexes["hnsw"] = landmark_index("hnsw", means, n_candidates)
    build = {"flat": t1 - t0, "hnsw": time.perf_counter() - t1}
    k = min(n_candidates, len(means))
    wall: dict[str, list[float]] = {"flat": [], "hnsw": []}
    cpu: dict[str, list[float]] = {"flat": [], "hnsw": []}
    recall = []
    for d in queries:
        found = {}
        for kind, index in indexes.items():  # both kinds per query: drifting load hits them alike
            best_w = best_c = float("inf")
            for _ in range(repeats):
                c0, w0 = time.process_time(), time.perf_counter()
                with search_threads(len(d)):  # as match_pairs searches: one image's features, one thread
                    _, nn = index.search(d, k)
                best_w, best_c = min(best_w, time.perf_counter() - w0), min(best_c, time.process_time() - c0)
            wall[kind].append(1e3 * best_w)
            cpu[kind].append(1e3 * best_c)
            found[kind] = nn
        exact, approx = found["flat"], found["hnsw"]
        recall.append(float(np.mean([len(np.intersect1d(a, b)) / k for a, b in zip(exact, approx, strict=True)])))
    return {"flat_ms": statistics.median(wall["flat"]), "hnsw_ms": statistics.median(wall["hnsw"]),
            "flat_cpu_ms": statistics.median(cpu["flat"]), "hnsw_cpu_ms": statistics.median(cpu["hnsw"]),
            "flat_build_s": build["flat"], "hnsw_build_s": build["hnsw"], "hnsw_recall": statistics.fmean(recall),
            "k": k}


def grid(max_landmarks: int, switch: int) -> list[int]:
    """Doubling sizes from 256 up to ``max_landmarks``, and the code's switch and the size above it."""
    sizes = {256 << i for i in range(32) if 256 << i <= max_landmarks}
    return sorted(sizes | {switch, switch + 1})


def choose_switch(rows: Sequence[dict[str, Any]], largest_map: int, *, few_ms: float = FEW_MS,
                  room: float = ROOM) -> dict[str, Any]:
    """The switch the rule gives: the smallest measured size past both bounds (see the module docstring).

    Parameters
    ----------
    rows : sequence of dict
        One per size, with ``landmarks`` and ``flat_ms`` (and ``hnsw_ms``), ascending sizes.
    largest_map : int
        Landmarks of the largest development map.

    Returns
    -------
    dict
        ``switch`` (None when no measured size passes both), ``few_ms_size`` (the first size whose flat
        search costs more than ``few_ms``), ``hnsw_faster_size`` (the first size from which HNSW is faster
        at every larger size), ``room_size`` (``room`` times ``largest_map``) and ``decided_by``.
    """
    few = next((r["landmarks"] for r in rows if r["flat_ms"] > few_ms), None)
    faster = None
    for r in reversed(rows):  # the first size of the last run of sizes at which HNSW wins
        if r["hnsw_ms"] >= r["flat_ms"]:
            break
        faster = r["landmarks"]
    need = room * largest_map
    switch = next((r["landmarks"] for r in rows
                   if r["flat_ms"] > few_ms and r["hnsw_ms"] < r["flat_ms"] and r["landmarks"] >= need), None)
    decided = None if switch is None else ("the development maps" if few is not None and few < need
                                           else "the flat search time")
    return {"switch": switch, "few_ms_size": few, "hnsw_faster_size": faster, "room_size": need,
            "decided_by": decided, "few_ms": few_ms, "room": room}


def page(result: dict[str, Any]) -> str:
    """The results page, written from ``result`` (what the .json holds)."""
    maps, rows, rule, change = result["dev_maps"], result["lookups"], result["rule"], result["hnsw_change"]
    code = result["code_switch"]
    largest = max(maps, key=lambda r: r["landmarks"])
    reported = [r for r in maps if r["reported"]]
    largest_reported = max(reported, key=lambda r: r["landmarks"])
    text = [
        "# Landmarks: exact or HNSW index (`index=\"auto\"`)\n\n",
        f"Generated by `{' '.join(['.venv/bin/python -m benchmarks.bench_landmark_index', result['args']]).strip()}`; "
        "do not edit by hand "
        f"({result['machine']}, {result['date']}; 1-minute load average {result['load_before']:.2f} before the "
        "run). Raw numbers: [landmark_index.json](landmark_index.json). `benchmarks/bench_landmark_index.py` "
        "says how each number is made.\n\n",
        "`LandmarkMap(index=\"auto\")`, the default, searches the landmark means with faiss's exact flat index up "
        f"to `AUTO_FLAT_MAX_LANDMARKS` = {code:,} landmarks (`topoloc.landmarks.model`) and with HNSW above; the "
        "kind is decided when the map is built and saved with it (`model_.index_kind_`).\n\n",
        "## The development maps\n\n",
        "Every landmark map the scorecard and the results pages build from the shared data (default parameters "
        "and the features of those runs), and the largest maps the data gives (no page reports them). Maps built "
        "with `tours=\"first\"` have the landmarks of their first tour alone, and the sparser variants of "
        "[landmarks_fps.md](landmarks_fps.md) (`min_track_length=3`, every k-th frame a node) fewer than these.\n\n",
        "| map | features | nodes | features per image (median) | landmarks | `auto` resolves to | reported in |\n",
        "| --- | --- | --- | --- | --- | --- | --- |\n",
    ]
    for r in maps:
        feats = "full resolution" if r["max_side"] == 0 else "default (longer side <= 640 px)"
        text.append(f"| {r['label']} | {feats} | {r['nodes']:,} | {r['features_per_image_median']:.0f} | "
                    f"{r['landmarks']:,} | {r['index_kind']} | {r['reported'] or 'none'} |\n")
    text.append(
        f"\nLargest: {largest['landmarks']:,} landmarks ({largest['label']}), {code / largest['landmarks']:.2f}x "
        f"below the switch; the largest a page reports: {largest_reported['landmarks']:,} "
        f"({largest_reported['label']}), {code / largest_reported['landmarks']:.2f}x below it. "
        + ("Every development map resolves to `flat`, so its results are those of the exact index, as before "
           "`auto` existed.\n" if all(r["index_kind"] == "flat" for r in maps) else
           "**Not every development map resolves to `flat`**: its results are no longer the exact index's.\n"))
    q = result["queries"]
    text += [
        "\n## One query's look-up against the number of landmarks\n\n",
        f"The faiss search of a query's features for their {rows[0]['k'] if rows else '-'} nearest landmark means "
        "(`n_candidates`), as `LandmarkModel.match_pairs` makes it (one thread), with each index over the same "
        f"means; {q['n']} gardens_point `day_right` queries (median {q['features_median']:.0f} features, the "
        f"scorecard's `landmarks_day` queries), each the fastest of {result['repeats']} runs, median over the "
        f"queries. The means are the {result['pool']:,} distinct landmark means of the development maps"
        + (", and beyond that many, copies of them with a little noise (marked)" if any(r["copies"] for r in rows)
           else "") + ". Recall: the share of the exact nearest means that HNSW also returns. The flat search of "
        "a query costs time proportional to its features times the landmarks, so a query with fewer features "
        "costs proportionally less at every size"
        + (f" (the route of [localize_100k.md](localize_100k.md) has a median of {result['route']['features']:.0f} "
           "features an image, for one)" if result.get("route") else "") + ".\n\n",
        "| landmarks | flat ms per query | HNSW ms per query | flat / HNSW | flat CPU ms | HNSW CPU ms | HNSW recall "
        "| HNSW build s | `auto` |\n",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n",
    ]
    for r in rows:
        mark = f" ({r['copies']:,} noisy copies)" if r["copies"] else ""
        text.append(f"| {r['landmarks']:,}{mark} | {r['flat_ms']:.2f} | {r['hnsw_ms']:.2f} | "
                    f"{r['flat_ms'] / r['hnsw_ms']:.2f} | {r['flat_cpu_ms']:.2f} | {r['hnsw_cpu_ms']:.2f} | "
                    f"{r['hnsw_recall']:.4f} | {r['hnsw_build_s']:.2f} | {r['auto']} |\n")
    per = [r["flat_ms"] / r["landmarks"] / q["features_median"] * 1e6 for r in rows if r["landmarks"] >= 4096]
    if per:
        text.append(f"\nFlat search costs about {statistics.median(per):.1f} ns per query feature and landmark "
                    "(median over the sizes from 4,096).")
    few, faster = rule["few_ms_size"], rule["hnsw_faster_size"]
    text.append(
        "\n\n## Where the switch is\n\n"
        f"Rule (`choose_switch`): the smallest measured size at which flat search costs more than "
        f"{rule['few_ms']:.0f} ms per query (`FEW_MS`: a tenth of the 50 ms a landmark query may take, "
        f"`TARGET_MS` of `bench_localize_100k`), at which HNSW is faster, and which is at least {rule['room']:g}x "
        f"(`ROOM`) the largest development map ({rule['room_size']:,.0f} landmarks). Flat search first costs more than "
        f"{rule['few_ms']:.0f} ms at {few:,} landmarks" if few is not None else
        "Flat search never costs more than the limit at the measured sizes")
    text.append(
        (f"; HNSW is faster from {faster:,} landmarks on" if faster is not None else "; HNSW is faster at no size")
        + ". ")
    if rule["switch"] is None:
        text.append("No measured size passes both bounds: measure larger sizes (`--max-landmarks`).\n")
    else:
        text.append(f"The rule gives {rule['switch']:,}, decided by {rule['decided_by']}")
        if rule["decided_by"] == "the development maps":
            inexact = next((r for r in rows if r["hnsw_recall"] < 1.0), None)
            text.append(
                f": a switch where flat search first costs more than {rule['few_ms']:.0f} ms ({few:,}) would put "
                "development maps on the approximate index"
                + (f" (its recall is below 1 from {inexact['landmarks']:,} landmarks on: "
                   f"{inexact['hnsw_recall']:.5f} there)" if inexact is not None else "")
                + f"; on the scorecard's `landmarks_day` map ({change['map']}) HNSW's scores of the "
                f"{change['queries']} {change['query']} queries differ from the exact index's by up to "
                f"{change['max_abs_score_difference']:.4f} (same best place for "
                f"{100 * change['same_best_place']:.0f}% of them), so the results pages' numbers would no longer "
                "be the exact index's. The switch is above the development maps instead, where a flat look-up "
                "costs more than the limit many times over")
        if rule["decided_by"] == "the flat search time":
            text.append(f". On the scorecard's `landmarks_day` map ({change['map']}) HNSW's scores of the "
                        f"{change['queries']} {change['query']} queries (unverified) differ from the exact index's "
                        f"by up to {change['max_abs_score_difference']:.4f}, the same best place for "
                        f"{100 * change['same_best_place']:.0f}% of them")
        text.append(". ")
        if rule["switch"] == code:
            text.append(f"The code's `AUTO_FLAT_MAX_LANDMARKS` ({code:,}) agrees.\n")
        else:
            text.append(f"**The code's `AUTO_FLAT_MAX_LANDMARKS` ({code:,}) differs from it**: set it to "
                        f"{rule['switch']:,}, or say why not.\n")
    at = next((r for r in rows if r["landmarks"] == code), None)
    if at is not None:
        text.append(f"\nAt the switch ({code:,} landmarks) a flat look-up costs {at['flat_ms']:.1f} ms per query, "
                    f"HNSW {at['hnsw_ms']:.1f} ms (recall {at['hnsw_recall']:.4f}).")
    route = result.get("route")
    if route:
        text.append(f" At {route['landmarks']:,} landmarks (the {route['places']:,}-place route of "
                    f"[localize_100k.md](localize_100k.md)) a whole query takes {route['flat_ms']:,.1f} ms with the "
                    f"flat index against {route['hnsw_ms']:.1f} ms with HNSW, which `auto` picks there.")
    text.append("\n")
    return "".join(text)


def route_numbers(path: Path) -> dict[str, Any] | None:
    """The largest landmark map of ``localize_100k.json`` (``bench_localize_100k``), if that page was made."""
    if not path.is_file():
        return None
    d = json.loads(path.read_text())
    sizes = [r for r in d.get("landmark_sizes", []) if "flat_ms_median" in r]
    if not sizes:
        return None
    r = max(sizes, key=lambda r: r["landmarks"])
    return {"places": r["places"], "landmarks": r["landmarks"], "flat_ms": r["flat_ms_median"],
            "hnsw_ms": r["ms_median"], "features": d["meta"]["n_features"]}


def main(argv: list[str] | None = None) -> None:
    from topoloc.landmarks import model as landmark_model
    from topoloc.methods.landmark_map import LandmarkMap

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queries", type=int, default=20, help="day_right queries timed (evenly spaced)")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each query with each index (fastest kept)")
    parser.add_argument("--max-landmarks", type=int, default=65536, help="largest size of the doubling grid")
    parser.add_argument("--cache-dir", type=Path, default=None, help="feature cache (default: topoloc's)")
    parser.add_argument("--seed", type=int, default=0, help="of the random means taken at each size")
    parser.add_argument("--out", type=Path, default=RESULTS / "landmark_index.md")
    parser.add_argument("--page-only", action="store_true", help="rewrite the page from its .json, measuring nothing")
    args = parser.parse_args(argv)
    if args.page_only:
        args.out.write_text(page(json.loads(args.out.with_suffix(".json").read_text())))
        print(f"wrote {args.out}")
        return
    require_data()
    load_before = os.getloadavg()[0]
    maps, pool, all_queries = dev_maps(args.cache_dir)
    step = max(1, len(all_queries) // max(args.queries, 1))
    queries = all_queries[::step][:args.queries]
    n_candidates = LandmarkMap().n_candidates
    code = landmark_model.AUTO_FLAT_MAX_LANDMARKS
    rng = np.random.default_rng(args.seed)
    rows = []
    for n in grid(args.max_landmarks, code):
        means, copies = means_of_size(pool, n, rng)
        row = {"landmarks": n, "copies": copies, "auto": landmark_model.resolve_index("auto", n),
               **time_lookups(means, queries, n_candidates, args.repeats), "load": os.getloadavg()[0]}
        rows.append(row)
        print(json.dumps(row), flush=True)
    largest = max(r["landmarks"] for r in maps)
    result = {"route": route_numbers(RESULTS / "localize_100k.json"), "hnsw_change": hnsw_change(args.cache_dir),
        "machine": machine_line(), "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "load_before": load_before,
        "args": " ".join(argv if argv is not None else sys.argv[1:]).strip(),
        "repeats": args.repeats, "pool": len(pool), "code_switch": code,
        "queries": {"n": len(queries), "features_median": float(np.median([len(d) for d in queries])),
                    "source": "gardens_point/day_right"},
        "dev_maps": maps, "lookups": rows, "rule": choose_switch(rows, largest),
    }
    args.out.with_suffix(".json").write_text(json.dumps(result, indent=1) + "\n")
    args.out.write_text(page(result))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
