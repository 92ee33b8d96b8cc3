"""``topoloc`` command line: evaluate, report, vocab, synth, demo (saved maps: :mod:`topoloc.cli.maps`)."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import typer

from topoloc.cli.app import app, bench_app, handle_errors, needs, vocab_app
from topoloc.cli.options import (
    CacheDirOption,
    ConfigOption,
    ConfirmOption,
    EveryMOption,
    EverySOption,
    FeaturesOption,
    MapToursOption,
    MaxFeaturesOption,
    MaxSideAutoOption,
    MethodOption,
    MinSupportOption,
    PairsOutOption,
    ParamOption,
    PoseTopicOption,
    PreprocessOption,
    QueryOption,
    QuietOption,
    SchedulerOption,
    SchedulerTimeoutOption,
    SequenceModeOption,
    SequenceOption,
    SlamFeaturesOption,
    ToleranceMOption,
    ToleranceOption,
    TopicOption,
    VerifyOption,
    VocabOption,
    VocabTrainOption,
    VocabWordsOption,
    at_least,
    own_names,
    parse_params,
    spec_from_cli,
)
from topoloc.cli.progress import rich_progress
from topoloc.errors import TopolocError

__all__ = ["app", "main"]


@app.command(cls=needs("(--map <path>... --method <str> | --map-file <path>)", "query", "out"))
@handle_errors
def evaluate(
    ctx: typer.Context,
    query: QueryOption = None,
    out: Annotated[Path | None, typer.Option(help="Output folder.")] = None,
    method: MethodOption = "",
    map: MapToursOption = None,
    map_file: Annotated[Path | None, typer.Option(
        "--map-file", help="A saved map (topoloc map build) instead of --map tours and --method.")] = None,
    vocab: VocabOption = None,
    vocab_train: VocabTrainOption = None,
    vocab_words: VocabWordsOption = 10000,
    tolerance: ToleranceOption = "0:8",
    tolerance_m: ToleranceMOption = None,
    ground_truth: Annotated[
        Path | None, typer.Option(help="VPR-Bench ground_truth_new.npy or .npz with GThard/GTsoft.")
    ] = None,
    sequence: SequenceOption = None,
    sequence_mode: SequenceModeOption = "constant",
    verify: VerifyOption = None,
    min_support: MinSupportOption = None,
    confirm: ConfirmOption = False,
    recall_at: Annotated[
        str, typer.Option(help="R@N to report, e.g. 1,5,10,20 (recall_at_N in metrics.json).")
    ] = "1,5,10",
    top_k: Annotated[int, typer.Option(
        "--top-k", help="Keep only the K best places per query (S_topk.npz) and compute every metric from them "
                        "(a correct place outside the top K counts as not found); 0 = the whole S.")] = 0,
    pairs_out: PairsOutOption = None,
    param: ParamOption = None,
    features: FeaturesOption = "auto",
    max_features: MaxFeaturesOption = 1000,
    max_side: MaxSideAutoOption = "auto",
    preprocess: PreprocessOption = "auto",
    cache_dir: CacheDirOption = None,
    quiet: QuietOption = False,
    html: Annotated[Path | None, typer.Option(
        help="Also write a self-contained HTML page to browse the run (e.g. OUT/index.html).")] = None,
    topic: TopicOption = None,
    every_s: EverySOption = None,
    every_m: EveryMOption = None,
    pose_topic: PoseTopicOption = None,
    scheduler: SchedulerOption = None,
    scheduler_timeout: SchedulerTimeoutOption = None,
    config: ConfigOption = None,
) -> None:
    """Run one method on map and query traverses and score it (docs/protocol.md)."""
    values = dict(locals())  # before any name is imported here
    from topoloc.evaluation.pipeline import evaluate as run
    from topoloc.evaluation.report import TABLE_HEADER, table_row
    from topoloc.io.paths import is_discard
    from topoloc.spec import EvaluateSpec

    single = values["map_file"] is not None and values["sequence"] == 0  # a saved map's "single images, not its own"
    if single:
        values["sequence"] = None
    spec = spec_from_cli(EvaluateSpec, ctx, values, config=config)
    if spec.map_file is not None and not single and not _given(ctx, "sequence", config):
        # A saved map is scored as `localize` uses it: with the sequence matching its threshold was calibrated on.
        import dataclasses

        from topoloc.maps import Map

        spec = dataclasses.replace(spec, sequence=Map.load(spec.map_file).calibrated_sequence)
    spec.check_outputs()  # again in the pipeline; here before a scheduler is waited for
    with spec.execution.connect() as executor, rich_progress(not quiet) as progress:
        metrics = run(spec, progress=progress, executor=executor)
    typer.echo(TABLE_HEADER + table_row(metrics), nl=False)
    s_file = "S_topk.npz" if spec.top_k else "S.npy"
    kept = [] if is_discard(spec.out) else [f"{spec.out}/{s_file}, metrics.json, pr.png, report.md"]
    kept += [str(p) for p in (spec.html, spec.pairs_out) if p is not None and not is_discard(p)]
    typer.echo(f"wrote {'; '.join(kept)}" if kept else "wrote nothing (the outputs were /dev/null)")


def _given(ctx: typer.Context, name: str, config: Path | None) -> bool:
    """Whether option ``name`` was given on the command line, in the environment or in the ``--config`` file."""
    source = getattr(ctx.get_parameter_source(name), "name", None)
    if source in ("COMMANDLINE", "ENVIRONMENT"):
        return True
    if config is None:
        return False
    from topoloc.spec import load_config, nest

    return name in nest(load_config(config))


@app.command(cls=needs())
@handle_errors
def report(
    runs: Annotated[list[Path], typer.Argument(help="Output folders of `topoloc evaluate`.")],
    out: Annotated[Path, typer.Option(help="Folder for report.md and pr_curves.png.")],
    title: Annotated[str, typer.Option(help="Title of the report.")] = "Results",
    html: Annotated[Path | None, typer.Option(
        help="Also write one self-contained HTML page to browse every query (e.g. OUT/index.html).")] = None,
    quiet: QuietOption = False,
) -> None:
    """Put several evaluate runs side by side: one table and one PNG of PR curves (and an HTML page)."""
    from topoloc.evaluation.report import build_report
    from topoloc.io.dirs import Output, check_outputs, html_marker, writing_into
    from topoloc.spec.parts import distinct_paths
    from topoloc.spec.runs import html_page

    distinct_paths("runs", runs)  # a run given twice would be two rows of one run (issue #49)
    outputs = [Output(out, "folder", names=REPORT_FILES, earlier=_earlier_report, what="report folder")]
    if html is not None:
        outputs.append(Output(html_page(html, None), what="HTML page", earlier=html_marker()))
    check_outputs(outputs, runs)
    with writing_into(out) as folder:
        path = build_report(list(runs), folder, title=title)
        typer.echo(path.read_text(), nl=False)
    if html is not None:
        from topoloc.evaluation.html import build_html_report

        with rich_progress(not quiet) as progress:
            page = build_html_report(list(runs), html, title=title, progress=progress)
        typer.echo(f"wrote {page}")


# What `report` writes into its folder; a folder holding both is an earlier report, rewritten.
REPORT_FILES = ("report.md", "pr_curves.png")


def _earlier_report(folder: Path) -> bool:
    return all((folder / name).is_file() for name in REPORT_FILES)


@app.command(cls=needs())
@handle_errors
def methods(
    name: Annotated[str | None, typer.Argument(help="A method: explain each of its parameters.")] = None,
    quiet: QuietOption = False,
) -> None:
    """List the methods `evaluate` accepts with their parameters; `methods NAME` explains each parameter."""
    from topoloc.methods import available_methods, get_method

    if name is not None:
        import shutil
        import textwrap

        from topoloc.methods.describe import describe_method, plain_text

        summary, documented = describe_method(name)
        summary = plain_text(summary)
        width = max(60, shutil.get_terminal_size().columns - 1)
        typer.echo(f"{name}: {summary}\n\nParameters (evaluate --param KEY=VALUE):")
        for p in documented:
            typer.echo(f"  {p.name} = {p.default!r}" + (f"  ({plain_text(p.type)})" if p.type else ""))
            typer.echo(textwrap.fill(plain_text(p.text) or "(not documented)", width=width, initial_indent=" " * 6,
                                     subsequent_indent=" " * 6, break_on_hyphens=False, break_long_words=False))
        return
    for method in available_methods():
        cls = get_method(method)
        params = ", ".join(f"{k}={v!r}" for k, v in _defaults(cls).items())
        typer.echo(f"{method}: {params}")
    typer.echo("\n`topoloc methods NAME` explains each parameter of method NAME.")


def _defaults(cls: type) -> dict[str, Any]:
    import inspect

    sig = inspect.signature(cls.__init__)  # type: ignore[misc]
    return {p.name: p.default for p in sig.parameters.values() if p.kind is p.KEYWORD_ONLY}


@vocab_app.command("train", cls=needs("folders", "out"))
@handle_errors
def vocab_train_cmd(
    ctx: typer.Context,
    folders: Annotated[list[Path] | None, typer.Argument(help="Image folders, searched recursively.")] = None,
    out: Annotated[Path | None, typer.Option(help="Vocabulary file to write.")] = None,
    words: Annotated[int, typer.Option(help="Number of visual words.")] = 10000,
    features: FeaturesOption = "auto",
    max_features: MaxFeaturesOption = 1000,
    max_side: MaxSideAutoOption = "auto",
    preprocess: PreprocessOption = "auto",
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    cache_dir: CacheDirOption = None,
    quiet: QuietOption = False,
    scheduler: SchedulerOption = None,
    scheduler_timeout: SchedulerTimeoutOption = None,
    config: ConfigOption = None,
) -> None:
    """Train a visual vocabulary (k-means) on the images under FOLDERS."""
    values = dict(locals())  # before any name is imported here
    from topoloc.features import FeatureExtractor
    from topoloc.io.paths import through_link
    from topoloc.spec import VocabTrainSpec
    from topoloc.vocabulary import train_vocabulary

    spec = spec_from_cli(VocabTrainSpec, ctx, values, config=config, names=VOCAB_TRAIN_NAMES)
    assert spec.out is not None
    spec.check_outputs()
    config_ = spec.features.config()
    extractor = FeatureExtractor(config_, cache_dir=spec.execution.cache_dir)
    with spec.execution.connect() as executor, rich_progress(not quiet) as progress:
        voc = train_vocabulary(list(spec.folders), extractor=extractor, n_words=spec.vocabulary.words,
                               seed=spec.vocabulary.seed, progress=progress, executor=executor)
    voc.save(through_link(spec.out))  # a link named as the file: its target replaced, the link kept
    typer.echo(json.dumps({"out": str(spec.out), **voc.provenance_}, default=str))


# ``vocab train`` says --words and --seed for the vocabulary's settings.
VOCAB_TRAIN_NAMES = {"words": "vocabulary.words", "seed": "vocabulary.seed"}


@app.command(cls=needs())
@handle_errors
def synth(
    ctx: typer.Context,
    out: Annotated[Path, typer.Argument(help="Folder to write the tours into.")],
    places: Annotated[int, typer.Option(help="Number of places along the route.")] = 60,
    hours: Annotated[str, typer.Option(help="Comma-separated times of day of the tours.")] = "9,13,17,22",
    width: Annotated[int, typer.Option(help="Image width.")] = 320,
    height: Annotated[int, typer.Option(help="Image height.")] = 240,
    seed: Annotated[int, typer.Option(help="World seed.")] = 0,
    quiet: QuietOption = False,
) -> None:
    """Generate a synthetic route (tours at several times of day) for tests and demos."""
    from topoloc.io.dirs import Output, check_outputs, writing_into
    from topoloc.io.paths import is_discard
    from topoloc.synth import RouteConfig, generate_route

    own_names(ctx, ROUTE_NAMES)
    tours = _tours(hours)
    names = tuple(name for name, _ in tours)
    check_outputs([Output(out, "folder", names=names, earlier=_earlier_route(names), what="output folder")], [])
    with writing_into(out) as folder:
        dirs = generate_route(folder, config=RouteConfig(n_places=places, width=width, height=height,
                                                         seed=seed), tours=tours)
    for d in dirs:
        typer.echo(f"{d.name}: discarded (/dev/null)" if is_discard(out) else str(out / d.relative_to(folder)))


# ``synth`` and ``demo`` say --places for the route's n_places.
ROUTE_NAMES = {"places": "n_places"}


def _earlier_route(names: tuple[str, ...]) -> Callable[[Path], bool]:
    """Whether the existing ones of a folder's tour folders ``names`` were written by ``synth``."""

    def earlier(folder: Path) -> bool:
        tours = [folder / n for n in names if (folder / n).exists()]
        return bool(tours) and all(_synthetic_tour(t) for t in tours)

    return earlier


