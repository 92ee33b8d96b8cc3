"""What the default feature scale costs and saves: ``max_side`` "auto" (640 px) against full size (0).

    .venv/bin/python -m benchmarks.bench_feature_scale [--methods bow,coocmap] [--pairs gp_day] [--work DIR]

``max_side="auto"`` extracts features with every image's longer side capped at
640 px (:data:`topoloc.spec.parts.AUTO_MAX_SIDE`); gardens_point's day frames
(960 x 540) are downscaled, its night frames (640 x 360) are not.  For each
method whose map `localize` serves at camera rate (bow, fabmap, fabmap2,
coocmap, landmarks) and each gardens_point pair, one ``topoloc evaluate`` at
``--max-side 640`` and one at ``--max-side 0``, default parameters otherwise
(vocabulary trained on webcam_daynight/map), give AUC, R@100P and R@1 side by
side; and SIFT plus quantisation of 20 day_right frames on one thread give the
milliseconds per frame at each scale.  Writes ``docs/results/feature_scale.json``
and the "Feature scale" section of ``docs/results/performance.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import GP, METRICS, RESULTS, VOCAB_FOR_GP, machine_line, require_data, run, write_section
from topoloc.spec.parts import AUTO_MAX_SIDE

METHODS = ("bow", "fabmap", "fabmap2", "coocmap", "landmarks")
#: (map tours, query): the day pair, the night pair from the same map tour, and the two-tour night map.
PAIRS: dict[str, tuple[list[str], str]] = {
    "gp_day": (["day_left"], "day_right"),
    "gp_night_from_left": (["day_left"], "night_right"),
    "gp_night_2tours": (["day_left", "day_right"], "night_right"),
}
SIDES = (AUTO_MAX_SIDE, 0)
USES_VOCABULARY = {"bow", "fabmap", "fabmap2", "coocmap"}


def extraction_cost(n_images: int = 20) -> dict[str, Any]:
    """Mean processor ms per day_right frame of SIFT (default preprocessing) and of quantising it, per scale."""
    import cv2
    import faiss

    from topoloc.datasets.traverse import read_image
    from topoloc.features import FeatureConfig
    from topoloc.features.local import extract_features
    from topoloc.spec import VocabularySpec
    from topoloc.spec.setup import make_resources

    images = [read_image(p, gray=True) for p in sorted((GP / "day_right").glob("*.jpg"))[:n_images]]
    cv2.setNumThreads(1)  # one core's cost; localize runs one describing thread per core
    out: dict[str, Any] = {"images": len(images), "image_shape": list(images[0].shape)}
    # The webcam images the words are trained on are 320 px wide: the same words at either scale.
    res, _ = make_resources(FeatureConfig(max_side=AUTO_MAX_SIDE), VocabularySpec(train=tuple(VOCAB_FOR_GP)),
                            needs_vocabulary="the quantisation timing")
    voc = res.vocabulary
    faiss.omp_set_num_threads(1)
    configs = {side: FeatureConfig(max_side=side) for side in SIDES}
    times: dict[int, dict[str, list[float]]] = {side: {"f": [], "q": [], "n": []} for side in SIDES}
    for config in configs.values():
        voc.quantize(extract_features(images[0], config).descriptors)  # detector and index built before timing
    for img in images:
        for side, config in configs.items():  # the scales alternate, so a burst of load hits both alike
            # Processor time of this thread (OpenCV and faiss run on it alone): what the work costs,
            # whatever else shares the cores.
            t0 = time.thread_time()
            fs = extract_features(img, config)
            t1 = time.thread_time()
            voc.quantize(fs.descriptors)
            t2 = time.thread_time()
            times[side]["f"].append(1e3 * (t1 - t0))
            times[side]["q"].append(1e3 * (t2 - t1))
            times[side]["n"].append(len(fs))
    for side, t in times.items():
        out[str(side)] = {"ms_extract_mean": float(np.mean(t["f"])), "ms_quantise_mean": float(np.mean(t["q"])),
                          "features_mean": float(np.mean(t["n"]))}
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--pairs", default=",".join(PAIRS))
    ap.add_argument("--work", type=Path, default=None,
                    help="Keep the evaluate runs here (default: a temporary folder).")
    args = ap.parse_args(argv)
    require_data()
    methods = [m for m in args.methods.split(",") if m]
    pairs = [p for p in args.pairs.split(",") if p]
    result: dict[str, Any] = {
        "machine": machine_line(),
        "date": datetime.now(UTC).isoformat(timespec="seconds"), "load_before": list(os.getloadavg()),
        "cost": extraction_cost(), "runs": [],
    }
    print(json.dumps(result["cost"]), flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        for pair in pairs:
            maps, query = PAIRS[pair]
            for method in methods:
                row: dict[str, Any] = {"method": method, "pair": pair}
                for side in SIDES:
                    out = work / f"{method}_{pair}_{side}"
                    if not (out / "metrics.json").is_file():
                        run(method, [GP / t for t in maps], GP / query, out,
                            vocab_train=VOCAB_FOR_GP if method in USES_VOCABULARY else [], tolerance="0:8",
                            options=["--max-side", str(side)])
                    m = json.loads((out / "metrics.json").read_text())
                    row[str(side)] = {key: m[key] for _, key in METRICS} | {"ms_features": m["ms_features"]}
                result["runs"].append(row)
                print(json.dumps(row), flush=True)
    result["load_after"] = list(os.getloadavg())
    (RESULTS / "feature_scale.json").write_text(json.dumps(result, indent=1) + "\n")
    write_section(RESULTS / "performance.md", "feature-scale", render(result))
    print(f"wrote {RESULTS / 'feature_scale.json'} and the feature scale section of {RESULTS / 'performance.md'}")


def _worse(row: dict[str, Any]) -> list[str]:
    """The metrics where 640 px is below full size by more than the anchors' rounding."""
    small, full = row[str(AUTO_MAX_SIDE)], row["0"]
    return [name for name, key in METRICS
            if small[key] is not None and full[key] is not None and small[key] < full[key] - 0.005]


