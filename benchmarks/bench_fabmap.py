"""Regenerate docs/results/fabmap.md: FAB-MAP and FAB-MAP 2.0 beside bow, and their speed.

    .venv/bin/python -m benchmarks.bench_fabmap

Accuracy runs go through `topoloc evaluate` (docs/results/runs/fabmap_*); the vocabulary
and the Chow-Liu model are trained on the other dataset (gardens_point runs: webcam_daynight
map images; webcam_daynight runs: gardens_point images), never on the evaluated images.
The `bow` rows are the runs of benchmarks/bench_bow.py (run it first). Speed: FAB-MAP 2.0
ms/query at 10,000 and 100,000 places, Bennett bail-out speed-up, and Chow-Liu training
time and memory at 10,000 words, all on synthetic Zipf-distributed bag-of-words data
(`topoloc.bench.fabmap_speed`).
"""

from __future__ import annotations

import json
import resource
from pathlib import Path

from benchmarks.common import (
    GP,
    GP_PAIRS,
    RESULTS,
    VOCAB_FOR_GP,
    VOCAB_FOR_WEBCAM,
    WEBCAM,
    WEBCAM_TOURS,
    gardens_section,
    report_table,
    require_data,
    run,
)
from topoloc.bench.fabmap_speed import bench_bailout, bench_chowliu, bench_fabmap2
from topoloc.methods.fab_map import FabMap2

#: Run-name suffix and ``--param`` of each score: the log-likelihood (default) and FAB-MAP's own confidence,
#: the posterior of Eq. 3, as a probability and as log-odds; every other setting, preprocessing included,
#: is the same in all three rows.
OUTPUTS: list[tuple[str, dict[str, str]]] = [("", {}), ("_posterior", {"output": "posterior"}),
                                             ("_logodds", {"output": "logodds"})]


def accuracy() -> tuple[list[Path], list[Path]]:
    runs = RESULTS / "runs"
    gp, wc = [], []
    for a, b in GP_PAIRS:
        for m in ("fabmap", "fabmap2"):
            for tag, p in OUTPUTS:
                gp.append(run(m, [GP / a], GP / b, runs / f"{m}{tag}_gp_{a}__{b}", vocab_train=VOCAB_FOR_GP,
                              tolerance="0:8", params=p))
        bow = runs / f"bow_gp_{a}__{b}"
        if (bow / "metrics.json").is_file():
            gp.append(bow)
    for m in ("fabmap", "fabmap2"):
        for tag, p in OUTPUTS:
            wc.append(run(m, [WEBCAM / "map" / "tour_1400"], WEBCAM / "queries", runs / f"{m}_webcam_tour1400{tag}",
                          vocab_train=VOCAB_FOR_WEBCAM, tolerance="0:0", params=p))
            wc.append(run(m, WEBCAM_TOURS, WEBCAM / "queries", runs / f"{m}_webcam_all_tours{tag}",
                          vocab_train=VOCAB_FOR_WEBCAM, tolerance="0:0", params=p))
    # The choice of default for several tours: one model per place (Eq. 11) against one per image.
    wc.append(run("fabmap2", WEBCAM_TOURS, WEBCAM / "queries", runs / "fabmap2_webcam_all_tours_merge",
                  vocab_train=VOCAB_FOR_WEBCAM, tolerance="0:0", params={"tours": "merge"}))
    for maps, query, tag in (((GP / "day_left", GP / "night_right"), GP / "day_right", "day"),
                             ((GP / "day_left", GP / "day_right"), GP / "night_right", "night")):
        for tours in ("separate", "merge"):
            for out, p in OUTPUTS:
                gp.append(run("fabmap2", list(maps), query, runs / f"fabmap2_gp_two_tours_{tag}_{tours}{out}",
                              vocab_train=VOCAB_FOR_GP, tolerance="0:8", params={"tours": tours, **p}))
    wc += [d for d in (runs / "bow_webcam_tour1400", runs / "bow_webcam_all_tours") if (d / "metrics.json").is_file()]
    return gp, wc


#: openFABMAP 2.0 on the development webcams with all 12 map tours (AUC, R@1), quoted from the
#: project's scorecard script (../shared/scorecard, row webcam_fabmap2); not measured here.
OPENFABMAP_WEBCAM = (0.80, 0.82)


def tours_choice(runs: Path) -> str:
    """The sentence that states the multi-tour default, written from the two webcam runs' metrics.json."""
    sep, mer = (json.loads((runs / f"fabmap2_webcam_all_tours{t}" / "metrics.json").read_text())
                for t in ("", "_merge"))
    better = "separate" if sep["recall_at_1"] >= mer["recall_at_1"] else "merge"
    default = FabMap2().tours
    verdict = "the better of the two there" if default == better else f"although `tours={better}` scores higher there"
    auc, r1 = OPENFABMAP_WEBCAM
    return (f"**Several map tours**: on webcam_daynight with all 12 tours `fabmap2` reaches R@1 "
            f"{sep['recall_at_1']:.3f} (AUC {sep['auc']:.3f}) with one model per image, a place scored by its best "
            f"image (`tours=separate`, openFABMAP's setting), against {mer['recall_at_1']:.3f} (AUC {mer['auc']:.3f}) "
            f"with one merged model per place (`tours=merge`); the default is `tours={default}`, {verdict}. "
            f"openFABMAP 2.0 on the same images reaches AUC {auc:.2f} / R@1 {r1:.2f} (its own vocabulary and "
            f"features; quoted from ../shared/scorecard): `tours=separate` is "
            f"{'at or above' if sep['recall_at_1'] >= r1 else 'below'} its R@1. " + _same_words(runs.parent))


