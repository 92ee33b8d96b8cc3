"""Online FAB-MAP over a traverse with the run's shared resources (``topoloc slam``).

The filter itself (:class:`topoloc.fabmap.slam.FabMapSlam`: motion-model prior,
likelihoods of Eq. 4-5, new-place term of Eq. 10, posterior of Eq. 3 with the
smoothing of Eq. 6, data association by Eq. 11) works on arrays of visual
words and a trained :class:`~topoloc.fabmap.model.FabMapModel`.  This adapter
binds it to a :class:`~topoloc.methods.resources.Resources` object: it quantises a
traverse's features with the run's vocabulary, trains the model on the
vocabulary's training images (or loads a saved model checked against the
vocabulary), runs the filter and writes the outputs described in
:mod:`topoloc.fabmap.slam`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from topoloc.datasets.traverse import Traverse, load_traverse
from topoloc.errors import TopolocError
from topoloc.fabmap.model import FabMapModel
from topoloc.fabmap.slam import FabMapSlam, SlamResult, write_slam_outputs
from topoloc.methods.resources import Resources
from topoloc.progress import stage


def train_model_from_resources(resources: Resources, **kwargs: Any) -> FabMapModel:
    """Train a model on ``resources.training_words()`` with ``resources.vocabulary``.

    Raises
    ------
    TopolocError
        If the resources cannot provide training images.
    """
    words = resources.training_words()
    if len(words) < 2:
        raise TopolocError(
            "FAB-MAP needs at least 2 training images that are not the map: pass --vocab-train DIR"
        )
    voc = resources.vocabulary
    with stage(resources.progress, f"FAB-MAP model: Chow-Liu tree on {len(words)} training images"):
        return FabMapModel.train(list(words), n_words=int(voc.n_words_), vocabulary=voc, **kwargs)


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
        return FabMapModel.load(model, vocabulary=voc)
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
        See :class:`FabMapSlam`.
    plot : bool
        Write ``loop_closures.png``.

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
    slam = FabMapSlam(
        fm, variant=variant, naive_bayes=naive_bayes, normaliser=normaliser,
        n_samples=n_samples, p_new=p_new, threshold=threshold, smoothing=smoothing,
        p_stay=p_stay, p_uniform=p_uniform, min_gap=min_gap, bailout=bailout, seed=seed,
    )
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
    result.params["traverse"] = str(tr.root)
    result.params["images"] = [p.name for p in tr.images]
    write_slam_outputs(result, out, plot=plot)
    progress_csv.unlink(missing_ok=True)
    return result
