"""Regenerate docs/results/default_vocabulary.md: what the default vocabulary costs, per method.

    .venv/bin/python -m benchmarks.bench_default_vocab [--pairs gp_day gp_night webcam]
        [--methods bow fabmap fabmap2 coocmap landmarks] [--page-only]

A first run needs no ``--vocab``/``--vocab-train`` (issue #27).  Two candidates for what it uses
instead, against today's practice, each evaluated with ``topoloc evaluate`` (one process per run,
default settings otherwise) on the development data:

* ``separate`` -- today's practice and the papers': ``--vocab-train`` on images apart from the
  evaluation data (webcam_daynight/map for gardens_point, gardens_point for webcam_daynight);
* ``map tours`` -- no vocabulary option: the default, trained on the map's own tours
  (``topoloc.spec.setup.tours_vocabulary``, as RTAB-Map does);
* ``shippable`` -- ``--vocab-train`` on the only development images whose licence allows shipping
  a vocabulary trained on them in the package: rtabmap_loop (BSD-3-Clause) and corridor (MIT).
  This is the vocabulary a shipped default would be; it is trained here, not shipped.

The pairs are those of ``benchmarks.common.PAIRS``: gardens_point day_left -> day_right and
day_right -> night_right (tolerance 0:8) and webcam_daynight's 12 map tours -> queries (0:0).
Runs are written under docs/results/runs/defvocab_*; each (pair, method, source) is stored in
docs/results/default_vocabulary.json as it finishes, so the benchmark can be run in parts
(``--pairs``, ``--methods``) and the page shows what has been measured.
``--page-only`` rewrites the page from the JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from benchmarks.common import DATA, PAIRS, RESULTS, require_data, run

METHODS = ("bow", "fabmap", "fabmap2", "coocmap", "landmarks")
DEFAULT_PAIRS = ("gp_day", "gp_night", "webcam")
SHIPPABLE = [DATA / "rtabmap_loop", DATA / "corridor"]
SOURCES = ("separate", "map tours", "shippable")
JSON = RESULTS / "default_vocabulary.json"
PAGE = RESULTS / "default_vocabulary.md"


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def measure(pair: str, method: str, source: str) -> dict[str, Any]:
    """One ``topoloc evaluate`` run; its metrics that the page shows."""
    maps, query, separate, tolerance = PAIRS[pair]
    train = {"separate": separate, "map tours": [], "shippable": SHIPPABLE}[source]
    out = RESULTS / "runs" / f"defvocab_{pair}_{method}_{source.replace(' ', '_')}"
    load = _load()
    t0 = time.perf_counter()
    started = datetime.now(UTC).replace(microsecond=0)
    run(method, list(maps), query, out, vocab_train=list(train), tolerance=tolerance)
    m = json.loads((out / "metrics.json").read_text())
    voc = m["run"]["vocabulary"]
    return {"pair": pair, "method": method, "source": source, "auc": m["auc"], "recall_at_1": m["recall_at_1"],
            "recall_at_100_precision": m["recall_at_100_precision"],
            "vocabulary_seconds": m["run"].get("vocabulary_seconds", 0.0), "vocabulary_used": bool(voc.get("used")),
            # A vocabulary made in this run (not loaded from the cache): its k-means time is the first run's cost.
            "vocabulary_trained_this_run": "created" in voc and datetime.fromisoformat(voc["created"]) >= started,
            "kmeans_seconds": voc.get("train_seconds"), "vocabulary_n_descriptors": voc.get("n_descriptors"),
            "vocabulary_images": voc.get("n_images"), "fit_seconds": m["run"].get("fit_seconds"),
            "wall_seconds": round(time.perf_counter() - t0, 1), "load_before": load, "load_after": _load(),
            "run": str(out.relative_to(RESULTS))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", nargs="+", default=list(DEFAULT_PAIRS), choices=sorted(PAIRS))
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--sources", nargs="+", default=list(SOURCES), choices=SOURCES)
    parser.add_argument("--page-only", action="store_true", help="rewrite the page from the JSON")
    args = parser.parse_args()
    data: dict[str, Any] = json.loads(JSON.read_text()) if JSON.is_file() else {"rows": []}
    if not args.page_only:
        require_data()
        for pair in args.pairs:
            for method in args.methods:
                for source in args.sources:
                    row = measure(pair, method, source)
                    data["rows"] = [r for r in data["rows"] if (r["pair"], r["method"], r["source"])
                                    != (pair, method, source)] + [row]
                    data.update({"machine": f"{platform.machine()}, {os.cpu_count()} cores, "
                                            f"Python {platform.python_version()}",
                                 "date": datetime.now(UTC).isoformat(timespec="seconds")})
                    JSON.write_text(json.dumps(data, indent=2) + "\n")
    PAGE.write_text(render(data))
    print(f"wrote {PAGE}")


def _cell(r: dict[str, Any] | None) -> str:
    return "not measured" if r is None else f"{r['auc']:.3f} / {r['recall_at_1']:.3f}"


def _delta(r: dict[str, Any] | None, base: dict[str, Any] | None) -> str:
    if r is None or base is None:
        return ""
    return f"{r['auc'] - base['auc']:+.3f} / {r['recall_at_1'] - base['recall_at_1']:+.3f}"


def _used(r: dict[str, Any]) -> bool:
    """Whether the run used a vocabulary (rows stored before the field was recorded: from its metrics.json)."""
    if "vocabulary_used" in r:
        return bool(r["vocabulary_used"])
    metrics = RESULTS / r["run"] / "metrics.json"
    return not metrics.is_file() or bool(json.loads(metrics.read_text())["run"]["vocabulary"].get("used"))


def render(data: dict[str, Any]) -> str:
    # A method that uses no vocabulary (its runs say so) scores alike whatever the source: left out.
    skipped = sorted({r["method"] for r in data["rows"] if not _used(r)})
    rows = {(r["pair"], r["method"], r["source"]): r for r in data["rows"] if r["method"] not in skipped}
    loads = [x for r in data["rows"] for x in (r["load_before"], r["load_after"])]
    lines = [
        "# Default vocabulary: what a first run without `--vocab-train` costs\n\n",
        "Generated by `.venv/bin/python -m benchmarks.bench_default_vocab` (raw numbers in "
        "`default_vocabulary.json`, runs under `runs/defvocab_*`); do not edit by hand. "
        f"Machine: {data.get('machine', '?')}; last run {data.get('date', '?')}",
        f"; 1-minute load average between {min(loads)} and {max(loads)} during the runs (the machine may be "
        "shared: the seconds are noisy).\n\n" if loads else ".\n\n",
        "Each cell is **AUC / R@1** of `topoloc evaluate` with default settings (SIFT, 10,000 words), on the "
        "development data only. Vocabulary sources: **separate** = `--vocab-train` on other images (today's "
        "practice: webcam_daynight/map for gardens_point, gardens_point for webcam_daynight); **map tours** = "
        "no vocabulary option, the default: trained on the map's own tours; **shippable** = `--vocab-train "
        "rtabmap_loop corridor`, the only development images whose licence (BSD-3-Clause, MIT) would allow "
        "shipping a vocabulary trained on them in the package. Δ = that source minus separate.\n\n",
    ]
    pairs = [p for p in DEFAULT_PAIRS if any(k[0] == p for k in rows)]
    for pair in pairs:
        maps, query, separate, tolerance = PAIRS[pair]
        where = (f"{' + '.join(Path(m).name for m in maps) if len(maps) <= 2 else f'{len(maps)} map tours'}"
                 f" -> {Path(query).name}")
        lines += [f"## {Path(query).parent.name if pair != 'webcam' else 'webcam_daynight'}: {where} "
                  f"(tolerance {tolerance}; separate = {', '.join(str(Path(s).relative_to(DATA)) for s in separate)})"
                  "\n\n",
                  "| method | separate | map tours (default) | Δ map tours | shippable | Δ shippable |\n",
                  "| --- | --- | --- | --- | --- | --- |\n"]
        for method in METHODS:
            got = [rows.get((pair, method, s)) for s in SOURCES]
            if not any(got):
                continue
            sep, own, ship = got
            lines.append(f"| {method} | {_cell(sep)} | {_cell(own)} | {_delta(own, sep)} | {_cell(ship)} | "
                         f"{_delta(ship, sep)} |\n")
        lines.append("\n")
    trained = [r for r in data["rows"] if r["vocabulary_trained_this_run"]]
    if trained:
        lines += ["## Training time of the vocabularies (first run; later runs load them from the cache)\n\n",
                  "| pair | source | images | descriptors | k-means s | vocabulary s (features + k-means) | "
                  "load average |\n| --- | --- | --- | --- | --- | --- | --- |\n"]
        for r in trained:
            lines.append(f"| {r['pair']} | {r['source']} | {r['vocabulary_images']} | "
                         f"{r['vocabulary_n_descriptors']:,} | {r['kmeans_seconds']:.0f} | "
                         f"{r['vocabulary_seconds']:.0f} | {r['load_before']} |\n")
        lines.append("\n")
    if skipped:
        what = "Method" if len(skipped) == 1 else "Methods"
        lines.append(f"{what} {_and_words(skipped)}: no visual vocabulary used (the runs record none), so left "
                     "out of the tables; a first run needs none.\n\n")
    lines += _summary(rows, pairs)
    lines += _verdict(rows, pairs)
    return "".join(lines)


def _and_words(words: list[str]) -> str:
    return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " and " + words[-1]


def _verdict(rows: dict[tuple[str, str, str], dict[str, Any]], pairs: list[str]) -> list[str]:
    """Which candidate the numbers above favour, counted over the measured cells (written from the data)."""
    text = []
    for source in ("map tours", "shippable"):
        cells = [(rows[(p, m, source)], rows[(p, m, "separate")]) for p in pairs for m in METHODS
                 if (p, m, source) in rows and (p, m, "separate") in rows]
        if cells:
            auc_up = sum(a["auc"] >= b["auc"] for a, b in cells)
            r1_up = sum(a["recall_at_1"] >= b["recall_at_1"] for a, b in cells)
            text.append(f"**{source}** reaches at least the AUC of a separate vocabulary in {auc_up} of "
                        f"{len(cells)} measured (pair, method) cells and at least its R@1 in {r1_up}")
    if not text:
        return []
    where = ", ".join(pairs)
    return [f"{'; '.join(text)}. The default of `map build`, `evaluate` and `slam` without `--vocab`/"
            f"`--vocab-train` is the vocabulary trained on the map's own tours, chosen on these development "
            f"pairs ({where}). The results pages keep training on separate images, as the papers do.\n"]


def _summary(rows: dict[tuple[str, str, str], dict[str, Any]], pairs: list[str]) -> list[str]:
    """Mean Δ AUC / R@1 of each candidate over the measured (pair, method) cells, per method."""
    out = ["## Summary: mean Δ against separate over the measured pairs\n\n",
           "| method | map tours Δ AUC / Δ R@1 | shippable Δ AUC / Δ R@1 | pairs |\n| --- | --- | --- | --- |\n"]
    for method in METHODS:
        cells = []
        n = 0
        for source in ("map tours", "shippable"):
            d = [(rows[(p, method, source)], rows[(p, method, "separate")]) for p in pairs
                 if (p, method, source) in rows and (p, method, "separate") in rows]
            n = max(n, len(d))
            cells.append("" if not d else
                         f"{sum(a['auc'] - b['auc'] for a, b in d) / len(d):+.3f} / "
                         f"{sum(a['recall_at_1'] - b['recall_at_1'] for a, b in d) / len(d):+.3f}")
        if n:
            out.append(f"| {method} | {cells[0]} | {cells[1]} | {n} |\n")
    return [*out, "\n"]


if __name__ == "__main__":
    main()
