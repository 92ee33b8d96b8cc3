"""Precision-recall plots (matplotlib, no display needed)."""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from topoloc.errors import WriteError


def plot_pr_curves(
    curves: Sequence[tuple[str, np.ndarray, np.ndarray]], path: str | Path, title: str = ""
) -> None:
    """Draw ``(label, precision, recall)`` curves into one PNG at ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # Long run labels go in a legend below the axes; the saved image grows to hold it (tight bounding box).
    fig, ax = plt.subplots(figsize=(7.0, 4.5), dpi=110)
    for label, p, r in curves:
        # Long labels are wrapped, and the figure is saved with a tight bounding box: never cut off.
        ax.plot(r, p, label="\n    ".join(textwrap.wrap(label, width=100)) or label, linewidth=1.6)
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    if title:
        # Wrapped to the figure's width: a long run title is never cut at the right edge.
        ax.set_title("\n".join(textwrap.wrap(title, width=90)) or title, fontsize=9)
    if curves:
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12), frameon=False)
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp.png")
    try:
        fig.savefig(tmp, bbox_inches="tight", pad_inches=0.15)
        tmp.replace(path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise WriteError.of(path, exc) from None
    finally:
        plt.close(fig)
