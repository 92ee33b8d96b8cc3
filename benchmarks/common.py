"""Shared helpers of the benchmark scripts: where the data is, running evaluate, tables, and prose.

The prose under a results table (:func:`prose`) is written from the runs' metrics.json and
``anchors.json``, so it changes with the numbers and is never typed by hand.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from topoloc.evaluation.report import build_report, run_title
from topoloc.io.container import atomic_write_bytes

# The results pages written before XFeat (issue #39) measure SIFT, the default features then; their benchmarks keep
# measuring SIFT unless TOPOLOC_FEATURES says otherwise (e.g. TOPOLOC_FEATURES=xfeat to redo a page with XFeat).
# benchmarks.bench_learned_features names its features on every run and is not affected.
os.environ.setdefault("TOPOLOC_FEATURES", "sift")
# Likewise the pages written before verification (issue #40) measure unverified answers unless TOPOLOC_VERIFY=1;
# benchmarks.bench_verification says --verify or --no-verify on every run.
os.environ.setdefault("TOPOLOC_VERIFY", "0")

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("TOPOLOC_DATA", REPO.parent / "shared" / "data")).resolve()
RESULTS = REPO / "docs" / "results"
TOPOLOC = Path(sys.executable).parent / "topoloc"
GP = DATA / "gardens_point"
WEBCAM = DATA / "webcam_daynight"
WEBCAM_TOURS = sorted((WEBCAM / "map").glob("tour_*"))

# The papers train their vocabularies on images apart from the evaluation data:
# gardens_point runs use a vocabulary trained on webcam_daynight's map tours and
# webcam_daynight runs one trained on all three gardens_point traverses.
VOCAB_FOR_GP = [WEBCAM / "map"]
VOCAB_FOR_WEBCAM = [GP]

GP_PAIRS = [("day_left", "day_right"), ("day_right", "night_right"), ("day_left", "night_right")]

#: The evaluation pairs several benchmarks share, by name (also the names of ../shared/scorecard's rows):
#: (map folders, query folder, vocabulary training folders, tolerance).
PAIRS: dict[str, tuple[list[Path], Path, list[Path], str]] = {
    "gp_day": ([GP / "day_left"], GP / "day_right", VOCAB_FOR_GP, "0:8"),
    "gp_night": ([GP / "day_right"], GP / "night_right", VOCAB_FOR_GP, "0:8"),
    "gp_night_2tours": ([GP / "day_left", GP / "day_right"], GP / "night_right", VOCAB_FOR_GP, "0:8"),
    "gp_day_2tours": ([GP / "day_left", GP / "night_right"], GP / "day_right", VOCAB_FOR_GP, "0:8"),
    "webcam": (WEBCAM_TOURS, WEBCAM / "queries", VOCAB_FOR_WEBCAM, "0:0"),
}


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The processor's model name (Linux's ``/proc/cpuinfo``), or the platform's processor string, or ""."""
    with contextlib.suppress(OSError):
        for line in cpuinfo.read_text(errors="replace").splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and value.strip():
                return value.strip()
    return platform.processor()


#: Headless browsers the HTML report is drawn and tested with (Debian's ``chromium`` first).
BROWSERS = ("chromium", "chromium-browser", "google-chrome")


def find_browser() -> str | None:
    """The path of the first of :data:`BROWSERS` on the PATH, or None."""
    return next((path for path in map(shutil.which, BROWSERS) if path), None)


def machine_line() -> str:
    """The machine a result was measured on, as results pages name it: architecture and processor, cores, Python.

    The processor is named because the same benchmark differs by more than its noise between machines of one
    architecture (an AMD EPYC without AVX-512 ran the verification stage 1.4x slower than the machine before it:
    verification.md, part ``speed``, on each).
    """
    model = cpu_model()
    arch = f"{platform.machine()} ({model})" if model else platform.machine()
    return f"{arch}, {os.cpu_count()} cores, Python {platform.python_version()}"


def write_results(md: Path, js: Path, res: dict[str, Any], text: str) -> None:
    """A benchmark's page ``md`` (its rendered ``text``) and the measurements behind it, ``js``, each written whole
    (:func:`topoloc.io.container.atomic_write_bytes`: a run killed while writing leaves the last page as it was)."""
    atomic_write_bytes(js, (json.dumps(res, indent=1) + "\n").encode())
    atomic_write_bytes(md, (text + "\n").encode())
    print(f"wrote {md}, {js}")


