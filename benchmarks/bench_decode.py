"""Regenerate docs/results/decode.md: what the one decode-and-convert path changes, and what it costs.

    .venv/bin/python -m benchmarks.bench_decode

Every source gives its frames through :mod:`topoloc.datasets.decode`: decoded in the colour they
are stored in, then converted to grey once (``BGR2GRAY``), so a folder of JPEG files, a ROS bag's
raw ``bgr8`` topic of the same frames and a lossless video give the same pixels.  Before, files
were decoded straight to grey (``cv2.IMREAD_GRAYSCALE``: libjpeg's luma).  On every JPEG of the
gardens_point traverses this measures how the two greys differ (pixels, images) and the time of
each way of decoding (median of ``--repeats`` passes, as a ratio measured in the same run), and
what it did to a method: a bag-of-words map of ``day_left`` (vocabulary trained on
webcam_daynight/map) scores the ``day_right`` frames as read from their files and as the BGR
pixels a raw ``bgr8`` topic carries (the files decoded in colour), with the old grey (straight
from the file) and with the one path.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from datetime import UTC, datetime
from typing import Any

import cv2
import numpy as np

from benchmarks.common import GP, RESULTS, VOCAB_FOR_GP, machine_line, require_data
from topoloc.datasets.decode import check_image_size, decode_bytes, read_image
from topoloc.datasets.traverse import Traverse, load_traverse

TRAVERSES = ("day_left", "day_right", "night_right")


def _straight(buf: np.ndarray) -> np.ndarray:
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)


def measure(repeats: int) -> dict[str, Any]:
    """Differences and decode times over the gardens_point JPEGs."""
    rows = []
    for name in TRAVERSES:
        files = sorted((GP / name).glob("*.jpg"))
        bufs = [np.fromfile(f, np.uint8) for f in files]
        differing = images_differing = max_diff = 0
        pixels = 0
        for f, buf in zip(files, bufs, strict=True):
            old, new = _straight(buf), read_image(f)
            d = np.abs(old.astype(np.int16) - new)
            differing += int((d > 0).sum())
            images_differing += int(d.any())
            max_diff = max(max_diff, int(d.max()))
            pixels += d.size
        times: dict[str, list[float]] = {"straight_to_grey": [], "colour_then_bgr2gray": []}
        for _ in range(repeats):
            t0 = time.perf_counter()
            for f, buf in zip(files, bufs, strict=True):
                check_image_size(buf, f)  # as read_image did before decoding, and decode_bytes does
                _straight(buf)
            t1 = time.perf_counter()
            for f, buf in zip(files, bufs, strict=True):
                decode_bytes(buf, f)  # from the same bytes in memory as the old way, so only decoding is timed
            t2 = time.perf_counter()
            times["straight_to_grey"].append((t1 - t0) / len(files))
            times["colour_then_bgr2gray"].append((t2 - t1) / len(files))
        ms = {k: 1e3 * float(np.median(v)) for k, v in times.items()}
        rows.append({"traverse": name, "images": len(files), "size": list(_straight(bufs[0]).shape[::-1]),
                     "pixels_differing": differing / pixels, "images_differing": images_differing,
                     "max_grey_difference": max_diff, "ms_straight_to_grey": ms["straight_to_grey"],
                     "ms_colour_then_bgr2gray": ms["colour_then_bgr2gray"],
                     "time_ratio": ms["colour_then_bgr2gray"] / ms["straight_to_grey"]})
    return {"rows": rows}


def bow_agreement(vocab_words: int) -> dict[str, Any]:
    """Share of day_right frames given the same best place from the files and from raw BGR frames."""
    from topoloc.maps import Map

    folder = load_traverse(GP / "day_right")
    bgr = [read_image(f, gray=False) for f in folder.images]
    raw = Traverse.from_images(bgr, name="bgr8")  # what a raw bgr8 topic of these frames gives
    old = Traverse.from_images([_straight(np.fromfile(f, np.uint8)) for f in folder.images], name="old")
    m = Map.build(method="bow", tours=[GP / "day_left"], vocab_train=VOCAB_FOR_GP, vocab_words=vocab_words)
    best = {k: m.place_ids[np.argmax(m.similarity(t), axis=0)] for k, t in
            (("folder", folder), ("raw", raw), ("old", old))}
    return {"vocab_words": vocab_words, "n_queries": len(folder),
            "same_best_place_old": float(np.mean(best["old"] == best["raw"])),
            "same_best_place_now": float(np.mean(best["folder"] == best["raw"]))}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="timed passes over each traverse (median)")
    parser.add_argument("--vocab-words", type=int, default=10000, help="vocabulary of the bow map (map build's)")
    args = parser.parse_args(argv)
    require_data()
    result = {"machine": f"{machine_line()}, OpenCV {cv2.__version__}",
              "date": datetime.now(UTC).isoformat(timespec="seconds"), "load_average": list(os.getloadavg()),
              **measure(args.repeats), "bow": bow_agreement(args.vocab_words)}
    (RESULTS / "decode.json").write_text(json.dumps(result, indent=1) + "\n")
    text = [
        "# One decode path for every source\n\n",
        f"Generated by `.venv/bin/python -m benchmarks.bench_decode` ({result['machine']}, {result['date']}, "
        f"load average {result['load_average'][0]:.1f}); raw numbers: [decode.json](decode.json).\n\n",
        "Every frame, from a folder, a ROS bag (raw or compressed topic), a video or memory, is decoded in the "
        "colour it is stored in and converted to grey once (`BGR2GRAY`, `topoloc.datasets.decode`), so the same "
        "frame gives the same pixels and features from every source (`tests/datasets/sources/test_same_pixels.py` "
        "checks it bit for bit). Files used to be decoded straight to grey (`IMREAD_GRAYSCALE`, libjpeg's own "
        "luma), which a raw `bgr8` message cannot reproduce. On the gardens_point JPEGs the two greys differ "
        "as follows; the times are per image, the median of passes in the same run.\n\n",
        "| traverse | images | size | pixels differing | images differing | largest grey difference "
        "| ms straight to grey | ms colour then BGR2GRAY | ratio |\n",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n",
    ]
    for r in result["rows"]:
        text.append(f"| {r['traverse']} | {r['images']} | {r['size'][0]} x {r['size'][1]} | "
                    f"{100 * r['pixels_differing']:.2f}% | {r['images_differing']} | {r['max_grey_difference']} | "
                    f"{r['ms_straight_to_grey']:.2f} | {r['ms_colour_then_bgr2gray']:.2f} | "
                    f"{r['time_ratio']:.2f} |\n")
    bow = result["bow"]
    text.append(f"\nBag of words (`bow`, map `day_left`, vocabulary of {bow['vocab_words']} words trained on "
                f"webcam_daynight/map): of the {bow['n_queries']} `day_right` frames, the files read the old way "
                f"(straight to grey) and the same frames as raw `bgr8` pixels got the same best place for "
                f"{100 * bow['same_best_place_old']:.0f}%; with the one path, files and raw frames agree for "
                f"{100 * bow['same_best_place_now']:.0f}%.\n")
    text.append("\nThe colour decode is the price of one path; feature extraction of the same images takes tens "
                "of milliseconds each (`docs/results/maps.md`), so decoding stays a small part of it. Features "
                "cached under the old decoding are not reused: the decode version is part of the feature cache "
                "key.\n")
    (RESULTS / "decode.md").write_text("".join(text))
    print(f"wrote {RESULTS / 'decode.md'}")


if __name__ == "__main__":
    main()
