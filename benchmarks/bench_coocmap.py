"""Regenerate docs/results/coocmap.md: Cooc-Map beside the other methods, ablations, and its speed.

    .venv/bin/python -m benchmarks.bench_coocmap [--only gardens|webcam|speed] [--page-only]

All accuracy numbers come from `topoloc evaluate` runs (docs/results/runs/coocmap_table_*).
Every table holds runs with the same preprocessing and the same map tours, so its rows
compare like with like:

- gardens_point, one map tour (the three pairs of the anchors): every method at its defaults
  (no `--param`, no `--preprocess`), beside the anchors measured on the same frames;
- gardens_point, two map tours (day_left + night_right -> day_right, day_left + day_right ->
  night_right): the same methods at their defaults;
- ablations of Cooc-Map on the two-tour pairs: the paper's own settings, `--preprocess clahe`
  (with bow under the same preprocessing) and the paper's II-F sequence matching (with bow
  under the same sequence stage and SeqSLAM's own sequence searches);
- webcam_daynight: the methods at their defaults with all 12 tours and with tour_1400 alone,
  Cooc-Map ablations, `--preprocess clahe` rows, and R@1 per hour of capture (the paper's
  Fig. 10 comparison) as a PNG.

Under each table, sentences written from the runs' metrics.json say where each row wins and
loses (`benchmarks.common.prose`). Vocabularies are trained on the other dataset. Speed:
`bench_coocmap` on a synthetic map of the paper's size (2,200 locations x 5 tours, 500
features per image, 10k words) -> coocmap_speed.json.

`--only PART` measures that part alone and re-renders the others from their existing runs
(and coocmap_speed.json); `--page-only` measures nothing.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.common import (
    GP,
    GP_PAIRS,
    RESULTS,
    VOCAB_FOR_GP,
    VOCAB_FOR_WEBCAM,
    WEBCAM,
    WEBCAM_TOURS,
    anchors_table,
    prose_for,
    report_table,
    require_data,
    run,
)
from topoloc._params import keyword_defaults
from topoloc.datasets.traverse import load_traverse
from topoloc.features.local import FeatureConfig
from topoloc.methods import get_method
from topoloc.methods.describe import describe_method

TWO_TOUR = [(("day_left", "night_right"), "day_right"), (("day_left", "day_right"), "night_right")]

#: (tag, method, --param) of the rows "at defaults"; ``fabmap2`` also with FAB-MAP's own confidence.
AT_DEFAULTS: list[tuple[str, str, dict[str, str]]] = [
    ("coocmap", "coocmap", {}),
    ("bow", "bow", {}),
    ("fabmap2", "fabmap2", {}),
    ("fabmap2_posterior", "fabmap2", {"output": "posterior"}),
    ("voting", "voting", {}),
    ("seqslam", "seqslam", {}),
]
#: Cooc-Map as the paper has it: equal spatial words (Sec. II-C), positions as extracted, the group size as score.
PAPER = {"spatial_tolerance": "0", "position_bits": "16", "confidence": "raw"}
CLAHE = ["--preprocess", "clahe"]
#: The paper's sequence matching (Sec. II-F): the forward search that allows acceleration.
SEQUENCE = 10
II_F = ["--sequence-mode", "acceleration"]


@dataclass(frozen=True)
class Table:
    """One table of the page: its heading, report folder (under docs/results), runs and prose."""

    heading: str
    folder: str
    title: str
    intro: str
    runs: list[Path]
    anchors: bool = False


class Runs:
    """The page's `evaluate` runs: each measured at most once (when ``measure``), else read back."""

    def __init__(self, folder: Path, *, measure: bool, part: str, methods: set[str] | None = None) -> None:
        self.folder, self.measure, self.part, self.methods = folder, measure, part, methods
        self.done: set[str] = set()

    def __call__(self, name: str, method: str, maps: Sequence[Path], query: Path, *, vocab: list[Path],
                 tolerance: str, params: dict[str, str] | None = None, options: list[str] | None = None,
                 sequence: int = 0) -> Path:
        out = self.folder / name
        if self.measure and name not in self.done and (self.methods is None or method in self.methods):
            # Methods without a vocabulary (voting, seqslam) would only train one for nothing.
            run(method, list(maps), query, out, vocab_train=vocab if get_method(method).uses_vocabulary else [],
                tolerance=tolerance, params=params, options=options, sequence=sequence)
            self.done.add(name)
        elif not (out / "metrics.json").is_file():
            raise SystemExit(f"no run {out}: measure it first (python -m benchmarks.bench_coocmap --only {self.part})")
        return out


