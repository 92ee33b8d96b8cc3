"""``topoloc map build|add|info|calibrate``, ``topoloc localize`` and ``topoloc cache info|clean``."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Annotated, Any

import typer

from topoloc.cli.app import (
    FeaturesOption,
    MaxFeaturesOption,
    PreprocessOption,
    SchedulerOption,
    SchedulerTimeoutOption,
    _parse_params,
    _sequence_length,
    app,
    handle_errors,
    open_executor,
)
from topoloc.cli.progress import rich_progress
from topoloc.cli.recordings import EveryMOption, EverySOption, PoseTopicOption, TopicOption
from topoloc.errors import TopolocError, input_error

log = logging.getLogger(__name__)

map_app = typer.Typer(help="Saved maps: build once from tours, add tours later, inspect, calibrate.",
                      no_args_is_help=True)
app.add_typer(map_app, name="map")

TourOption = Annotated[list[Path], typer.Option(
    "--map", help="Tour of the map (repeatable): a folder, a ROS bag (--topic) or a video.")]
CacheOption = Annotated[Path | None, typer.Option(help="Feature/vocabulary cache folder.")]


def _check_out_file(path: Path) -> None:
    from topoloc.io.dirs import check_output_file

    check_output_file(path)


def _feature_config(features: str, max_features: int, max_side: str, preprocess: str,
                    tours: list[Any]) -> Any:
    from topoloc.features import FeatureConfig
    from topoloc.maps.map import auto_max_side

    text = str(max_side).strip().lower()
    if text == "auto":
        side = auto_max_side(tours)
    else:
        try:
            side = int(text)
        except ValueError:
            raise TopolocError(f"--max-side must be 'auto' or a number of pixels, got {max_side!r}") from None
    return FeatureConfig(method=features, max_features=max_features, max_side=side, preprocess=preprocess)


@map_app.command("build")
@handle_errors
def map_build(
    method: Annotated[str, typer.Option(help="Method name (see `topoloc methods`).")],
    map: TourOption,
    out: Annotated[Path, typer.Option(help="Map file to write (.tlm).")],
    vocab: Annotated[Path | None, typer.Option(help="Vocabulary file (embedded in the map).")] = None,
    vocab_train: Annotated[
        list[Path] | None, typer.Option("--vocab-train", help="Folders to train the vocabulary on (repeatable).")
    ] = None,
    vocab_words: Annotated[int, typer.Option(help="Words when training with --vocab-train.")] = 10000,
    param: Annotated[list[str] | None, typer.Option(help="Method parameter KEY=VALUE (repeatable).")] = None,
    features: FeaturesOption = "sift",
    max_features: MaxFeaturesOption = 1000,
    max_side: Annotated[str, typer.Option(
        help="Downscale images to this longer side; 'auto' = the smallest among the map's tours "
             "(queries are then described at the map's scale).")] = "auto",
    preprocess: PreprocessOption = "auto",
    cache_dir: CacheOption = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars.")] = False,
    topic: TopicOption = None,
    every_s: EverySOption = None,
    every_m: EveryMOption = None,
    pose_topic: PoseTopicOption = None,
    shards: Annotated[int, typer.Option(
        help="Build the map as this many partial models of place ranges, one task each, merged into the "
                    "same map as a one-piece build (docs/map_shards.md).")] = 1,
    scheduler: SchedulerOption = None,
    scheduler_timeout: SchedulerTimeoutOption = None,
) -> None:
    """Build a map from one or more tours and save it in one file."""
    from topoloc.cli.recordings import load_tours
    from topoloc.evaluation.prepare import build_method
    from topoloc.maps import Map

    _check_out_file(out)
    if vocab is not None and vocab_train:
        raise TopolocError("pass either --vocab or --vocab-train, not both")
    tours = load_tours(list(map), topic, every_s, every_m, pose_topic)
    params = build_method(method, _parse_params(param or [])).get_params()  # checks names and types first
    config = _feature_config(features, max_features, max_side, preprocess, tours)
    t0 = time.perf_counter()
    with open_executor(scheduler, scheduler_timeout) as executor, rich_progress(not quiet) as progress:
        m = Map.build(executor=executor,
                      method=method, tours=tours, params=params, vocabulary=vocab, vocab_train=list(vocab_train or []),
                      vocab_words=vocab_words, features=config, cache_dir=cache_dir, progress=progress,
                      shards=shards)
    m.save(out)
    info = m.info()
    typer.echo(json.dumps({"out": str(out), "bytes": info["bytes"], "method": info["method"],
                           "places": info["places"], "tours": [t["name"] for t in m.tours],
                           "seconds": round(time.perf_counter() - t0, 2)}))


@map_app.command("add")
@handle_errors
def map_add(
    map_file: Annotated[Path, typer.Argument(help="Map file to extend (rewritten atomically).")],
    tour: Annotated[Path, typer.Argument(help="Tour to add: a folder, a ROS bag (--topic) or a video.")],
    vocab: Annotated[Path | None, typer.Option(help="Must be the map's vocabulary when given.")] = None,
    features: Annotated[str | None, typer.Option(help="Must be the map's when given.")] = None,
    max_features: Annotated[int | None, typer.Option(help="Must be the map's when given.")] = None,
    preprocess: Annotated[str | None, typer.Option(help="Must be the map's when given.")] = None,
    cache_dir: CacheOption = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars.")] = False,
    topic: TopicOption = None,
    every_s: EverySOption = None,
    every_m: EveryMOption = None,
    pose_topic: PoseTopicOption = None,
    scheduler: SchedulerOption = None,
    scheduler_timeout: SchedulerTimeoutOption = None,
) -> None:
    """Add a tour to a saved map without rebuilding it from the earlier images."""
    from topoloc.cli.recordings import load_tours
    from topoloc.maps import Map
    from topoloc.vocabulary import Vocabulary
    from topoloc.vocabulary.vocab import vocabulary_fingerprint

    m = Map.load(map_file)
    _check_out_file(map_file)
    given = {"features": features, "max_features": max_features, "preprocess": preprocess}
    for key, value in given.items():
        have = getattr(m.features, "method" if key == "features" else key)
        if value is not None and str(value).lower() != str(have).lower():
            raise input_error(f"--{key.replace('_', '-')} {value} differs from the map's {have}", map_file)
    if vocab is not None:
        other = vocabulary_fingerprint(Vocabulary.load(vocab))
        if m.vocabulary is None or other != vocabulary_fingerprint(m.vocabulary):
            raise input_error(f"vocabulary {vocab} is not the one this map was built with", map_file)
    t = load_tours([tour], topic, every_s, every_m, pose_topic)[0]
    with open_executor(scheduler, scheduler_timeout) as executor, rich_progress(not quiet) as progress:
        m.add_tour(t, cache_dir=cache_dir, progress=progress, executor=executor)
    m.save(map_file)
    typer.echo(json.dumps({"out": str(map_file), "places": len(m.place_ids),
                           "tours": [x["name"] for x in m.tours]}))


@map_app.command("info")
@handle_errors
def map_info(
    map_file: Annotated[Path, typer.Argument(help="Map file.")],
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object.")] = False,
) -> None:
    """Method, parameters, places, tours, vocabulary, feature settings, calibration and size of a map."""
    from topoloc.maps import Map

    info = Map.load(map_file).info()
    if as_json:
        typer.echo(json.dumps(info, default=str))
        return
    for key, value in info.items():
        if key == "tours":
            typer.echo(f"tours: {len(value)}")
            for t in value:
                when = f", {t['start']} .. {t['end']}" if t.get("start") else ""
                typer.echo(f"  - {t['name']}: {t['n_images']} images, {t['n_places']} places{when} ({t['root']})")
        else:
            typer.echo(f"{key}: {json.dumps(value, default=str) if isinstance(value, dict | list) else value}")


@map_app.command("calibrate")
@handle_errors
def map_calibrate(
    map_file: Annotated[Path, typer.Argument(help="Map file (rewritten atomically with the threshold).")],
    query: Annotated[Path, typer.Option(help="A labelled tour (places.csv or natural order) not in the map.")],
    precision: Annotated[float, typer.Option(help="Precision the accepted localisations must reach.")] = 0.99,
    tolerance: Annotated[str, typer.Option(help="Ground-truth tolerance HARD:SOFT in place ids.")] = "0:8",
    tolerance_m: Annotated[
        str | None, typer.Option("--tolerance-m", help="Tolerance HARD:SOFT in metres (needs x,y).")] = None,
    cache_dir: CacheOption = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars.")] = False,
    topic: TopicOption = None,
    every_s: EverySOption = None,
    every_m: EveryMOption = None,
    pose_topic: PoseTopicOption = None,
) -> None:
    """Choose the score threshold that reaches --precision on a labelled tour and store it in the map."""
    from topoloc.cli.recordings import load_tours
    from topoloc.datasets.groundtruth import ground_truth_from_places, ground_truth_from_xy, parse_tolerance
    from topoloc.maps import Map

    if not 0 < precision <= 1:
        raise TopolocError(f"--precision must be in (0, 1], got {precision}")
    hard, soft = parse_tolerance(tolerance_m if tolerance_m is not None else tolerance)
    m = Map.load(map_file)
    _check_out_file(map_file)
    q = load_tours([query], topic, every_s, every_m, pose_topic)[0]
    if tolerance_m is not None:
        if q.xy is None:
            raise input_error("--tolerance-m needs x,y columns in places.csv", q.root)
        gt = ground_truth_from_xy(m.place_xy, q.xy, hard, soft)
    else:
        gt = ground_truth_from_places(m.place_ids, q.places, hard, soft)
    if not gt.hard.any():
        raise input_error("calibration tour has no ground truth in this map (no query place is a map place)",
                          query)
    with rich_progress(not quiet) as progress:
        S = m.recognizer.similarity(q, resources=m._resources(cache_dir=cache_dir, progress=progress))
    cal = m.calibrate(S, gt, precision=precision, query=str(query))
    m.save(map_file)
    typer.echo(json.dumps(cal))


@app.command()
@handle_errors
def localize(
    map_file: Annotated[Path, typer.Argument(help="Map file (topoloc map build).")],
    inputs: Annotated[list[Path], typer.Argument(
        help="Image files or folders, ROS bags (.bag, rosbag2 folders; --topic) or videos, in order.")],
    out: Annotated[Path, typer.Option(help="JSON lines file, one line per frame, written as it goes.")],
    top_k: Annotated[int, typer.Option(help="Places listed per frame.")] = 5,
    sequence: Annotated[int | None, typer.Option(
        help="Match each frame with the N >= 1 before it, online (off when not given).")] = None,
    sequence_mode: Annotated[str, typer.Option(help="constant (SeqSLAM) or acceleration (Cooc-Map II-F).")]
    = "constant",
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
    topic: TopicOption = None,
    every_s: EverySOption = None,
    every_m: EveryMOption = None,
    pose_topic: PoseTopicOption = None,
    scheduler: SchedulerOption = None,
    scheduler_timeout: SchedulerTimeoutOption = None,
) -> None:
    """Localise new images against a saved map: place, score, accepted, top places (and x, y) per frame.

    With --scheduler the frames are described and scored in batches by the Dask workers (which open the
    map file: it must be on a file system they share); the lines are the same, in the same order.
    """
    from topoloc.cli.recordings import localize_frames
    from topoloc.maps import Map

    m = Map.load(map_file)
    if m.threshold is None:
        # For loop closure an accepted false match breaks the map: say so before the first frame.
        log.warning("%s is not calibrated: every frame is marked accepted; run `topoloc map calibrate %s "
                    "--query FOLDER` on a tour with ground truth to set the acceptance threshold",
                    map_file, map_file)
    total, frames = localize_frames(list(inputs), topic=topic, every_s=every_s, every_m=every_m,
                                    pose_topic=pose_topic)
    _check_out_file(out)
    loc = m.localizer(top_k=top_k, sequence=_sequence_length(sequence), sequence_mode=sequence_mode)
    t0 = time.perf_counter()
    out.parent.mkdir(parents=True, exist_ok=True)
    # Written line by line: a run that is stopped keeps every frame done so far.
    with open_executor(scheduler, scheduler_timeout) as executor, open(out, "w", encoding="utf-8") as fh, \
            rich_progress(not quiet) as progress:
        advance = progress(f"localize ({m.recognizer.name})", total)
        decode_s = 0.0
        if executor.name != "local":  # batches of frames scored on the cluster, lines in frame order
            from topoloc.maps.batch import localize_on

            for line, seconds in localize_on(executor, loc, frames):
                decode_s += seconds
                fh.write(json.dumps(line) + "\n")
                fh.flush()
                advance(1)
        while executor.name == "local":  # bags and videos are streamed: one frame decoded at a time
            t1 = time.perf_counter()
            item = next(frames, None)
            decode_s += time.perf_counter() - t1
            if item is None:
                break
            name, time_s, frame = item
            fh.write(json.dumps(loc.step(frame, name=name, time_s=time_s)) + "\n")
            fh.flush()
            advance(1)
    wall = time.perf_counter() - t0
    n = max(loc.frames, 1)
    feat_ms, match_ms = sum(loc.ms_features) / n, sum(loc.ms_matching) / n
    # Features include decoding the image, as evaluate's ms_features does.
    features_ms = feat_ms + 1e3 * decode_s / n
    summary = {"out": str(out), "frames": loc.frames, "fps": round(loc.frames / wall, 2) if wall else None,
               "fps_without_features": round(1e3 / match_ms, 2) if match_ms else None,
               "ms_features_mean": round(features_ms, 2), "ms_matching_mean": round(match_ms, 2),
               "ms_overhead_mean": round(1e3 * wall / n - features_ms - match_ms, 2),
               "calibrated": m.threshold is not None}
    typer.echo(json.dumps(summary))


cache_app = typer.Typer(help="The feature and vocabulary cache (~/.cache/topoloc or TOPOLOC_CACHE_DIR).",
                        no_args_is_help=True)
app.add_typer(cache_app, name="cache")


@cache_app.command("info")
@handle_errors
def cache_info(
    cache_dir: CacheOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object.")] = False,
) -> None:
    """Files and bytes in each part of the cache, and the feature stores of each feature setting."""
    from topoloc.features.cache import cache_usage, default_cache_dir
    from topoloc.features.store import store_usage

    usage = cache_usage(cache_dir)
    stores = store_usage(cache_dir)
    per_setting: dict[str, dict[str, int]] = {}
    for st in stores:
        agg = per_setting.setdefault(st["settings"], {"traverses": 0, "images": 0, "bytes": 0})
        agg["traverses"] += 1
        agg["images"] += st["images"]
        agg["bytes"] += st["bytes"]
    if as_json:
        typer.echo(json.dumps({"cache_dir": str(cache_dir or default_cache_dir()), **usage,
                               "feature_stores": per_setting, "stores": stores}))
        return
    typer.echo(f"cache: {cache_dir or default_cache_dir()}")
    for part, u in usage.items():
        typer.echo(f"  {part}: {u['files']} files, {u['bytes'] / 2**20:.1f} MiB")
    if per_setting:
        typer.echo("feature stores (one per traverse and setting):")
    for key, agg in per_setting.items():
        typer.echo(f"  {key}: {agg['traverses']} traverses, {agg['images']} images, {agg['bytes'] / 2**20:.1f} MiB")


@cache_app.command("clean")
@handle_errors
def cache_clean(
    cache_dir: CacheOption = None,
    max_size: Annotated[str | None, typer.Option(help="Keep at most this much, the most recently used (500M, 2G).")]
    = None,
    older_than: Annotated[float | None, typer.Option(help="Remove entries not used for this many days.")] = None,
    all_: Annotated[bool, typer.Option("--all", help="Remove everything.")] = False,
) -> None:
    """Remove cache entries, least recently used first: whole feature stores and files (computed again when needed)."""
    from topoloc.features.cache import clean_cache, parse_size

    if not all_ and max_size is None and older_than is None:
        raise TopolocError("say what to remove: --max-size SIZE, --older-than DAYS or --all")
    if older_than is not None and older_than < 0:
        raise TopolocError(f"--older-than must be >= 0 days, got {older_than}")
    limit = parse_size(max_size) if max_size is not None else None
    res = clean_cache(cache_dir, max_bytes=limit, older_than_s=None if older_than is None else older_than * 86400)
    typer.echo(json.dumps(res))