def _synthetic_tour(folder: Path) -> bool:
    # generate_route writes this exact header (with x, y from the route); a user's tour rarely does.
    try:
        with open(folder / "places.csv", encoding="utf-8") as fh:
            return fh.readline().strip() == "image,place,time,x,y"
    except (OSError, UnicodeDecodeError):
        return False


def _tours(hours: str) -> list[tuple[str, float]]:
    try:
        hs = [float(h) for h in hours.split(",") if h.strip()]
    except ValueError:
        raise TopolocError(f"--hours {hours!r} is not a comma-separated list of numbers") from None
    if not all(math.isfinite(h) and 0 <= h <= 24 for h in hs):
        raise TopolocError(f"--hours {hours!r} needs finite hours of the day in [0, 24]")
    return [(f"tour_{int(h):02d}{round((h % 1) * 60):02d}", h) for h in hs]


@app.command(cls=needs())
@handle_errors
def demo(
    ctx: typer.Context,
    out: Annotated[Path, typer.Option(help="Output folder.")] = Path("demo_out"),
    places: Annotated[int, typer.Option(help="Places along the generated route.")] = 60,
    quiet: QuietOption = False,
) -> None:
    """Generate a route at several times of day, run the methods, print a table, plot PR curves."""
    from topoloc.demo import DEMO_FILES, run_demo
    from topoloc.io.dirs import Output, check_outputs, writing_into

    own_names(ctx, ROUTE_NAMES)
    check_outputs([Output(out, "folder", names=DEMO_FILES, what="output folder",
                          earlier=lambda d: _earlier_route(("tour_0900",))(d / "route"))], [])
    with rich_progress(not quiet) as progress, writing_into(out) as folder:
        report_path = run_demo(folder, n_places=places, progress=progress)
        typer.echo(report_path.read_text(), nl=False)
    typer.echo(f"\nPR curves: {out / report_path.relative_to(folder).parent / 'pr_curves.png'}")