def _gp(tag: str, maps: Sequence[str], query: str) -> str:
    return f"coocmap_table_{tag}_gp_{'+'.join(maps)}__{query}"


def gardens(runs: Runs, *, pairs: Sequence[tuple[str, str]] = GP_PAIRS,
            two_tour: Sequence[tuple[tuple[str, ...], str]] = TWO_TOUR) -> list[Table]:
    """The gardens_point tables (tolerance 0:8; vocabulary trained on webcam_daynight's map tours)."""

    def at(tag: str, method: str, maps: Sequence[str], query: str, params: dict[str, str] | None = None,
           options: list[str] | None = None, sequence: int = 0) -> Path:
        return runs(_gp(tag, maps, query), method, [GP / x for x in maps], GP / query, vocab=VOCAB_FOR_GP,
                    tolerance="0:8", params=params, options=options, sequence=sequence)

    one = [at(tag, m, [a], b, params=p) for a, b in pairs for tag, m, p in AT_DEFAULTS]
    paper_one = [x for a, b in pairs
                 for x in (at("coocmap", "coocmap", [a], b), at("coocmap_paper", "coocmap", [a], b, params=PAPER))]
    two: list[Path] = []
    paper: list[Path] = []
    clahe: list[Path] = []
    seq: list[Path] = []
    for maps, q in two_tour:
        two += [at(tag, m, maps, q, params=p) for tag, m, p in AT_DEFAULTS]
        paper += [at("coocmap", "coocmap", maps, q), at("coocmap_paper", "coocmap", maps, q, params=PAPER)]
        clahe += [at("coocmap_clahe", "coocmap", maps, q, options=CLAHE),
                  at("bow_clahe", "bow", maps, q, options=CLAHE)]
        seq += [at("coocmap_iif", "coocmap", maps, q, options=II_F, sequence=SEQUENCE),
                at("bow_iif", "bow", maps, q, options=II_F, sequence=SEQUENCE),
                at("seqslam", "seqslam", maps, q),
                at("seqslam_accel", "seqslam", maps, q, params={"search": "acceleration"})]
    paper_text = ", ".join(f"`{k}={v}`" for k, v in PAPER.items())
    defaults = keyword_defaults(get_method("coocmap"))
    return [
        Table("gardens_point, one map tour: every method at its defaults", "coocmap_gp_defaults_one_tour",
              "gardens_point, one map tour, defaults (vocabulary: webcam_daynight)",
              "Each method with no `--param` and no `--preprocess`, on the three pairs the anchors were "
              "measured on; `fabmap2 (output=posterior)` is FAB-MAP 2.0 with its own confidence, the "
              "posterior of Eq. 3, beside its default log-likelihood.\n\n", one, anchors=True),
        Table("gardens_point, two map tours: every method at its defaults", "coocmap_gp_defaults_two_tours",
              "gardens_point, two map tours, defaults (vocabulary: webcam_daynight)",
              "The same methods on maps of two tours. No anchor was measured with two map tours, so these rows "
              "are compared only with each other.\n\n", two),
        Table("Ablation: Cooc-Map at the paper's own settings (one map tour)", "coocmap_gp_paper_one_tour",
              "Cooc-Map, defaults and the paper's settings, one map tour (vocabulary: webcam_daynight)",
              f"The paper's settings are {paper_text}; the defaults are "
              + ", ".join(f"`{k}={defaults[k]!r}`" for k in PAPER) + " (why: the defaults section above). The "
              "prose compares both with the anchors of the first table.\n\n", paper_one),
        Table("Ablation: Cooc-Map at the paper's own settings (two map tours)", "coocmap_gp_paper_two_tours",
              "Cooc-Map, defaults and the paper's settings, two map tours (vocabulary: webcam_daynight)",
              "The same two settings on the two-tour maps.\n\n", paper),
        Table("Ablation: CLAHE before feature extraction (two map tours)", "coocmap_gp_clahe",
              "Cooc-Map and bow with --preprocess clahe (vocabulary: webcam_daynight)",
              "Every row here extracts features after `--preprocess clahe`; compare with the two-tour table "
              "above for the default preprocessing.\n\n", clahe),
        Table("Ablation: sequence matching (two map tours)", "coocmap_gp_sequence",
              "Sequence matching over 10 frames (vocabulary: webcam_daynight)",
              f"`seq {SEQUENCE} acceleration` is the paper's II-F sequence matching (`--sequence {SEQUENCE} "
              "--sequence-mode acceleration`) on top of each method's scores; `seqslam` searches sequences "
              "itself (constant velocity by default, `search=acceleration` the II-F forward path).\n\n", seq),
    ]