def _markers(name: str) -> tuple[str, str]:
    return f"<!-- begin {name}: generated -->\n", f"<!-- end {name} -->\n"


def write_section(path: Path, name: str, body: str) -> None:
    """Write ``body`` as the section ``name`` of the results page ``path``, between its markers.

    The section replaces the one of that name, or is appended; the rest of the page is kept, so that
    several benchmarks write one page (each regenerating its own part).
    """
    begin, end = _markers(name)
    text = path.read_text() if path.is_file() else ""
    block = begin + body.rstrip("\n") + "\n" + end
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        text = head + block + rest.split(end, 1)[1]
    else:
        text = text.rstrip("\n") + ("\n\n" if text else "") + block
    atomic_write_bytes(path, text.encode())


def marked_sections(path: Path) -> str:
    """Every marked section of ``path`` (:func:`write_section`), for a benchmark that rewrites the rest."""
    if not path.is_file():
        return ""
    text, out = path.read_text(), []
    while "<!-- begin " in text:
        start = text.index("<!-- begin ")
        name = text[start + len("<!-- begin "):].split(":", 1)[0]
        end = _markers(name)[1]
        if end not in text[start:]:
            break
        stop = text.index(end, start) + len(end)
        out.append(text[start:stop])
        text = text[stop:]
    return "".join(out)


