"""Online FAB-MAP: appearance-only SLAM with loop-closure detection (``topoloc slam``).

For every image of a traverse, in order (overview paper, Sec. 5):

1. **Location prior** (motion model): the belief over places after the
   previous step is moved along the *topological* adjacency of the map (two
   places are adjacent when they were observed at consecutive time steps):
   a place keeps ``p_stay`` of its mass and spreads the rest evenly over its
   neighbours (openFABMAP's default is a third each way on a chain); a small
   uniform part ``p_uniform`` allows unexpected jumps.  The map's places share
   ``1 - p_new``; the new-place hypothesis gets ``p_new``.
2. **Likelihoods** ``p(Z_k | L_i)`` of all places (Eq. 4-5; FAB-MAP 1.0 dense
   models or the FAB-MAP 2.0 inverted index) and the **new-place** term, sampled
   (Eq. 10) or mean-field.
3. **Posterior** (Eq. 3) after the smoothing of Eq. 6 (``smoothing`` = sigma).
4. **Data association**: if the most probable hypothesis is an existing place
   with posterior >= ``threshold``, the observation updates that place
   (Eq. 11); otherwise it starts a new place (prior + Eq. 11).  Several
   observations of one place are thus merged into one appearance model.

An accepted association is reported as a **loop closure** when the robot
arrives at a place last observed at least ``min_gap`` images earlier, and for
the following images as long as it stays at that place; associations with a
place seen within the last ``min_gap`` images are the robot lingering at the
same place, not closing a loop (as RTAB-Map excludes its short-term memory of
the last 10 images from loop-closure detection).

The default ``threshold`` is 0.98: with the smoothing of Eq. 6 at
``sigma = 0.99`` and ``p_new = 0.9`` (openFABMAP's defaults) every hypothesis keeps
a floor of ``(1 - sigma) / n_k`` of the likelihood, which caps the posterior of
a place in a map of a few dozen places at about 0.99, so a 0.99 threshold would
rarely be reachable there.

:class:`FabMapSlam` works on visual-word arrays and a trained model and returns
a :class:`SlamResult` (arrays: the posterior of every step, the assignments, the
loop closures); the maps it grows are those of :mod:`topoloc.fabmap.place_map`.
``topoloc slam`` runs it over a traverse through
:func:`topoloc.evaluation.slam.run_slam`, which supplies the words and the model
from the run's features and vocabulary and writes the result's files.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from topoloc._params import Constraint, Interval, validate_params
from topoloc.fabmap.model import FabMapModel
from topoloc.fabmap.observation import ObservationModel
from topoloc.fabmap.place_map import make_map
from topoloc.fabmap.posterior import location_posterior

# ---------------------------------------------------------------------------------------
# Location prior (motion model)
# ---------------------------------------------------------------------------------------


def motion_prior(
    belief: np.ndarray,
    edges: np.ndarray,
    *,
    p_stay: float = 1.0 / 3.0,
    p_uniform: float = 0.01,
) -> np.ndarray:
    """Location prior over the map's places from the previous belief (overview Sec. 5).

    Parameters
    ----------
    belief : ndarray, shape (n,)
        ``p(L_i | Z^{k-1})`` after the previous data association (sums to 1).
    edges : ndarray of int, shape (m, 2)
        Undirected topological adjacencies (unique pairs, ``i != j``).
    p_stay : float
        Probability of staying at the same place; the rest is split evenly
        among the neighbours (a place without neighbours keeps its mass).
    p_uniform : float
        Weight of a uniform distribution mixed in.

    Returns
    -------
    ndarray, shape (n,)
        The prior over the map's places (sums to 1; the caller scales it by
        ``1 - p_new``).
    """
    b = np.asarray(belief, dtype=np.float64)
    n = b.size
    if n == 0:
        return b.copy()
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    deg = np.bincount(e.ravel(), minlength=n).astype(np.float64)
    moving = np.where(deg > 0, 1.0 - p_stay, 0.0)
    out = b * (1.0 - moving)
    if e.size:
        share = np.divide(b * moving, deg, out=np.zeros(n), where=deg > 0)
        out += np.bincount(e[:, 1], weights=share[e[:, 0]], minlength=n)
        out += np.bincount(e[:, 0], weights=share[e[:, 1]], minlength=n)
    total = out.sum()
    out = out / total if total > 0 else np.full(n, 1.0 / n)
    return np.asarray((1.0 - p_uniform) * out + p_uniform / n)


# ---------------------------------------------------------------------------------------
# The filter
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SlamStep:
    """What happened at one image.

    Attributes
    ----------
    image : int
        0-based image index in traverse order.
    posterior : ndarray of float64, shape (n_places_before + 1,)
        Posterior over the places existing before this image, then the new place.
    place : int
        Place the image was assigned to.
    new_place : bool
        Whether that place was created by this image.
    loop_closure : bool
        Accepted association that closes a loop (module docstring).
    probability : float
        Posterior of the chosen hypothesis.
    """

    image: int
    posterior: np.ndarray
    place: int
    new_place: bool
    loop_closure: bool
    probability: float


@dataclass
class SlamResult:
    """All steps of a run (:func:`topoloc.evaluation.slam.write_slam_outputs` writes them as files)."""

    steps: list[SlamStep] = field(default_factory=list)
    founders: list[int] = field(default_factory=list)
    params: dict[str, Any] = field(default_factory=dict)

    @property
    def n_images(self) -> int:
        return len(self.steps)

    @property
    def n_places(self) -> int:
        return len(self.founders)

    @property
    def image_place(self) -> np.ndarray:
        """Place assigned to each image, shape (n_images,)."""
        return np.array([s.place for s in self.steps], dtype=np.int64)

    def loop_closures(self) -> list[tuple[int, int, float]]:
        """``(image, matched_image, probability)`` of every accepted loop closure."""
        return [(s.image, self.founders[s.place], s.probability) for s in self.steps
                if s.loop_closure]

    def posterior_matrix(self) -> np.ndarray:
        """The posterior of every step, (n_images, n_places + 1), NaN-padded, new place last (``posterior.npy``)."""
        out = np.full((self.n_images, self.n_places + 1), np.nan)
        for s in self.steps:
            n = s.posterior.size - 1
            out[s.image, :n] = s.posterior[:n]
            out[s.image, -1] = s.posterior[-1]
        return out

    def loop_closure_matrix(self) -> np.ndarray:
        """(n_images, n_images): posterior at image ``k`` of the place founded by image ``j``."""
        out = np.zeros((self.n_images, self.n_images))
        founders = np.asarray(self.founders, dtype=np.int64)
        for s in self.steps:
            n = s.posterior.size - 1
            if n:
                out[s.image, founders[:n]] = s.posterior[:n]
        return out


class FabMapSlam:
    """Online FAB-MAP filter (module docstring).

    Parameters
    ----------
    model : FabMapModel
        Trained model (training images, not the traverse).
    variant : {"fabmap", "fabmap2"}
        FAB-MAP 1.0 dense models or FAB-MAP 2.0 inverted index.
    naive_bayes : bool
        Ignore the Chow-Liu tree.
    normaliser : {"sampled", "mean_field"}
        New-place term (Eq. 10 or mean-field).
    n_samples : int
        Sampled training places (all if <= 0).
    p_new : float
        Prior probability of a new place, ``p(L_new | Z^{k-1})``.
    threshold : float
        Posterior needed to associate an observation with an existing place.
    smoothing : float
        ``sigma`` of Eq. 6 (1 = off).
    p_stay, p_uniform : float
        Motion model (:func:`motion_prior`).
    min_gap : int
        Associations with places seen within this many images are not loop closures.
    bailout : bool
        Bennett bail-out for the FAB-MAP 1.0 likelihoods.
    seed : int
    verify : callable, optional
        ``verify(image, place) -> bool``: a geometric check of a loop closure
        before it is accepted (``topoloc slam --verify``:
        :mod:`topoloc.verification` of the image against the place's founding
        image).  A loop closure that fails it is not made: the image founds a
        new place, as when the posterior stays below ``threshold`` (RTAB-Map
        and DLoopDetector reject an unverified loop the same way).  Places
        the image merely continues (the previous image's place) are not checked.
    """

    #: The filter's own parameters (``variant`` and ``normaliser``: :data:`~topoloc.fabmap.place_map.MAP_CONSTRAINTS`).
    parameter_constraints: Mapping[str, Constraint] = {
        "threshold": Interval(float, 0.0, 1.0, closed="right"), "p_new": Interval(float, 0.0, 1.0, closed="left"),
        "p_stay": Interval(float, 0.0, 1.0), "p_uniform": Interval(float, 0.0, 1.0),
    }

    def __init__(
        self,
        model: FabMapModel,
        *,
        variant: str = "fabmap",
        naive_bayes: bool = False,
        normaliser: str = "sampled",
        n_samples: int = 1000,
        p_new: float = 0.9,
        threshold: float = 0.98,
        smoothing: float = 0.99,
        p_stay: float = 1.0 / 3.0,
        p_uniform: float = 0.01,
        min_gap: int = 10,
        bailout: bool = False,
        seed: int = 0,
        verify: Callable[[int, int], bool] | None = None,
    ) -> None:
        validate_params("fabmap", {"threshold": threshold, "p_new": p_new, "p_stay": p_stay, "p_uniform": p_uniform},
                        self.parameter_constraints)
        self.obs_model = ObservationModel(model, naive_bayes=naive_bayes)
        self.map = make_map(self.obs_model, variant=variant, normaliser=normaliser,
                            n_samples=n_samples, seed=seed, bailout=bailout)
        self.map.prepare_normaliser()
        self.params: dict[str, Any] = {
            "variant": variant, "naive_bayes": naive_bayes, "normaliser": normaliser,
            "n_samples": n_samples, "p_new": p_new, "threshold": threshold,
            "smoothing": smoothing, "p_stay": p_stay, "p_uniform": p_uniform,
            "min_gap": min_gap, "bailout": bailout, "seed": seed,
            "p_fp": model.p_fp, "p_fn": model.p_fn,
        }
        self.p_new = p_new
        self.threshold = threshold
        self.smoothing = smoothing
        self.p_stay = p_stay
        self.p_uniform = p_uniform
        self.min_gap = int(min_gap)
        self.verify = verify
        self.rejected: list[tuple[int, int]] = []
        self.result = SlamResult(params=dict(self.params))
        self._belief = np.zeros(0)
        self._edges: set[tuple[int, int]] = set()
        self._edge_cache = np.zeros((0, 2), dtype=np.int64)
        self._last_seen: list[int] = []
        self._prev_place: int | None = None
        self._prev_closure = False

    def _edge_array(self) -> np.ndarray:
        if self._edge_cache.shape[0] != len(self._edges):
            self._edge_cache = np.array(sorted(self._edges), dtype=np.int64).reshape(-1, 2)
        return self._edge_cache

    def step(self, words: np.ndarray | Sequence[int]) -> SlamStep:
        """Process the next image's visual words; returns what happened."""
        k = self.result.n_images
        obs = self.obs_model.observe(words)
        n = self.map.n_places
        if n == 0:
            post = np.ones(1)
        else:
            prior = motion_prior(self._belief, self._edge_array(), p_stay=self.p_stay,
                                 p_uniform=self.p_uniform)
            ll, new_ll = self.map.log_likelihood_and_new(obs)
            post = location_posterior(ll, prior, new_ll, p_new=self.p_new,
                                      smoothing=self.smoothing)
        best = int(np.argmax(post[:n])) if n else -1
        accept = bool(n) and post[best] >= self.threshold
        if accept and self.verify is not None and best != self._prev_place \
                and k - self._last_seen[best] >= self.min_gap and not self.verify(k, best):
            self.rejected.append((k, best))  # a loop closure the geometry does not confirm
            accept = False
        if accept:
            place, is_new, prob = best, False, float(post[best])
            self.map.update(place, obs)
            if place == self._prev_place:
                closure = self._prev_closure  # a revisit continues while it stays at the place
            else:
                closure = k - self._last_seen[place] >= self.min_gap
            belief = post[:n].copy()
            belief[place] += post[n]  # the observation was assigned here
        else:
            place, is_new, prob, closure = self.map.add(obs), True, float(post[n]), False
            self.result.founders.append(k)
            self._last_seen.append(k)
            belief = post.copy()
        total = belief.sum()
        self._belief = belief / total if total > 0 else np.full(belief.size, 1.0 / belief.size)
        if self._prev_place is not None and self._prev_place != place:
            self._edges.add((min(self._prev_place, place), max(self._prev_place, place)))
        self._prev_place = place
        self._prev_closure = closure
        self._last_seen[place] = k
        s = SlamStep(image=k, posterior=post, place=place, new_place=is_new,
                     loop_closure=closure, probability=prob)
        self.result.steps.append(s)
        return s

    def run(self, word_lists: Sequence[np.ndarray]) -> SlamResult:
        """Process a whole traverse's images in order."""
        for w in word_lists:
            self.step(w)
        return self.result