def webcam(runs: Runs) -> tuple[list[Table], list[Path]]:
    """The webcam_daynight tables (tolerance 0:0) and the runs of the per-hour plot."""
    q = WEBCAM / "queries"

    def at(name: str, method: str, maps: list[Path], params: dict[str, str] | None = None,
           options: list[str] | None = None) -> Path:
        return runs(f"coocmap_table_{name}_webcam", method, maps, q, vocab=VOCAB_FOR_WEBCAM, tolerance="0:0",
                    params=params, options=options)

    one = [WEBCAM / "map" / "tour_1400"]
    methods = [(t, m, p) for t, m, p in AT_DEFAULTS if m not in {"voting", "seqslam"}]
    every = [at(f"{t}_all_tours", m, WEBCAM_TOURS, params=p) for t, m, p in methods]
    single = [at(f"{t}_tour1400", m, one, params=p) for t, m, p in methods]
    ablation = [every[0], at("coocmap_nointerp_all_tours", "coocmap", WEBCAM_TOURS, params={"interpolate": "false"}),
                at("coocmap_paper_all_tours", "coocmap", WEBCAM_TOURS, params=PAPER)]
    clahe = [at("coocmap_clahe_all_tours", "coocmap", WEBCAM_TOURS, options=CLAHE),
             at("bow_clahe_all_tours", "bow", WEBCAM_TOURS, options=CLAHE)]
    tables = [
        Table("webcam_daynight, 12 map tours: methods at their defaults", "coocmap_webcam_defaults_all_tours",
              "webcam_daynight, 12 map tours, defaults (vocabulary: gardens_point)", "", every),
        Table("webcam_daynight, map tour_1400 alone: methods at their defaults",
              "coocmap_webcam_defaults_tour1400", "webcam_daynight, tour_1400, defaults (vocabulary: gardens_point)",
              "", single),
        Table("Ablation: Cooc-Map without II-E interpolation and at the paper's settings (12 map tours)",
              "coocmap_webcam_ablations", "Cooc-Map ablations on webcam_daynight (vocabulary: gardens_point)",
              "`interpolate=False` drops the virtual images between adjacent tours (Sec. II-E).\n\n", ablation),
        Table("Ablation: CLAHE before feature extraction (12 map tours)", "coocmap_webcam_clahe",
              "Cooc-Map and bow with --preprocess clahe on webcam_daynight (vocabulary: gardens_point)",
              "Every row here extracts features after `--preprocess clahe`.\n\n", clahe),
    ]
    return tables, [every[0], every[1], every[2], single[0], single[1]]