def output_folder(path: Path, flag: str = "--out") -> Path:
    """``path`` checked as an output folder before any work (as the commands check theirs), and created.

    A benchmark that runs for minutes must not find at its end that it cannot write its result
    (issue #41: ``bench_cluster --out`` naming a folder that did not exist).  One line and exit 2.
    """
    from topoloc.errors import TopolocError
    from topoloc.io.dirs import check_output_dir

    try:
        check_output_dir(path)
        path.mkdir(parents=True, exist_ok=True)
    except (TopolocError, OSError) as exc:
        print(f"{flag}: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    return path


def require_data() -> None:
    if not GP.is_dir() or not WEBCAM.is_dir():
        raise SystemExit(f"shared data not found under {DATA} (set TOPOLOC_DATA)")


def run(method: str, maps: list[Path], query: Path, out: Path, *, vocab_train: list[Path],
        tolerance: str, params: dict[str, str] | None = None, sequence: int = 0,
        ground_truth: Path | None = None, options: list[str] | None = None) -> Path:
    """One `topoloc evaluate` run in its own process (so peak memory is per run); returns its folder.

    ``options`` are further `topoloc evaluate` arguments (e.g. ``["--preprocess", "clahe"]``).
    """
    cmd = [str(TOPOLOC), "evaluate", "--method", method, "--query", str(query), "--out", str(out),
           "--tolerance", tolerance, "--quiet"]
    for m in maps:
        cmd += ["--map", str(m)]
    for v in vocab_train:
        cmd += ["--vocab-train", str(v)]
    for k, value in (params or {}).items():
        cmd += ["--param", f"{k}={value}"]
    if sequence:
        cmd += ["--sequence", str(sequence)]
    if ground_truth is not None:
        cmd += ["--ground-truth", str(ground_truth)]
    cmd += options or []
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    m = json.loads((out / "metrics.json").read_text())
    print(f"{out.name}: AUC {m['auc']:.3f} R@1 {m['recall_at_1']:.3f} ms/q {m['ms_per_query']:.2f}", flush=True)
    return out


def load_anchors() -> dict[str, Any]:
    return dict(json.loads((REPO / "benchmarks" / "anchors.json").read_text()))


def _num(x: float | None) -> str:
    return "-" if x is None else f"{x:g}"


def _anchor_values(row: dict[str, Any], k: int) -> tuple[float | None, float | None, float | None]:
    """(AUC, R@100P, R@1) of anchor ``row`` on column ``k``; None where no source gives it."""
    auc, r1 = row["auc_r1"][k]
    r100p = (row.get("r100p") or [None] * len(row["auc_r1"]))[k]
    return auc, r100p, r1


def anchors_table(anchors: dict[str, Any] | None = None) -> str:
    a = anchors or load_anchors()
    lines = ["| system | " + " | ".join(f"{c} AUC / R@100P / R@1" for c in a["columns"]) + " |\n",
             "| --- |" + " --- |" * len(a["columns"]) + "\n"]
    for row in a["rows"]:
        cells = " | ".join(" / ".join(_num(v) for v in _anchor_values(row, k)) for k in range(len(a["columns"])))
        lines.append(f"| {row['system']} | {cells} |\n")
    return f"{a['source']} {a.get('r100p_source', '')}".strip() + "\n\n" + "".join(lines)


#: The anchors are quoted to two decimals, so a difference under half their last digit is no difference.
TIE = 0.005
METRICS = (("AUC", "auc"), ("R@100P", "recall_at_100_precision"), ("R@1", "recall_at_1"))
Values = tuple[float | None, ...]


def _label(m: dict[str, Any]) -> str:
    """The run's row label in the tables (method and the parameters that differ from its defaults)."""
    return "`" + run_title(m).rsplit(": ", 1)[0] + "`"


def _where(m: dict[str, Any]) -> tuple[str, tuple[str, ...], str]:
    """(dataset, map tour names, query name) of a run, from its metrics.json."""
    run = m.get("run", {})
    query = Path(run.get("query", "?"))
    return query.parent.name, tuple(Path(x).name for x in run.get("map", [])), query.name


def _maps_text(maps: tuple[str, ...], query: str) -> str:
    tours = " + ".join(maps) if len(maps) <= 3 else f"{len(maps)} map tours {maps[0]} + ... + {maps[-1]}"
    return f"{tours} -> {query}"


def _and(words: list[str]) -> str:
    return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " and " + words[-1]


def _fmt(values: Values, digits: int) -> str:
    return " / ".join("-" if v is None else f"{v:.{digits}f}" for v in values)


def compare_sentence(who: str, other: str, where: str, ours: Values, theirs: Values, *, digits: int = 3) -> str:
    """One plain sentence: does ``who`` beat or lose to ``other`` in AUC / R@100P / R@1 (None: not known)?

    A metric counts as beaten or lost when the two differ by at least :data:`TIE`.
    """
    verdict: dict[str, list[str]] = {"beats": [], "loses": [], "ties": []}
    for (name, _), a, b in zip(METRICS, ours, theirs, strict=True):
        if a is None or b is None:
            continue
        verdict["beats" if a - b >= TIE else "loses" if b - a >= TIE else "ties"].append(name)
    won, lost, tied = verdict["beats"], verdict["loses"], verdict["ties"]
    if won and lost:
        head = f"{who} beats {other} on {where} in {_and(won)} but loses in {_and(lost)}"
    elif lost:
        head = f"{who} loses to {other} on {where}"
    elif won:
        head = f"{who} beats {other} on {where}"
    else:
        head = f"{who} ties with {other} on {where}"
    if tied and (won or lost):
        head += f" (equal in {_and(tied)})"
    return f"{head}: AUC / R@100P / R@1 {_fmt(ours, 3)} against {_fmt(theirs, digits)}."


def metric_change(before: Path, after: Path) -> tuple[str, list[str]]:
    """``"AUC a -> b, R@100P ..., R@1 ..."`` from two runs' metrics.json, and the metrics ``after`` loses in.

    For ablation prose: one run beside the same run with one setting changed.
    """
    old, new = (json.loads((d / "metrics.json").read_text()) for d in (before, after))
    change = ", ".join(f"{name} {old[k]:.3f} -> {new[k]:.3f}" for name, k in METRICS)
    return change, [name for name, k in METRICS if new[k] < old[k]]


def best_anchor(anchors: dict[str, Any], column: int) -> tuple[Values, str]:
    """The best anchor value of each metric on ``column`` and who holds it.

    One system when it holds every best value, else each metric's holders; a named system is
    preferred to an aggregate row (the scorecard's best) holding the same value.
    """
    rows = anchors["rows"]
    values: list[float | None] = []
    holders: list[list[str]] = []
    for k in range(len(METRICS)):
        known = [(float(v), r) for r in rows if (v := _anchor_values(r, column)[k]) is not None]
        if not known:
            values.append(None)
            continue
        top = max(v for v, _ in known)
        at_top = [r for v, r in known if v == top]
        values.append(top)
        holders.append([r["name"] for r in ([r for r in at_top if not r.get("aggregate")] or at_top)])
    everywhere = [name for name in (holders[0] if holders else []) if all(name in h for h in holders)]
    if everywhere:
        return tuple(values), everywhere[0]
    known_names = [name for (name, _), v in zip(METRICS, values, strict=True) if v is not None]
    held = "; ".join(f"{name}: {_and(h)}" for name, h in zip(known_names, holders, strict=True))
    return tuple(values), f"the best anchors ({held})"


def prose(metrics: list[dict[str, Any]], anchors: dict[str, Any]) -> str:
    """Where each run of a table wins and loses, in sentences made from the runs' metrics (no typed numbers).

    A run with one map tour on a pair the anchors cover is compared with the best anchor of that
    pair; every other run (several map tours, or frames no anchor was measured on) only with the
    other runs on the same maps and query, led by the one with the highest AUC.

    Parameters
    ----------
    metrics : list of dict
        The ``metrics.json`` of each run, in table order.
    anchors : dict
        ``benchmarks/anchors.json``: ``dataset``, ``columns`` ("map -> query") and ``rows``.

    Returns
    -------
    str
        A markdown bullet list (empty when ``metrics`` is).
    """
    columns = {tuple(c.split(" -> ")): k for k, c in enumerate(anchors["columns"])}
    anchored: list[str] = []
    groups: dict[tuple[str, tuple[str, ...], str], list[dict[str, Any]]] = {}
    for m in metrics:
        dataset, maps, query = _where(m)
        ours = tuple(float(m[key]) for _, key in METRICS)
        k = columns.get((*maps, query)) if len(maps) == 1 and dataset == anchors["dataset"] else None
        if k is None:
            groups.setdefault((dataset, maps, query), []).append(m)
            continue
        theirs, who = best_anchor(anchors, k)
        anchored.append(compare_sentence(_label(m), who, f"{dataset} {_maps_text(maps, query)}", ours, theirs,
                                         digits=2))
    lines = [f"- {s}\n" for s in anchored]
    for (dataset, maps, query), rows in groups.items():
        where = f"{dataset} {_maps_text(maps, query)}"
        why = ("several map tours: not comparable with the single-tour anchors"
               if len(maps) > 1 and dataset == anchors["dataset"] else "no anchor measured on these frames")
        if len(rows) == 1:
            lines.append(f"- {_label(rows[0])} is the only row on {where} ({why}).\n")
            continue
        lead = max(rows, key=lambda r: float(r["auc"]))
        lv = tuple(float(lead[key]) for _, key in METRICS)
        lines.append(f"- On {where} ({why}; compared only with the other rows on the same maps) the highest AUC "
                     f"is {_label(lead)}'s: AUC / R@100P / R@1 {_fmt(lv, 3)}.\n")
        for m in rows:
            if m is not lead:
                ours = tuple(float(m[key]) for _, key in METRICS)
                lines.append(f"- {compare_sentence(_label(m), _label(lead), where, ours, lv)}\n")
    return "".join(lines)


def prose_for(run_dirs: list[Path]) -> str:
    """:func:`prose` of the ``evaluate`` folders ``run_dirs`` against ``benchmarks/anchors.json``."""
    return prose([json.loads((Path(d) / "metrics.json").read_text()) for d in run_dirs], load_anchors())


def report(run_dirs: list[Path], out: Path, title: str) -> Path:
    return build_report(run_dirs, out, title=title)


def report_table(run_dirs: list[Path], out: Path, title: str) -> str:
    """Write the side-by-side report of ``run_dirs`` under ``out``; return just its markdown table."""
    return report(run_dirs, out, title).read_text().split("\n", 2)[2].split("\nRuns:")[0]


def gardens_section(run_dirs: list[Path], name: str, title: str) -> str:
    """Table of gardens_point runs, their PR-curve PNG (under ``docs/results/<name>``), the anchors and the prose."""
    return (report_table(run_dirs, RESULTS / name, title) + f"\n![PR curves]({name}/pr_curves.png)\n\n"
            + "### Anchors on the same data\n\n" + anchors_table()
            + "\n### Where each row wins and loses (written from the runs' metrics.json)\n\n" + prose_for(run_dirs))


def keep_sections(path: Path, text: str) -> str:
    """``text`` with the marked sections (:func:`write_section`) of the page now at ``path`` that it lacks appended."""
    old = marked_sections(path)
    while "<!-- begin " in old:
        start = old.index("<!-- begin ")
        name = old[start + len("<!-- begin "):].split(":", 1)[0]
        begin, end = _markers(name)
        stop = old.index(end, start) + len(end)
        if begin not in text:
            text = text.rstrip("\n") + "\n\n" + old[start:stop]
        old = old[stop:]
    return text


@contextlib.contextmanager
def environ(**values: str | None) -> Iterator[None]:
    """``os.environ`` with ``values`` set for the block (a value None leaves that one as it is), restored after:
    this process and the commands it starts see them."""
    given = {k: v for k, v in values.items() if v is not None}
    before = {k: os.environ.get(k) for k in given}
    os.environ.update(given)
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