@app.command(cls=needs())
@handle_errors
def convert(
    format: Annotated[str, typer.Argument(help="vpr-bench, utm-names, dbstruct, msls, kitti or latlon-csv.")],
    src: Annotated[Path, typer.Argument(help="The dataset: folder, .mat or CSV file, as the format takes.")],
    out: Annotated[Path, typer.Option(help="Output folder: OUT/map and OUT/query, or one traverse at OUT.")],
    images: Annotated[
        Path | None, typer.Option(help="Folder the image names are relative to (dbstruct, latlon-csv).")
    ] = None,
    query_images: Annotated[
        Path | None, typer.Option(help="dbstruct: folder the query names are relative to (default: --images).")
    ] = None,
    poses: Annotated[Path | None, typer.Option(help="kitti: poses file (default ../../poses/XX.txt).")] = None,
    column: Annotated[
        list[str] | None, typer.Option(help="latlon-csv: KEY=NAME for image, lat, lon, time (repeatable).")
    ] = None,
    copy: Annotated[bool, typer.Option("--copy", help="Copy images instead of linking them.")] = False,
    quiet: QuietOption = False,
) -> None:
    """Write a public dataset (VPR-Bench, Pittsburgh/Tokyo .mat, MSLS, KITTI, ...) as traverses."""
    from topoloc.datasets.formats import ConvertOptions
    from topoloc.datasets.formats import convert as run
    from topoloc.io.dirs import Output, check_outputs, json_marker, writing_into

    # Images are linked into the folder under their own names: any entry of a folder that is not an
    # earlier conversion (its dataset.json) could be replaced.
    check_outputs([Output(out, "folder", names=None, earlier=json_marker("dataset.json", "n_images"),
                          what="output folder")], [src, images, query_images, poses])
    with writing_into(out) as folder:
        result = run(format, src, folder, ConvertOptions(images=images, query_images=query_images, poses=poses,
                                                         columns=parse_params(column or []), copy=copy))
    for key, where in result.traverses.items():
        typer.echo(f"{key or 'traverse'}: {where} ({result.n_images[key]} images)")
    if result.projection:
        typer.echo(f"x, y: {result.projection}")
    for note in result.notes:
        typer.echo(f"note: {note}")
    typer.echo(f"evaluate with: topoloc evaluate ... {result.evaluate}")


