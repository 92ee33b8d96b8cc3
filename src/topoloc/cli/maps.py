"""``topoloc map build|add|info|calibrate``, ``topoloc localize`` and ``topoloc cache info|clean``."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import sys
import tempfile
import time
from collections import deque
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from topoloc.cli.app import app, command_group, handle_errors, needs
from topoloc.cli.options import (
    CacheDirOption,
    CalibrateSequenceOption,
    ConfigOption,
    ConfirmOption,
    EveryMOption,
    EverySOption,
    FeaturesOption,
    LocalizeSequenceOption,
    MapToursOption,
    MaxFeaturesOption,
    MaxSideAutoOption,
    MethodOption,
    MinSupportOption,
    PairsOutOption,
    ParamOption,
    PoseTopicOption,
    PrefetchOption,
    PreprocessOption,
    QuietOption,
    SchedulerOption,
    SchedulerTimeoutOption,
    SequenceModeOption,
    TopicOption,
    VerifyOption,
    VocabOption,
    VocabTrainOption,
    VocabWordsOption,
    at_least,
    spec_from_cli,
)
from topoloc.cli.progress import rich_progress
from topoloc.errors import TopolocError
from topoloc.io.scratch import spill_to
from topoloc.maps.acceptance import warn_before_localizing
from topoloc.spec.parts import STREAM_SEQUENCE_MODE, stream_sequence_for

if TYPE_CHECKING:
    from topoloc.maps import Map
    from topoloc.spec import LocalizeSpec

log = logging.getLogger(__name__)

map_app = command_group(help="Saved maps: build once from tours, add tours later, inspect, calibrate.")
app.add_typer(map_app, name="map")

@map_app.command("build", cls=needs("method", "map", "out"))
@handle_errors
def map_build(
    ctx: typer.Context,
    method: MethodOption = "",
    map: MapToursOption = None,
    out: Annotated[Path | None, typer.Option(help="Map file to write (.tlm).")] = None,
    vocab: VocabOption = None,
    vocab_train: VocabTrainOption = None,
    vocab_words: VocabWordsOption = 10000,
    param: ParamOption = None,
    features: FeaturesOption = "auto",
    max_features: MaxFeaturesOption = 1000,
    max_side: MaxSideAutoOption = "auto",
    preprocess: PreprocessOption = "auto",
    cache_dir: CacheDirOption = None,
    quiet: QuietOption = False,
    topic: TopicOption = None,
    every_s: EverySOption = None,
    every_m: EveryMOption = None,
    pose_topic: PoseTopicOption = None,
    shards: Annotated[int, typer.Option(
        help="Build the map as this many partial models of place ranges, one task each, merged into the "
             "same map as a one-piece build (docs/map_shards.md).")] = 1,
    verify: VerifyOption = None,
    min_support: MinSupportOption = None,
    scheduler: SchedulerOption = None,
    scheduler_timeout: SchedulerTimeoutOption = None,
    config: ConfigOption = None,
) -> None:
    """Build a map from one or more tours and save it in one file."""
    values = dict(locals())  # before any name is imported here
    from topoloc.io.paths import is_discard
    from topoloc.maps import Map
    from topoloc.spec import MapBuildSpec, spec_to_dict
    from topoloc.spec.setup import build_method

    spec = spec_from_cli(MapBuildSpec, ctx, values, config=config)
    if spec.out is None:
        raise TopolocError("--out is needed: the map file to write")
    spec.check_outputs()
    tours = spec.inputs.load(spec.maps)
    params = build_method(spec.method, spec.params).get_params()  # checks names and types first
    t0 = time.perf_counter()
    discard = is_discard(spec.out)  # --out /dev/null: built (and timed), not kept
    # The map's large intermediates (merged shards, inverted files) as scratch files beside the map,
    # until it is saved: the process then holds chunks of the map, not all of it (io.scratch).
    with spill_to(Path(tempfile.gettempdir()) if discard else spec.out.parent):
        with spec.execution.connect() as executor, rich_progress(not quiet) as progress:
            v = spec.vocabulary
            m = Map.build(executor=executor, method=spec.method, tours=tours, params=params, vocabulary=v.file,
                          vocab_train=v.train, vocab_words=v.words, seed=v.seed,
                          features=spec.features.config(), cache_dir=spec.execution.cache_dir,
                          progress=progress, shards=spec.shards)
        m.spec = spec_to_dict(spec)
        if not discard:
            m.save(spec.out)  # after any update of the file in progress elsewhere, which it replaces
    info = m.info()
    typer.echo(json.dumps({"out": str(spec.out), "bytes": info["bytes"], "method": info["method"],
                           "places": info["places"], "tours": [t["name"] for t in m.tours],
                           "seconds": round(time.perf_counter() - t0, 2)}))


@map_app.command("add", cls=needs())
@handle_errors
def map_add(
    map_file: Annotated[Path, typer.Argument(help="Map file to extend (rewritten atomically).")],
    tour: Annotated[Path, typer.Argument(help="Tour to add: a folder, a ROS bag (--topic) or a video.")],
    vocab: Annotated[Path | None, typer.Option(help="Must be the map's vocabulary when given.")] = None,
    features: Annotated[str | None, typer.Option(help="Must be the map's when given.")] = None,
    max_features: Annotated[int | None, typer.Option(help="Must be the map's when given.")] = None,
    preprocess: Annotated[str | None, typer.Option(help="Must be the map's when given.")] = None,
    cache_dir: CacheDirOption = None,
    quiet: QuietOption = False,
    topic: TopicOption = None,
    every_s: EverySOption = None,
    every_m: EveryMOption = None,
    pose_topic: PoseTopicOption = None,
    scheduler: SchedulerOption = None,
    scheduler_timeout: SchedulerTimeoutOption = None,
) -> None:
    """Add a tour to a saved map: the map is then what `map build` of all its tours gives.

    Most maps learn the tour alone, without revisiting the earlier images. A map whose vocabulary was trained on
    its own tours (map build without --vocab/--vocab-train) is built again from all its tours, the vocabulary
    trained again with the new tour (its words, and the map's checksum, change), and so is a map of a method
    that cannot add a tour exactly; the earlier tours' features come from the cache. It says so in one line when
    it does. Another `map add`, `map calibrate` or `map build` of the same file waits for this one (and says so
    once).
    """
    from dataclasses import replace

    from topoloc.io.dirs import Output, check_outputs, container_marker
    from topoloc.maps import Map
    from topoloc.spec import ExecutionSpec, FeatureSpec, InputSpec
    from topoloc.vocabulary import Vocabulary

    execution = ExecutionSpec(scheduler=scheduler, scheduler_timeout=scheduler_timeout, cache_dir=cache_dir)
    inputs = InputSpec(topic=topic, every_s=every_s, every_m=every_m, pose_topic=pose_topic)
    # Loaded, extended and saved with no other writer of the file in between (a second
    # `map add` or a `map calibrate` waits, then extends this one's result).
    with Map.update(map_file) as m:
        # The map is rewritten (that is the command); what it reads beside it must not be the map.
        check_outputs([Output(map_file, what="map file", earlier=container_marker("map"))], [tour, vocab, cache_dir])
        # Options left out take the map's own values, so only those given are compared.
        have = FeatureSpec(method=m.features.method, max_features=m.features.max_features,
                           preprocess=m.features.preprocess)
        given: dict[str, Any] = {k: v for k, v in (("method", features), ("max_features", max_features),
                                                   ("preprocess", preprocess)) if v is not None}
        m.check_compatible(features=replace(have, **given),
                           vocabulary=Vocabulary.load(vocab) if vocab is not None else None)
        t = inputs.load([tour])[0]
        if m.add_rebuilds:  # said before the work: minutes where a vocabulary is trained again (issue #49)
            n = len(m.tours)
            log.warning("%s: %s: building it again from its %d tour%s and this one, as map build of them would",
                        map_file, m.add_rebuilds_why, n, "" if n == 1 else "s")
        with execution.connect() as executor, rich_progress(not quiet) as progress:
            m.add_tour(t, cache_dir=execution.cache_dir, progress=progress, executor=executor)
    out: dict[str, Any] = {"out": str(map_file), "places": len(m.place_ids), "tours": [x["name"] for x in m.tours]}
    if m.calibration_stale:
        # Kept (the map still accepts by it), but chosen on the scores before this tour.
        out["calibration_stale"] = True
        log.warning("%s: the calibration predates the tour just added; run `topoloc map calibrate` again",
                    map_file)
    typer.echo(json.dumps(out))


@map_app.command("info", cls=needs())
@handle_errors
def map_info(
    map_file: Annotated[Path, typer.Argument(help="Map file.")],
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object.")] = False,
    quiet: QuietOption = False,
) -> None:
    """Method, parameters, places, tours, vocabulary, feature settings, calibration and size of a map."""
    from topoloc.datasets.sources import describe_source
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
                where = describe_source(t["source"]) if t.get("source") else t["root"]
                typer.echo(f"  - {t['name']}: {t['n_images']} images, {t['n_places']} places{when} ({where})")
        else:
            typer.echo(f"{key}: {json.dumps(value, default=str) if isinstance(value, dict | list) else value}")
        if key == "verification" and isinstance(value, dict) and "default" in value:
            typer.echo(f"  default {json.dumps(value['default'])}: {VERIFY_DEFAULT_WORDS[value['default']]}")
        if key == "calibration" and isinstance(value, dict) and value.get("stale"):
            typer.echo(f"  stale: tours added since it was made ({', '.join(value.get('tours_added_since', []))}); "
                       "run `topoloc map calibrate` again")


#: What a map's ``verification.default`` means to localize and evaluate --map-file, said under it by map info.
VERIFY_DEFAULT_WORDS = {
    True: "answers are verified (as the map was built or calibrated); --no-verify turns it off",
    False: "answers are not verified (the map was calibrated without verification, or saved before it existed): "
           "--verify turns it on",
    None: "not set: answers are verified wherever the map's images can be read (verification.can_verify); "
          "--no-verify turns it off",
}


@map_app.command("calibrate", cls=needs())
@handle_errors
def map_calibrate(
    map_file: Annotated[Path, typer.Argument(help="Map file (rewritten atomically with the threshold).")],
    query: Annotated[Path, typer.Option(help="A labelled tour (places.csv or natural order) not in the map.")],
    precision: Annotated[float, typer.Option(help="Precision the accepted localisations must reach.")] = 0.99,
    tolerance: Annotated[str, typer.Option(
        help="A match within N place ids of the query's place is right, any other is wrong (default 8); "
             "the reported precision and recall are what `localize` then accepts on this tour. HARD:SOFT "
             "is still read (a match HARD..SOFT away is neither right nor wrong); N is N:N.")] = "8",
    tolerance_m: Annotated[str | None, typer.Option(
        "--tolerance-m", help="The same in metres (needs x,y): within M metres is right; replaces --tolerance.")
    ] = None,
    cache_dir: CacheDirOption = None,
    quiet: QuietOption = False,
    topic: TopicOption = None,
    every_s: EverySOption = None,
    every_m: EveryMOption = None,
    pose_topic: PoseTopicOption = None,
    sequence: CalibrateSequenceOption = None,
    sequence_mode: SequenceModeOption = STREAM_SEQUENCE_MODE,
    verify: VerifyOption = None,
) -> None:
    """Choose the threshold that reaches --precision on a labelled tour and store it in the map.

    Where answers are verified (the default), the answers' confidence model is fitted on the tour and the
    threshold is on the confidence; with --no-verify, on the method's score (docs/protocol.md, Verification).
    Precision is right accepted frames over accepted frames; recall is right accepted frames over the frames
    that have a right place in the map.  Calibrating again clears a calibration that `map add` marked stale.
    """
    from topoloc.io.dirs import Output, check_outputs, container_marker
    from topoloc.maps import Map
    from topoloc.maps.calibration import check_precision
    from topoloc.spec import GroundTruthSpec, InputSpec, SequenceSpec

    check_precision(precision)
    seq = None if sequence is None else SequenceSpec(length=at_least("--sequence", sequence, 0), mode=sequence_mode)
    gt = GroundTruthSpec.for_calibration(tolerance, tolerance_m)
    inputs = InputSpec(topic=topic, every_s=every_s, every_m=every_m, pose_topic=pose_topic)
    with Map.update(map_file) as m:  # no tour another writer adds meanwhile is lost
        check_outputs([Output(map_file, what="map file", earlier=container_marker("map"))], [query, cache_dir])
        q = inputs.load([query])[0]
        if seq is None:  # not told: sequences where the tour travels the route, as a stream would
            seq = stream_sequence_for(q.places)
            if sequence_mode != STREAM_SEQUENCE_MODE and seq.length:
                seq = SequenceSpec(length=seq.length, mode=sequence_mode)
        with rich_progress(not quiet) as progress:
            cal = m.calibrate_on(q, ground_truth=gt, precision=precision, label=str(query), cache_dir=cache_dir,
                                 progress=progress, sequence=seq, verify=verify)
    typer.echo(json.dumps(cal))


@app.command(cls=needs("map_file", "inputs", "out"))
@handle_errors
def localize(
    ctx: typer.Context,
    map_file: Annotated[Path | None, typer.Argument(help="Map file (topoloc map build).")] = None,
    inputs: Annotated[list[str] | None, typer.Argument(
        help="Image files or folders, ROS bags (.bag, rosbag2 folders; --topic) or videos, in order; or one "
             "camera (/dev/video0 or its index) or network stream (rtsp://, http:// MJPEG), read live: the "
             "newest frame is matched, the ones that arrive meanwhile are skipped (counted), Ctrl-C stops.")] = None,
    out: Annotated[Path | None, typer.Option(
        help="JSON lines file, one line per frame, written as it goes (-: standard output, the summary then on "
             "standard error).")] = None,
    top_k: Annotated[int, typer.Option(help="Places listed per frame.")] = 5,
    pairs_out: PairsOutOption = None,
    prefetch: PrefetchOption = -1,
    sequence: LocalizeSequenceOption = None,
    sequence_mode: SequenceModeOption = "constant",
    verify: VerifyOption = None,
    min_support: MinSupportOption = None,
    confirm: ConfirmOption = False,
    quiet: QuietOption = False,
    topic: TopicOption = None,
    every_s: EverySOption = None,
    every_m: EveryMOption = None,
    pose_topic: PoseTopicOption = None,
    scheduler: SchedulerOption = None,
    scheduler_timeout: SchedulerTimeoutOption = None,
    config: ConfigOption = None,
) -> None:
    """Localise new images against a saved map: place, score, accepted, top places (and x, y) per frame.

    With --scheduler the frames are described and scored in batches by the Dask workers (which open the
    map file: it must be on a file system they share); the lines are the same, in the same order.
    """
    values = dict(locals())  # before any name is imported here
    from topoloc.maps import Map
    from topoloc.spec import LocalizeSpec

    values["images"], values["stream"] = _split_inputs(values.pop("inputs") or [])
    single = values["sequence"] == 0  # --sequence 0: single images, whatever the map was calibrated with
    if single:
        values["sequence"] = None
    spec = spec_from_cli(LocalizeSpec, ctx, values, config=config)
    assert spec.map_file is not None
    m = Map.load(spec.map_file)
    if not single and not spec.sequence.length:  # not given: match as the threshold was calibrated
        spec = dataclasses.replace(spec, sequence=m.calibrated_sequence)
    assert spec.out is not None
    if spec.stream is not None:
        _localize_live(spec, m)
        return
    names: deque[str] = deque()  # the pairs name of each frame read and not yet written (lines keep its order)
    check_name = None
    if spec.pairs_out is not None:
        from topoloc.evaluation.pairs import check_pair_name

        for name in m.place_image_names():
            check_pair_name(name, spec.map_file)
        check_name = check_pair_name
    total, frames = spec.inputs.frames(spec.images, on_frame=names.append if spec.pairs_out else None,
                                       check_name=check_name)
    # The map file is memory-mapped while the lines are written: truncating it would kill the run.
    spec.check_outputs()
    # After the inputs are checked, so that an input error stays the only line.
    warn_before_localizing(m, spec.map_file, spec.sequence, spec.verification.enabled,
                           spec.verification.min_support)
    loc = m.localizer_for(spec)
    # Written line by line: a run that is stopped keeps every frame done so far.
    # ``--out -``: the lines on standard output (the Unix convention, for `| jq`), the summary on standard error.
    lines_to = _LineFile(Path("-"), stream=sys.stdout) if spec.to_stdout else _LineFile(spec.out)
    with spec.execution.connect() as executor, lines_to as fh, rich_progress(not quiet) as progress:
        advance = progress(f"localize ({m.recognizer.name})", total)
        pairs: list[tuple[str, str]] = []
        place_images = dict(zip(m.place_ids.tolist(), m.place_image_names(), strict=True)) if spec.pairs_out else {}
        for line in loc.stream(frames, executor=executor):
            fh.write(json.dumps(line) + "\n")
            if spec.pairs_out is not None:
                query = names.popleft()
                pairs.extend((query, place_images[int(p)]) for p, _ in line["top"])
            advance(1)
    if spec.pairs_out is not None:
        from topoloc.evaluation.pairs import write_pairs

        write_pairs(spec.pairs_out, pairs)
    typer.echo(json.dumps({"out": str(spec.out), **({"pairs": str(spec.pairs_out)} if spec.pairs_out else {}),
                           **loc.summary()}), err=spec.to_stdout)


def _split_inputs(inputs: list[str]) -> tuple[list[Path], str | None]:
    """The command line's inputs as files, folders and recordings, or the one camera or stream among them."""
    from topoloc.datasets.sources.live import is_live_source

    live = [s for s in inputs if is_live_source(s)]
    if not live:
        return [Path(s) for s in inputs], None
    if len(inputs) > 1:
        raise TopolocError(f"a camera or stream is read alone, give no other input: {live[0]}")
    return [], live[0]


def _localize_live(spec: LocalizeSpec, m: Map) -> None:
    """``localize`` of a camera or network stream: the newest frame each time, until Ctrl-C or the stream ends.

    The lines are those of a recording, ``time`` the wall-clock time the frame
    was captured (Unix seconds), ``frame`` its number in the stream (the frames
    skipped leave gaps); the last line adds what the stream gave: frames read,
    skipped (arrived while others were matched), refused by the decoding
    (``frames_bad``: random bytes, a truncated or too large JPEG; each said in a
    warning line, the first and every 100th) and how it ended.
    Ctrl-C (SIGINT) or SIGTERM stops the reading: the frames already read are
    answered, then the summary; a second one stops at once.
    """
    import signal

    from topoloc.datasets.sources.live import LiveSource

    assert spec.stream is not None and spec.out is not None and spec.map_file is not None
    given = [flag for flag, v in (("--topic", spec.inputs.topic), ("--every-s", spec.inputs.every_s),
                                  ("--every-m", spec.inputs.every_m), ("--pose-topic", spec.inputs.pose_topic),
                                  ("--pairs-out", spec.pairs_out), ("--scheduler", spec.execution.scheduler))
             if v is not None]
    if given:
        raise TopolocError(f"{'/'.join(given)} does not apply to a camera or stream: {spec.stream}")
    spec.check_outputs()
    source = LiveSource(spec.stream)
    warn_before_localizing(m, spec.map_file, spec.sequence, spec.verification.enabled,
                           spec.verification.min_support)
    loc = m.localizer_for(spec)
    stopped_by: list[str] = []

    def stop(signum: int, frame: object) -> None:
        if stopped_by:
            raise KeyboardInterrupt  # the second one: at once
        stopped_by.append(signal.Signals(signum).name)
        source.stop()

    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with (_LineFile(Path("-"), stream=sys.stdout) if spec.to_stdout else _LineFile(spec.out)) as fh:
            for line in loc.stream(source.frames()):
                fh.write(json.dumps(line) + "\n")
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        source.close()
    if not stopped_by:
        # One line naming the stream: whether it was over or broke off, OpenCV cannot tell.
        log.warning("the stream ended after %d frames: %s", source.frames_read, source.name)
    typer.echo(json.dumps({"out": str(spec.out), "stream": source.name, "ended": stopped_by[0] if stopped_by
                           else "stream", "frames_read": source.frames_read, "frames_skipped": source.buffer.skipped,
                           "frames_bad": source.frames_bad,
                           **loc.summary()}), err=spec.to_stdout)


class _LineFile:
    """A text file written one whole line at a time, straight to the file (no buffer).

    A write that fails (disk full, quota) is one line naming the file, and
    the file is cut back to its last whole line, so what is there still reads.
    """

    def __init__(self, path: Path, *, stream: Any = None) -> None:
        from topoloc.errors import WriteError

        self.path = path
        self.size = 0
        self.stream = stream  # standard output: each line written and flushed, never cut back or closed
        if stream is not None:
            return
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        except OSError as exc:
            raise WriteError.of(path, exc) from None

    def write(self, text: str) -> None:
        from topoloc.errors import WriteError

        if self.stream is not None:
            try:
                self.stream.write(text)
                self.stream.flush()
            except OSError as exc:
                raise WriteError.of(self.path, exc) from None
            return
        raw = text.encode("utf-8")
        data = memoryview(raw)
        try:
            while data:
                data = data[os.write(self.fd, data):]
        except OSError as exc:
            try:
                os.ftruncate(self.fd, self.size)
            except OSError:
                log.debug("cannot cut %s back to its last whole line", self.path)
            raise WriteError.of(self.path, exc) from None
        self.size += len(raw)

    def __enter__(self) -> _LineFile:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.stream is None:
            os.close(self.fd)


cache_app = command_group(help="The feature and vocabulary cache (~/.cache/topoloc or TOPOLOC_CACHE_DIR).")
app.add_typer(cache_app, name="cache")


@cache_app.command("info", cls=needs())
@handle_errors
def cache_info(
    cache_dir: CacheDirOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object.")] = False,
    quiet: QuietOption = False,
) -> None:
    """Files and bytes in each part of the cache, and the feature stores of each feature setting."""
    from topoloc.features.cache import cache_root, cache_usage
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
        typer.echo(json.dumps({"cache_dir": str(cache_root(cache_dir)), **usage,
                               "feature_stores": per_setting, "stores": stores}))
        return
    typer.echo(f"cache: {cache_root(cache_dir)}")
    for part, u in usage.items():
        typer.echo(f"  {part}: {u['files']} files, {u['bytes'] / 2**20:.1f} MiB")
    if per_setting:
        typer.echo("feature stores (one per traverse and setting):")
    for key, agg in per_setting.items():
        typer.echo(f"  {key}: {agg['traverses']} traverses, {agg['images']} images, {agg['bytes'] / 2**20:.1f} MiB")


@cache_app.command("clean", cls=needs())
@handle_errors
def cache_clean(
    cache_dir: CacheDirOption = None,
    max_size: Annotated[str | None, typer.Option(help="Keep at most this much, the most recently used (500M, 2G).")]
    = None,
    older_than: Annotated[float | None, typer.Option(help="Remove entries not used for this many days.")] = None,
    all_: Annotated[bool, typer.Option("--all", help="Remove everything.")] = False,
    quiet: QuietOption = False,
) -> None:
    """Remove cache entries, least recently used first: whole feature stores and files (computed again when needed)."""
    from topoloc.features.cache import clean_cache, parse_size

    if not all_ and max_size is None and older_than is None:
        raise TopolocError("say what to remove: --max-size SIZE, --older-than DAYS or --all")
    if older_than is not None and not (math.isfinite(older_than) and older_than >= 0):
        raise TopolocError(f"--older-than must be a finite number of days >= 0, got {older_than}")
    limit = parse_size(max_size) if max_size is not None else None
    res = clean_cache(cache_dir, max_bytes=limit, older_than_s=None if older_than is None else older_than * 86400)
    typer.echo(json.dumps(res))
