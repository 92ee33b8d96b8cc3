"""``topoloc demo``: the whole pipeline on a route the project generates itself.

A synthetic street is rendered on four tours at different times of day
(09:00, 13:00, 17:00 and 22:00).  A vocabulary is trained on a *different*
generated street (another seed), as the papers train on separate images.
Methods are evaluated through the same ``evaluate`` door as real data, and the
runs are put side by side in ``report.md`` and ``pr_curves.png``.

Synthetic data exercises the code; it is never used for published results.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from topoloc.evaluation.pipeline import evaluate
from topoloc.evaluation.report import build_report
from topoloc.methods import available_methods, get_method
from topoloc.progress import ProgressFactory

log = logging.getLogger(__name__)

DEMO_TOURS = (("tour_0900", 9.0), ("tour_1300", 13.0), ("tour_1700", 17.0), ("tour_2200", 22.0))
# What run_demo writes into its folder.
DEMO_FILES = ("route", "vocab_train", "runs", "cache", "report.md", "pr_curves.png")
VOCAB_WORDS = 1000
MAX_FEATURES = 1000


def _runs(route: Path) -> list[tuple[str, list[Path], Path]]:
    t = {name: route / name for name, _ in DEMO_TOURS}
    runs = [
        # One tour at noon as the map: later times of day must be recognised.
        ("bow", [t["tour_1300"]], t["tour_1700"]),
        ("bow", [t["tour_1300"]], t["tour_2200"]),
        # Tours throughout the day as the map: the Cooc-Map setting.
        ("bow", [t["tour_0900"], t["tour_1300"], t["tour_2200"]], t["tour_1700"]),
    ]
    extra = [m for m in ("coocmap", "fabmap", "seqslam") if m in available_methods()]
    for m in extra:
        runs.append((m, [t["tour_0900"], t["tour_1300"], t["tour_2200"]], t["tour_1700"]))
    return runs


def run_demo(out: Path, *, n_places: int = 60, progress: ProgressFactory | None = None) -> Path:
    """Generate the demo data, evaluate the methods and write ``out/report.md``."""
    from topoloc.synth import RouteConfig, generate_route

    out = Path(out)
    route = out / "route"
    train = out / "vocab_train"
    generate_route(route, config=RouteConfig(n_places=n_places, seed=0), tours=DEMO_TOURS)
    generate_route(train, config=RouteConfig(n_places=n_places, seed=1),
                   tours=(("tour_1000", 10.0), ("tour_2100", 21.0)))
    run_dirs = []
    for i, (method, maps, query) in enumerate(_runs(route)):
        run_dir = out / "runs" / f"{i:02d}_{method}_{query.name}"
        # Only methods that read visual words get the training folder: the others would warn that it is ignored.
        words: dict[str, Any] = (
            {"vocab_train": [train], "vocab_words": VOCAB_WORDS} if get_method(method).uses_vocabulary else {})
        evaluate(method=method, maps=maps, query=query, out=run_dir, max_features=MAX_FEATURES, tolerance="0:1",
                 cache_dir=out / "cache", progress=progress, **words)
        run_dirs.append(run_dir)
    return build_report(run_dirs, out, title="topoloc demo: synthetic street, tours at 9, 13, 17, 22 h")