@app.command("show-match", cls=needs())
@handle_errors
def show_match_cmd(
    query_image: Annotated[Path, typer.Argument(help="Query image.")],
    map: Annotated[list[Path], typer.Option(
        "--map", metavar="<path>", help="Map traverse folder (repeatable): the tours.")],
    out: Annotated[Path, typer.Option(help="PNG to write.")],
    vocab: VocabOption = None,
    vocab_train: VocabTrainOption = None,
    vocab_words: VocabWordsOption = 10000,
    param: ParamOption = None,
    method: MethodOption = "coocmap",
    place: Annotated[int | None, typer.Option(
        help="Draw this map place (e.g. the right one) instead of the best match; its score and rank are shown.")
    ] = None,
    tolerance: Annotated[int, typer.Option(
        help="Places apart still counted right in the verdict (from the query folder's place ids).")] = 0,
    features: FeaturesOption = "auto",
    max_features: MaxFeaturesOption = 1000,
    max_side: MaxSideAutoOption = "auto",
    preprocess: PreprocessOption = "auto",
    cache_dir: CacheDirOption = None,
    quiet: QuietOption = False,
) -> None:
    """Localise one image and draw it beside the map place it matched, labelled, correspondences coloured.

    The header names the query (file, time, true place from its folder) and the map place (id, tour,
    file, time); the footer the score, the rank among all places, the number of consistent
    correspondences (green; inconsistent ones red) and whether the match is right.
    """
    from topoloc.datasets.traverse import check_distinct_tours, load_traverse
    from topoloc.drawing.match_figure import labelled_match
    from topoloc.drawing.show_match import write_png
    from topoloc.io.dirs import Output, check_outputs, png_marker
    from topoloc.io.paths import check_kind
    from topoloc.spec import FeatureSpec, VocabularySpec
    from topoloc.spec.setup import build_method, make_resources

    check_outputs([Output(out, what="PNG", earlier=png_marker())], [query_image, *map, vocab, *(vocab_train or ()),
                                                                    cache_dir])
    at_least("--tolerance", tolerance, 0)
    check_kind(query_image, "file", "query image")
    rec = build_method(method, parse_params(param or []))
    voc_spec = VocabularySpec(file=vocab, train=tuple(vocab_train or ()), words=vocab_words)
    feature_spec = FeatureSpec(method=features, max_features=max_features, max_side=max_side, preprocess=preprocess)
    maps = [load_traverse(m) for m in map]
    check_distinct_tours(maps)
    config_ = feature_spec.config()
    with rich_progress(not quiet) as progress:
        resources, _ = make_resources(
            config_, voc_spec, cache_dir=cache_dir,
            needs_vocabulary=f"show-match with {rec.name}" if rec.uses_vocabulary else "", progress=progress,
            tours=maps,
        )
        rec.fit(maps, resources=resources)
        canvas, info = labelled_match(rec, query_image, maps, resources=resources, place=place,
                                      tolerance=tolerance)
    write_png(canvas, out)
    typer.echo(json.dumps({**info, "out": str(out)}, default=str))