def _same_words(results: Path) -> str:
    """What ``fabmap_openfabmap.json`` (benchmarks.bench_fabmap_openfabmap) found on the webcam words."""
    f = results / "fabmap_openfabmap.json"
    if not f.is_file():
        return "Run `benchmarks.bench_fabmap_openfabmap` for openFABMAP 2.0 on the same words."
    wc = next(r for r in json.loads(f.read_text())["results"] if r["workload"] == "webcam")
    return (f"On the same words (`fabmap_openfabmap.md`) openFABMAP 2.0 with each image its own location ranks the "
            f"same map image first on {100 * wc['same_best_image']:.1f}% of the webcam queries: R@1 "
            f"{wc['recall_at_1_ties_as_chance_openfabmap']:.3f} (openFABMAP) and "
            f"{wc['recall_at_1_ties_as_chance_fabmap2']:.3f} (fabmap2) counted as `evaluate` does, ties as chance; "
            f"{wc['recall_at_1_openfabmap']:.3f} and {wc['recall_at_1_fabmap2']:.3f} when a tie goes to the first "
            "image. ")


def speed() -> dict[str, object]:
    out: dict[str, object] = {}
    for n in (10_000, 100_000):
        out[f"fabmap2_{n}"] = bench_fabmap2(n_places=n)
        print(n, out[f"fabmap2_{n}"], flush=True)
    out["bailout"] = bench_bailout()
    print(out["bailout"], flush=True)
    out["chowliu"] = bench_chowliu(n_words=10_000)
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(out["chowliu"], flush=True)
    return out


def main() -> None:
    require_data()
    gp, wc = accuracy()
    s = speed()
    (RESULTS / "fabmap_speed.json").write_text(json.dumps(s, indent=2, default=float) + "\n")
    f2a, f2b, bo, cl = s["fabmap2_10000"], s["fabmap2_100000"], s["bailout"], s["chowliu"]
    assert isinstance(f2a, dict) and isinstance(f2b, dict) and isinstance(bo, dict) and isinstance(cl, dict)
    text = [
        "# FAB-MAP (`fabmap`, `fabmap2`)\n\n",
        "Generated by `.venv/bin/python -m benchmarks.bench_fabmap`; do not edit by hand. SIFT (at most 1000 per ",
        "image), 10,000-word vocabulary and Chow-Liu model trained on the other dataset; S = log p(Z|L_i) ",
        "(Chow-Liu, detector model p(z=1|e=0)=0.005, p(z=0|e=1)=0.61), and beside each such row the same run with ",
        "`output=posterior`, FAB-MAP's own confidence p(L_i|Z) of Eq. 3 (rows tagged `output=posterior`), and "
        "the same posterior as log-odds log p/(1-p) (`output=logodds`), which does not round to 1; every ",
        "row uses `evaluate`'s default preprocessing. With several map tours each map image ",
        "keeps its own model and a place scores its best image (`tours=separate`, the default; `tours=merge` ",
        "merges a place's images by Eq. 11, as the paper does: rows below). Raw speed numbers: ",
        "`fabmap_speed.json`; per query beside openFABMAP 2.0 on the same words: `fabmap_openfabmap.md` ",
        "(`benchmarks.bench_fabmap_openfabmap`).\n\n",
        tours_choice(RESULTS / "runs"), "\n\n",
        "## gardens_point (tolerance 0:8)\n\n",
        gardens_section(gp, "fabmap_gardens_point", "FAB-MAP on gardens_point (vocabulary: webcam_daynight/map)"),
        "\n## webcam_daynight (48 places, 976 queries, tolerance 0:0)\n\n",
        report_table(wc, RESULTS / "fabmap_webcam", "FAB-MAP on webcam_daynight (vocabulary: gardens_point)"),
        "\n![PR curves](fabmap_webcam/pr_curves.png)\n\n",
        "## Speed (synthetic Zipf bag-of-words, 10,000 words, ~300 words per image)\n\n",
        "| measurement | result |\n| --- | --- |\n",
        f"| FAB-MAP 2.0, 10,000 places | median {f2a['ms_per_query_median']:.2f} ms, p95 "
        f"{f2a['ms_per_query_p95']:.2f} ms per query (R@1 {f2a['recall_at_1']:.2f}) |\n",
        f"| FAB-MAP 2.0, 100,000 places | median **{f2b['ms_per_query_median']:.2f} ms**, p95 "
        f"{f2b['ms_per_query_p95']:.2f} ms per query (R@1 {f2b['recall_at_1']:.2f}); paper: 14 ms mean |\n",
        f"| Bennett bail-out, {bo['n_places']} places | {bo['speedup']:.1f}x faster than exhaustive "
        f"({bo['ms_bailout']:.2f} vs {bo['ms_exhaustive']:.2f} ms); {100 * bo['fraction_evaluated']:.2f}% of places "
        f"fully evaluated; same best place on {100 * bo['top1_agree']:.0f}% of queries |\n",
        f"| Chow-Liu training, {cl['n_words']} words, {cl['n_images']} images | {cl['seconds']:.1f} s, peak traced "
        f"memory {cl['peak_mb']:.0f} MiB |\n",
        f"\nPeak resident memory of the whole speed benchmark process: {s['peak_rss_mb']:.0f} MiB.\n",
    ]
    (RESULTS / "fabmap.md").write_text("".join(text))
    print(f"wrote {RESULTS / 'fabmap.md'}")


if __name__ == "__main__":
    main()
