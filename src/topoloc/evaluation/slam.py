"""Online FAB-MAP over a traverse and the files it leaves (``topoloc slam``).

The filter itself (:class:`topoloc.fabmap.slam.FabMapSlam`: motion-model prior,
likelihoods of Eq. 4-5, new-place term of Eq. 10, posterior of Eq. 3 with the
smoothing of Eq. 6, data association by Eq. 11) works on arrays of visual
words and a trained :class:`~topoloc.fabmap.model.FabMapModel`.
:func:`run_slam` binds it to a :class:`~topoloc.resources.Resources`
object: it quantises a traverse's features with the run's vocabulary, trains
the model on the vocabulary's training images (or loads a model file checked
against the vocabulary, :func:`load_fabmap_model`), runs the filter and writes
the outputs below.

Outputs (:func:`write_slam_outputs`), under ``out_dir``:

``posterior.npy``
    float64 (n_images, n_places + 1): row ``k`` holds the posterior over the
    places that existed when image ``k`` arrived (columns ``0..n_k - 1``, places
    numbered in creation order; NaN for places created later) and, in the
    **last column**, the probability of a new place.  Each row sums to 1 over
    its non-NaN entries.
``loop_closures.csv``
    header ``image,image_name,matched_image,matched_image_name,probability``:
    0-based image indices in traverse order (rows of ``posterior.npy``) and the
    images' file names (``1.jpg`` is index 0 in a folder numbered from 1);
    ``matched_image`` is the image that founded the matched place; one row per
    accepted loop closure (posterior >= ``threshold``, default 0.98).
``loop_closures.png``
    the loop-closure matrix: entry (k, j) is the posterior, at image ``k``, of
    the place founded by image ``j``; accepted loop closures are circled.
``assignments.csv``
    ``image,image_name,place,founder_image,founder_image_name,new_place,loop_closure``:
    the place each image was assigned to.
``slam.json``
    parameters and counts.

A FAB-MAP model file (:func:`save_fabmap_model`) is the versioned, checksummed,
atomically written container of :mod:`topoloc.io.container` (kind
``"fabmap_model"``) holding :meth:`FabMapModel.to_state`; it records the
vocabulary that produced its word ids, and :func:`load_fabmap_model` refuses it
with another vocabulary.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.datasets.traverse import Traverse, load_traverse
from topoloc.errors import TopolocError
from topoloc.fabmap.model import FabMapModel
from topoloc.fabmap.slam import FabMapSlam, SlamResult
from topoloc.io.container import atomic_write_bytes, read_container, write_container
from topoloc.methods.fab_map import train_model_from_resources
from topoloc.resources import Resources

MODEL_KIND = "fabmap_model"
MODEL_VERSION = 1


def save_fabmap_model(model: FabMapModel, path: str | Path) -> None:
    """Write ``model`` atomically to ``path`` (versioned container, module docstring)."""
    meta, arrays = model.to_state()
    write_container(path, MODEL_KIND, MODEL_VERSION, arrays, meta)


def load_fabmap_model(path: str | Path, *, vocabulary: Any = None) -> FabMapModel:
    """Read and validate a model written by :func:`save_fabmap_model`.

    Parameters
    ----------
    path : path-like
        The model file.
    vocabulary : Vocabulary, optional
        If given, the model must have been trained with it
        (:meth:`FabMapModel.check_vocabulary`).

    Raises
    ------
    TopolocError
        Missing, truncated, corrupted or inconsistent file, or another vocabulary.
    """
    meta, arrays = read_container(path, MODEL_KIND, MODEL_VERSION)
    model = FabMapModel.from_state(meta, arrays, path=path)
    if vocabulary is not None:
        model.check_vocabulary(vocabulary, path=path)
    return model


def load_or_train_model(
    model: FabMapModel | str | Path | None, resources: Resources | None = None
) -> FabMapModel:
    """A model given directly, loaded from a file (checked against the run's vocabulary),
    or trained from ``resources.training_words()``."""
    if isinstance(model, FabMapModel):
        return model
    voc = None
    if resources is not None and resources.has_vocabulary:
        voc = resources.vocabulary
    if model is not None and str(model):
        return load_fabmap_model(model, vocabulary=voc)
    if resources is None:
        raise TopolocError("FAB-MAP needs a trained model (model=...) or resources to train one")
    return train_model_from_resources(resources)


def run_slam(
    traverse: Traverse | str | Path,
    *,
    out_dir: str | Path,
    model: FabMapModel | str | Path | None = None,
    resources: Resources | None = None,
    words: Sequence[np.ndarray] | None = None,
    variant: str = "fabmap",
    threshold: float = 0.98,
    p_new: float = 0.9,
    min_gap: int = 10,
    naive_bayes: bool = False,
    normaliser: str = "sampled",
    n_samples: int = 1000,
    smoothing: float = 0.99,
    p_stay: float = 1.0 / 3.0,
    p_uniform: float = 0.01,
    bailout: bool = False,
    seed: int = 0,
    plot: bool = True,
    verify: bool = False,
) -> SlamResult:
    """Run online FAB-MAP over one traverse in order and write the outputs.

    Parameters
    ----------
    traverse : Traverse or path
        The images, processed in traverse order.
    out_dir : path
        Output folder (module docstring for the files).
    model : FabMapModel, path, or None
        Trained model, a saved model file (checked against ``resources.vocabulary``),
        or None to train on ``resources.training_words()``.
    resources : Resources, optional
        Provides ``words(traverse)`` (features quantised with the run's
        vocabulary), ``vocabulary`` and ``training_words()``.
    words : sequence of int arrays, optional
        Visual words of each image, instead of ``resources.words(traverse)``.
    variant, threshold, p_new, min_gap, naive_bayes, normaliser, n_samples, smoothing,
    p_stay, p_uniform, bailout, seed
        See :class:`~topoloc.fabmap.slam.FabMapSlam`.
    plot : bool
        Write ``loop_closures.png``.
    verify : bool
        Check each loop closure geometrically before accepting it
        (:mod:`topoloc.verification`: the image against the image that founded
        the place, with the local features of ``resources``); one that fails
        founds a new place instead.  ``slam.json`` counts them
        (``rejected_by_verification``).

    Returns
    -------
    SlamResult
    """
    tr = traverse if isinstance(traverse, Traverse) else load_traverse(traverse)
    if words is None:
        if resources is None:
            raise TopolocError("run_slam needs resources (features + vocabulary) or words")
        words = resources.words(tr)
    if len(words) != len(tr):
        raise TopolocError(f"got words for {len(words)} images but the traverse has {len(tr)}")
    fm = load_or_train_model(model, resources)
    check = None
    founders: list[int] = []  # the filter's, once it exists: the image that founded each place
    if verify:
        if resources is None:
            raise TopolocError("run_slam needs resources (local features) to verify loop closures")
        check = _loop_check(resources.features(tr), lambda place: founders[place])
    slam = FabMapSlam(
        fm, variant=variant, naive_bayes=naive_bayes, normaliser=normaliser,
        n_samples=n_samples, p_new=p_new, threshold=threshold, smoothing=smoothing,
        p_stay=p_stay, p_uniform=p_uniform, min_gap=min_gap, bailout=bailout, seed=seed, verify=check,
    )
    founders = slam.result.founders
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    # Loop closures are appended as they are found, so an interrupted run keeps what it found;
    # the complete outputs replace this file when the run ends.
    progress_csv = out / "loop_closures.partial.csv"
    with progress_csv.open("w", encoding="utf-8") as fh:
        fh.write("image,image_name,matched_image,matched_image_name,probability\n")
        for w in words:
            step = slam.step(w)
            if step.loop_closure:
                matched = slam.result.founders[step.place]
                fh.write(f"{step.image},{tr.images[step.image].name},{matched},{tr.images[matched].name},"
                         f"{step.probability:.6f}\n")
                fh.flush()
    result = slam.result
    # A recording is named by its file (an in-memory traverse's root is a placeholder).
    result.params["traverse"] = str(tr.source["file"]) if tr.source and "file" in tr.source else str(tr.root)
    result.params["images"] = [p.name for p in tr.images]
    extractor = getattr(resources, "extractor", None)
    if extractor is not None:  # which features the words came from (slam's default differs from evaluate's)
        result.params["features"] = extractor.config.descriptor_kind
    result.params["verify"] = bool(verify)
    if verify:
        result.params["rejected_by_verification"] = [[k, slam.result.founders[p] if p < len(slam.result.founders)
                                                      else -1] for k, p in slam.rejected]
    write_slam_outputs(result, out, plot=plot)
    progress_csv.unlink(missing_ok=True)
    return result


def _loop_check(features: Sequence[Any], founder: Any) -> Any:
    """``verify(image, place)`` for :class:`FabMapSlam`: the image against the place's founding image."""
    from topoloc.verification import Verifier

    checker = Verifier(lambda place: [features[founder(place)]])

    def verify(k: int, place: int) -> bool:
        return checker.is_verified(features[k], place)

    return verify


# Every file a run writes into its folder (the partial file is removed when the run ends).
SLAM_FILES = ("posterior.npy", "loop_closures.csv", "loop_closures.png", "assignments.csv", "slam.json",
              "loop_closures.partial.csv")


def write_slam_outputs(result: SlamResult, out_dir: str | Path, *, plot: bool = True) -> dict[str, Path]:
    """Write ``posterior.npy``, ``loop_closures.csv``, ``loop_closures.png``,
    ``assignments.csv`` and ``slam.json`` (module docstring) atomically.

    Returns
    -------
    dict of str to Path
        The files written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    buf = io.BytesIO()
    np.save(buf, result.posterior_matrix())
    paths["posterior"] = out / "posterior.npy"
    atomic_write_bytes(paths["posterior"], buf.getvalue())

    # Image indices are positions in the traverse, from 0 (rows of posterior.npy); the names are the files'.
    names = list(result.params.get("images") or [])

    def name(i: int) -> str:
        return str(names[i]) if 0 <= i < len(names) else ""

    text = io.StringIO()
    w = csv.writer(text, lineterminator="\n")
    w.writerow(["image", "image_name", "matched_image", "matched_image_name", "probability"])
    for img, matched, p in result.loop_closures():
        w.writerow([img, name(img), matched, name(matched), f"{p:.6f}"])
    paths["loop_closures"] = out / "loop_closures.csv"
    atomic_write_bytes(paths["loop_closures"], text.getvalue().encode("utf-8", "surrogateescape"))

    text = io.StringIO()
    w = csv.writer(text, lineterminator="\n")
    w.writerow(["image", "image_name", "place", "founder_image", "founder_image_name", "new_place", "loop_closure"])
    for s in result.steps:
        w.writerow([s.image, name(s.image), s.place, result.founders[s.place], name(result.founders[s.place]),
                    int(s.new_place), int(s.loop_closure)])
    paths["assignments"] = out / "assignments.csv"
    atomic_write_bytes(paths["assignments"], text.getvalue().encode("utf-8", "surrogateescape"))

    summary = {
        "n_images": result.n_images,
        "n_places": result.n_places,
        "n_loop_closures": len(result.loop_closures()),
        "params": result.params,
    }
    paths["summary"] = out / "slam.json"
    atomic_write_bytes(paths["summary"], (json.dumps(summary, indent=2) + "\n").encode("utf-8", "surrogateescape"))

    if plot:
        paths["plot"] = out / "loop_closures.png"
        atomic_write_bytes(paths["plot"], _plot_png(result))
    return paths


def _plot_png(result: SlamResult) -> bytes:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    m = result.loop_closure_matrix()
    fig, ax = plt.subplots(figsize=(6.4, 5.6), dpi=100)
    im = ax.imshow(m, cmap="viridis", vmin=0.0, vmax=1.0, origin="upper", interpolation="nearest")
    lc = result.loop_closures()
    if lc:
        ax.scatter([b for _, b, _ in lc], [a for a, _, _ in lc], s=30, facecolors="none",
                   edgecolors="red", linewidths=1.0, label="accepted loop closure")
        ax.legend(loc="lower left", fontsize=8)
    ax.set_xlabel("image that founded the place")
    ax.set_ylabel("image (time)")
    ax.set_title(f"FAB-MAP loop closures ({len(lc)} accepted, p >= {result.params.get('threshold')})")
    fig.colorbar(im, ax=ax, label="posterior p(L | Z^k)")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


__all__ = [
    "SLAM_FILES", "load_fabmap_model", "load_or_train_model", "run_slam", "save_fabmap_model", "write_slam_outputs",
]