def render(r: dict[str, Any]) -> str:
    c = r["cost"]
    a, f = c[str(AUTO_MAX_SIDE)], c["0"]
    h, w = c["image_shape"]
    lines = [
        "## Feature scale: 640 px (the default) against full size\n\n",
        f"Generated by `.venv/bin/python -m benchmarks.bench_feature_scale` ({r['machine']}, {r['date']}, "
        f"load average {r['load_before'][0]:.1f} before and {r['load_after'][0]:.1f} after; raw numbers: "
        "[feature_scale.json](feature_scale.json)). `max_side=\"auto\"` caps every image's longer side at "
        f"{AUTO_MAX_SIDE} px; gardens_point's day frames ({w} x {h}) are downscaled, its night frames "
        "(640 x 360) are not.\n\n",
        f"Cost per day_right frame on one thread, in processor time ({c['images']} frames, SIFT with the default "
        "preprocessing, then quantised with the 10,000 words of webcam_daynight/map):\n\n",
        "| max_side | ms SIFT | ms quantisation | features per frame |\n| --- | --- | --- | --- |\n",
        f"| {AUTO_MAX_SIDE} | {a['ms_extract_mean']:.1f} | {a['ms_quantise_mean']:.1f} | {a['features_mean']:.0f} |\n",
        f"| 0 (full size) | {f['ms_extract_mean']:.1f} | {f['ms_quantise_mean']:.1f} | {f['features_mean']:.0f} |\n\n",
        "Quality with default parameters (`topoloc evaluate`, tolerance 0:8, vocabulary trained on "
        "webcam_daynight/map where the method uses one); AUC / R@100P / R@1:\n\n",
        f"| method | pair | {AUTO_MAX_SIDE} px | full size | 640 px lower by more than 0.005 in |\n",
        "| --- | --- | --- | --- | --- |\n",
    ]
    losses = []
    for row in r["runs"]:
        vals = [" / ".join(f"{row[s][key]:.3f}" if row[s][key] is not None else "-" for _, key in METRICS)
                for s in (str(AUTO_MAX_SIDE), "0")]
        worse = _worse(row)
        if worse:
            losses.append(f"{row['method']} on {row['pair']} ({', '.join(worse)})")
        lines.append(f"| {row['method']} | {row['pair']} | {vals[0]} | {vals[1]} | {', '.join(worse) or '-'} |\n")
    lines.append("\nPairs: " + "; ".join(f"`{k}` = {' + '.join(v[0])} -> {v[1]}" for k, v in PAIRS.items()) + ". ")
    lines.append("640 px loses on: " + "; ".join(losses) + ".\n" if losses
                 else "640 px loses on none of these rows.\n")
    return "".join(lines)


if __name__ == "__main__":
    main()