def per_hour_plot(run_dirs: list[Path], out: Path) -> None:
    """R@1 of each run by hour of capture of the query (tolerance 0:0: best place == true place)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from topoloc.evaluation.report import run_title

    query = load_traverse(WEBCAM / "queries")
    assert query.times is not None
    hours = ((query.times - query.times.astype("datetime64[D]")).astype("timedelta64[h]").astype(int))
    fig, ax = plt.subplots(figsize=(7.5, 4.2), dpi=110)
    for d in run_dirs:
        S, places, truth = (np.load(d / f) for f in ("S.npy", "places.npy", "queries.npy"))
        right = places[np.argmax(S, axis=0)] == truth
        r1 = [right[hours == h].mean() if (hours == h).any() else np.nan for h in range(24)]
        label = run_title(json.loads((d / "metrics.json").read_text())).replace("webcam_daynight/", "")
        ax.plot(range(24), r1, marker="o", markersize=3, label=label)
    ax.set_xlabel("hour of capture of the query")
    ax.set_ylabel("R@1")
    ax.set_xticks(range(0, 24, 2))
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.15), ncol=2, frameon=False)
    ax.set_title("webcam_daynight: R@1 by time of day", fontsize=9)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def render_tables(tables: list[Table], results: Path) -> str:
    """Each table with its PR curves, the anchors where they apply, and the generated prose."""
    text = []
    for t in tables:
        text += [f"### {t.heading}\n\n", t.intro, report_table(t.runs, results / t.folder, t.title),
                 f"\n![PR curves]({t.folder}/pr_curves.png)\n\n"]
        if t.anchors:
            text += ["Anchors on the same frames (one map tour):\n\n", anchors_table(), "\n"]
        text += ["Where each row wins and loses (written from the runs' metrics.json):\n\n", prose_for(t.runs), "\n"]
    return "".join(text)


def defaults_section(methods: Sequence[str]) -> str:
    """The defaults of the rows "at defaults", read from the code, and where each was chosen."""
    feats = FeatureConfig()
    lines = [
        "## Defaults, and the data they were chosen on\n\n",
        "Every default was chosen on the development split in `../shared/data` only: gardens_point "
        "Image000-099 (the first half of the route) and webcam_daynight's map tours (each camera's first 24 h) "
        "with its queries (the following days); the parts of both datasets held back for checking were never "
        "used. Rows \"at defaults\" pass no `--param` and no `--preprocess`: features "
        f"`{feats.method}`, at most {feats.max_features} per image, preprocessing `{feats.preprocess}` (compared "
        "with the alternatives by `benchmarks/bench_preprocess.py`, docs/results/preprocess.md), extracted at the "
        "smallest image size among a run's traverses (`--max-side auto`); vocabularies trained on the other "
        "dataset (their size: the `vocabulary` column under each table). Each method's defaults (`topoloc methods "
        "NAME`), with what its docstring says about "
        "where a default was chosen:\n\n",
    ]
    for name in methods:
        summary, params = describe_method(name)
        values = ", ".join(f"{p.name}={p.default!r}" for p in params)
        lines.append(f"- `{name}` ({summary.rstrip('.')}): {values}.\n")
        for p in params:
            if "chosen" in p.text.lower() or "development data" in p.text.lower():
                lines.append(f"  - `{p.name}`: {p.text}\n")
    return "".join(lines) + "\n"


def speed_section(results: Path, *, measure: bool) -> str:
    path = results / "coocmap_speed.json"
    if measure:
        from topoloc.bench.coocmap_speed import bench_coocmap

        speed = bench_coocmap()
        print(speed, flush=True)
        path.write_text(json.dumps(speed, indent=2, default=float) + "\n")
    elif not path.is_file():
        raise SystemExit(f"no {path}: measure it first (python -m benchmarks.bench_coocmap --only speed)")
    speed = json.loads(path.read_text())
    return "".join([
        "## Speed and memory at the paper's size (synthetic map, `topoloc bench coocmap`)\n\n",
        "| measurement | result |\n| --- | --- |\n",
        f"| map | {speed['locations']} locations x {speed['tours']} tours, {speed['features']} features per image, "
        f"{speed['n_words']} words, {speed['spatial_words']} spatial words |\n",
        f"| ms per localisation (default lazy bound-ordered II-D) | median **{speed['ms_per_query_median']:.1f}**, "
        f"p95 {speed['ms_per_query_p95']:.1f} |\n",
        f"| ms per localisation, paper's round-robin II-D | median {speed['ms_per_query_rounds_median']:.1f} |\n",
        f"| II-D speed-up over matching every location to completion | round-robin "
        f"{speed['speedup_vs_sequential']:.1f}x, best-first {speed['speedup_best_first']:.1f}x (time); "
        f"best matches identical: {speed['best_matches_agree']} |\n",
        f"| map memory | {speed['map_bytes'] / 1e6:.1f} MB, {speed['bytes_per_location']:.0f} bytes per location "
        f"(explicit (word, word, spatial word) keys would take {speed['explicit_keys_bytes_per_location']:.0f}) |\n",
        "\nPaper: 82 ms per localisation on a 20 km route (6 tours x ~2,200 images); about 80x from II-D. Raw: "
        "`coocmap_speed.json`.\n",
    ])


def page(gp: list[Table], wc: list[Table], speed: str, results: Path = RESULTS) -> str:
    return "".join([
        "# Cooc-Map (`coocmap`), the flagship\n\n",
        "Generated by `.venv/bin/python -m benchmarks.bench_coocmap`; do not edit by hand. In every table all rows "
        "have the same preprocessing and the same map tours. Several `--map` "
        "traverses are the tours of the map. The prose under each table is written by the script from the runs' "
        "metrics.json: single-tour rows against the best anchor of their pair, other rows only against the rows "
        "on the same maps.\n\n",
        defaults_section(list(dict.fromkeys(m for _, m, _ in AT_DEFAULTS))),
        "## gardens_point (tolerance 0:8)\n\n",
        render_tables(gp, results),
        "## webcam_daynight (48 places, 976 queries, tolerance 0:0)\n\n",
        render_tables(wc, results),
        "### R@1 by hour of capture (paper's Fig. 10 comparison)\n\n![R@1 by hour](coocmap_webcam_by_hour.png)\n\n",
        speed,
    ])


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", choices=("gardens", "webcam", "speed"),
                    help="measure this part alone; the others are re-rendered from their existing runs")
    ap.add_argument("--page-only", action="store_true", help="measure nothing; re-render the page")
    ap.add_argument("--methods", help="measure only the runs of these methods (comma-separated, e.g. after "
                    "changing one method's defaults); the others are read back")
    args = ap.parse_args(argv)
    methods = set(args.methods.split(",")) if args.methods else None
    require_data()
    folder = RESULTS / "runs"

    def measures(part: str) -> bool:
        return not args.page_only and args.only in (None, part)

    gp = gardens(Runs(folder, measure=measures("gardens"), part="gardens", methods=methods))
    wc, hourly = webcam(Runs(folder, measure=measures("webcam"), part="webcam", methods=methods))
    if measures("webcam"):  # the plot needs the runs' S.npy, which the repository does not keep
        per_hour_plot(hourly, RESULTS / "coocmap_webcam_by_hour.png")
    speed = speed_section(RESULTS, measure=measures("speed"))
    (RESULTS / "coocmap.md").write_text(page(gp, wc, speed))
    print(f"wrote {RESULTS / 'coocmap.md'}")


if __name__ == "__main__":
    main()