def slam_verify(verify: bool | None) -> bool:
    """``slam --verify/--no-verify``; not given: ``$TOPOLOC_VERIFY``, else on (verification.md, part ``slam``): the
    one precedence (:func:`topoloc.spec.parts.choose_verify`), a bad ``$TOPOLOC_VERIFY`` refused either way."""
    from topoloc.spec.parts import choose_verify

    return choose_verify(verify).enabled is not False


@app.command(cls=needs())
@handle_errors
def slam(
    traverse: Annotated[Path, typer.Argument(
        help="Traverse folder, ROS bag (.bag, rosbag2 folder; --topic) or video, processed in order.")],
    out: Annotated[Path, typer.Option(help="Output folder.")],
    vocab: VocabOption = None,
    vocab_train: VocabTrainOption = None,
    vocab_words: VocabWordsOption = 10000,
    model: Annotated[Path | None, typer.Option(help="Saved FAB-MAP model (else trained).")] = None,
    variant: Annotated[str, typer.Option(help="fabmap or fabmap2.")] = "fabmap",
    threshold: Annotated[float, typer.Option(help="Posterior needed to accept a loop closure.")] = 0.98,
    p_new: Annotated[float, typer.Option(help="Prior probability of a new place.")] = 0.9,
    min_gap: Annotated[int, typer.Option(help="Images between a place's last visit and a loop closure.")] = 10,
    features: SlamFeaturesOption = "sift",
    verify: VerifyOption = None,
    max_features: MaxFeaturesOption = 1000,
    max_side: MaxSideAutoOption = "auto",
    preprocess: PreprocessOption = "auto",
    cache_dir: CacheDirOption = None,
    quiet: QuietOption = False,
    topic: TopicOption = None,
    every_s: EverySOption = None,
    every_m: EveryMOption = None,
    pose_topic: PoseTopicOption = None,
    html: Annotated[Path | None, typer.Option(
        help="Also write a self-contained HTML page: closures along the route, posterior, image pairs.")] = None,
) -> None:
    """Online FAB-MAP over one traverse: new places and loop closures (posterior.npy, loop_closures.csv).

    A ROS bag or a video is read as `localize` reads it (--topic, --every-s, --every-m, --pose-topic).
    """
    from topoloc.evaluation.slam import SLAM_FILES, run_slam
    from topoloc.io.dirs import Output, check_outputs, html_marker, json_marker, writing_into
    from topoloc.io.paths import is_discard
    from topoloc.spec import FeatureSpec, InputSpec, VocabularySpec
    from topoloc.spec.setup import make_resources

    if min_gap < 0:
        raise TopolocError(f"--min-gap must be >= 0, got {min_gap}")
    if not 0.0 < threshold <= 1.0:
        raise TopolocError(f"--threshold must be in (0, 1], got {threshold}")
    if not 0.0 <= p_new < 1.0:
        raise TopolocError(f"--p-new must be in [0, 1), got {p_new}")
    voc_spec = VocabularySpec(file=vocab, train=tuple(vocab_train or ()), words=vocab_words)
    feature_spec = FeatureSpec(method=features, max_features=max_features, max_side=max_side, preprocess=preprocess)
    outputs = [Output(out, "folder", names=SLAM_FILES, earlier=json_marker("slam.json", "params"),
                      what="output folder")]
    if html is not None:
        outputs.append(Output(html, what="HTML page", earlier=html_marker()))
    check_outputs(outputs, [traverse, vocab, *(vocab_train or ()), model, cache_dir])
    trav = InputSpec(topic=topic, every_s=every_s, every_m=every_m, pose_topic=pose_topic).load([traverse])[0]
    with rich_progress(not quiet) as progress, writing_into(out) as folder:
        resources, _ = make_resources(feature_spec.config(), voc_spec, cache_dir=cache_dir,
                                      needs_vocabulary="slam", progress=progress, tours=[trav])
        result = run_slam(trav, out_dir=folder, model=model, resources=resources, variant=variant,
                          threshold=threshold, p_new=p_new, min_gap=min_gap, verify=slam_verify(verify))
        if html is not None:
            from topoloc.evaluation.slam_html import build_slam_html

            typer.echo(f"wrote {build_slam_html(folder, html, progress=progress)}")
    rejected = len(result.params.get("rejected_by_verification", []))
    typer.echo(f"{result.n_images} images, {result.n_places} places, {len(result.loop_closures())} loop closures"
               + (f" ({rejected} rejected by verification)" if result.params.get("verify") else "") + "; "
               + ("discarded the files (--out /dev/null)" if is_discard(out) else
                  f"wrote {out}/posterior.npy, loop_closures.csv, loop_closures.png"))


@bench_app.command("fabmap2", cls=needs())
@handle_errors
def bench_fabmap2_cmd(
    places: Annotated[int, typer.Option(help="Places in the map.")] = 100000,
    words: Annotated[int, typer.Option(help="Vocabulary size.")] = 10000,
    words_per_image: Annotated[int, typer.Option(help="Words per image.")] = 300,
    queries: Annotated[int, typer.Option(help="Timed queries.")] = 200,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON line.")] = False,
    quiet: QuietOption = False,
) -> None:
    """FAB-MAP 2.0 (inverted index) ms per query on synthetic Zipf-distributed bag-of-words streams."""
    from topoloc.bench.fabmap_speed import bench_fabmap2

    for flag, value in (("--places", places), ("--words", words), ("--words-per-image", words_per_image),
                        ("--queries", queries)):
        at_least(flag, value, 1)
    res = bench_fabmap2(n_places=places, n_words=words, words_per_image=words_per_image, n_queries=queries,
                        seed=seed)
    _print_bench(res, as_json)


@bench_app.command("coocmap", cls=needs())
@handle_errors
def bench_coocmap_cmd(
    locations: Annotated[int, typer.Option(help="Locations in the map.")] = 2200,
    tours: Annotated[int, typer.Option(help="Training tours per location.")] = 5,
    features: Annotated[int, typer.Option(help="Features per image.")] = 500,
    words: Annotated[int, typer.Option(help="Vocabulary size.")] = 10000,
    queries: Annotated[int | None, typer.Option(help="Timed queries (default 20 synthetic, 500 real).")] = None,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON line.")] = False,
    real: Annotated[bool, typer.Option("--real", help="Locations from the images under DIRS (real features).")] = False,
    dirs: Annotated[list[Path] | None, typer.Argument(help="With --real: folders of images (recursive).")] = None,
    vocab_train: Annotated[
        list[Path] | None, typer.Option("--vocab-train", help="With --real: folders to train the vocabulary on.")
    ] = None,
    compare: Annotated[int, typer.Option(help="With --real: queries also timed with the previous matcher.")] = 20,
    cache_dir: CacheDirOption = None,
    quiet: QuietOption = False,
) -> None:
    """Cooc-Map ms per localisation and map memory at the paper's size: synthetic, or real images with --real DIR..."""
    from topoloc.bench.coocmap_speed import bench_coocmap, bench_coocmap_real

    for flag, value in (("--locations", locations), ("--tours", tours), ("--features", features),
                        ("--words", words), ("--queries", 1 if queries is None else queries)):
        at_least(flag, value, 1)
    at_least("--compare", compare, 0)
    if real or dirs:
        if not (real and dirs):
            raise TopolocError("bench coocmap: give --real and at least one folder of images")
        if not vocab_train:
            raise TopolocError("bench coocmap --real needs --vocab-train DIR (images other than the benchmark's)")
        with rich_progress(not (as_json or quiet)) as progress:
            res = bench_coocmap_real(list(dirs), locations=locations, tours=tours, n_queries=queries or 500,
                                     vocab_train=list(vocab_train), n_words=words, compare=compare, seed=seed,
                                     cache_dir=cache_dir, progress=progress)
    else:
        res = bench_coocmap(locations=locations, tours=tours, features=features, n_words=words,
                            n_queries=queries or 20, seed=seed)
    _print_bench(res, as_json)


def _print_bench(res: dict[str, Any], as_json: bool) -> None:
    if as_json:
        typer.echo(json.dumps(res, default=float))
    else:
        for k, v in res.items():
            typer.echo(f"{k}: {v}")


# The saved-map commands live in their own module; importing it registers them on `app`
# (it imports topoloc.cli.app, not this module, so there is no import cycle).
from topoloc.cli import maps as _maps  # noqa: E402, F401
from topoloc.cli import ros as _ros  # noqa: E402, F401


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":
    main()
