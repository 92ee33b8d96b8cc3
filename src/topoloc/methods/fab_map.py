"""FAB-MAP (Cummins & Newman) as a localisation method: ``--method fabmap`` / ``fabmap2``.

* **Training** (:mod:`topoloc.fabmap.model`): word marginals and the Chow-Liu
  tree are learned from the vocabulary's training images
  (``resources.training_words()``), never from the map.  A fitted method,
  model included, is kept in a map file (``topoloc map build``,
  :class:`~topoloc.maps.Map`).
* **Map**: every map image is an observation of its place.  With
  ``tours="separate"`` (default) each image is its own appearance model (prior
  + Eq. 11) and a place scores its best image; with ``tours="merge"`` the first
  observation of a place creates its model and the following ones (other
  images or other map traverses of the same place id) update it with Eq. 11,
  so several map traverses merge into one model per place.  ``fabmap`` keeps dense FAB-MAP 1.0 models; ``fabmap2`` keeps
  FAB-MAP 2.0 two-level models in an inverted index.
* **Scores** ``S`` (rows = sorted map place ids, columns = query images):

  - ``output="loglik"`` (default): ``log p(Z_q | L_i)`` (Eq. 4-5, natural log),
    the quantity FAB-MAP ranks places by;
  - ``output="posterior"``: ``p(L_i | Z_q)`` of Eq. 3 with a uniform location
    prior over the map (queries are independent), the new-place hypothesis of
    prior ``p_new`` normalised by Eq. 10 (``normaliser="sampled"``) or
    mean-field, and the smoothing of Eq. 6 (``smoothing``).  Columns sum to
    ``1 - p(new place)``: a query unlike every map place scores low everywhere,
    which makes one acceptance threshold meaningful across queries.
  - ``output="logodds"``: the same posterior as ``log p / (1 - p)`` of each
    place, computed in the log domain: a probability rounds to exactly 1 once
    the best place leads the rest by a few dozen nats, so confident queries
    tie at the top of a PR curve; the log-odds keep them apart.

Parameters (keyword-only, ``--param KEY=VALUE``): ``output``,
``naive_bayes`` (ignore the Chow-Liu tree), ``normaliser``, ``n_samples``,
``p_new``, ``smoothing``, ``p_fp`` / ``p_fn`` (detector model, Eq. 2),
``bailout`` / ``p_bailout`` (Bennett bail-out, ``fabmap`` only), ``seed``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np

from topoloc._params import Constraint, Interval, OfType, Options
from topoloc.confidence import CONFIDENCE_MODES
from topoloc.datasets.traverse import Traverse
from topoloc.errors import ParameterError, TopolocError
from topoloc.fabmap.model import DEFAULT_P_FN, DEFAULT_P_FP, FabMapModel
from topoloc.fabmap.observation import Observation, ObservationModel
from topoloc.fabmap.place_map import DenseMap, IndexMap, make_map
from topoloc.fabmap.posterior import location_log_odds, location_posterior
from topoloc.io.state import object_state, restore_state
from topoloc.methods.base import PlaceRecognizer
from topoloc.methods.shards import ShardPart, merge_order
from topoloc.progress import stage
from topoloc.resources import Resources

OUTPUTS = ("loglik", "posterior", "logodds")
#: Outputs that are FAB-MAP's own confidence (Eq. 3) and are returned without the margin.
_POSTERIORS = ("posterior", "logodds")


class FabMap(PlaceRecognizer):
    """FAB-MAP 1.0: Chow-Liu appearance model with dense place models.

    Parameters
    ----------
    output : {"loglik", "posterior", "logodds"}
        What ``S`` holds (module docstring).
    naive_bayes : bool
        Naive-Bayes likelihood instead of the Chow-Liu tree.
    normaliser : {"sampled", "mean_field"}
        New-place term for ``output="posterior"`` (Eq. 10 / mean-field).
    n_samples : int
        Training images used as sampled places (0 = all).
    p_new : float
        Prior of a new place for ``output="posterior"``.
    smoothing : float
        ``sigma`` of Eq. 6 for ``output="posterior"`` (1 = off).
    p_fp, p_fn : float
        Detector false-positive ``p(z=1|e=0)`` and false-negative ``p(z=0|e=1)`` (Eq. 2).
    bailout : bool
        Bennett bail-out evaluation (``fabmap`` only): places that cannot win
        get a surrogate score below the leader.
    p_bailout : float
        Bail-out probability bound.
    seed : int
        Seed of the sampled places.
    tours : {"separate", "merge"}
        ``"separate"`` (default): every map image keeps its own model, as
        openFABMAP does with one tour image per place; a place scores its best
        image (``loglik``) or the sum of its images' posteriors (``posterior``:
        the probability of being at the place).  ``"merge"`` (the paper): all
        images of a place, from every map tour, update one appearance model
        (Eq. 11), which averages day and night away.  Identical when every
        place has one map image.  Default chosen on the development data
        (``benchmarks/bench_fabmap.py``, docs/results/fabmap.md, default
        features and confidence): fabmap2 on webcam_daynight with all 12
        tours, R@1 0.519 merged, 0.807 separate; gardens_point day_left +
        night_right -> day_right R@1 0.50 merged, 0.45 separate, but R@100P
        0.00 merged, 0.18 separate; day_left + day_right -> night_right R@1
        0.15 merged, 0.16 separate.  ``"separate"`` is openFABMAP's setting:
        on the same words openFABMAP 2.0 ranks the same map image first on
        every webcam query (docs/results/fabmap_openfabmap.md,
        ``benchmarks/bench_fabmap_openfabmap.py``).  Maps saved before this
        parameter existed load with ``"merge"`` (``legacy_defaults``).
    confidence : {"margin", "raw"}
        ``"margin"`` (default): each query's column is shifted so that its
        best score is its margin over the best place outside the best
        place's peak, a confidence comparable across queries (same order
        within a column; :mod:`topoloc.confidence`); with
        ``output="posterior"`` or ``"logodds"`` the posterior is kept, it is FAB-MAP's own confidence.
        ``"raw"``: what ``output`` says.

    Attributes
    ----------
    place_ids_ : ndarray of int64, shape (n_places,)
    model_row_ : ndarray of int64, shape (n_models,)
        Row of ``S`` of each appearance model (one per place, or per image with ``tours="separate"``).
    """

    name: ClassVar[str] = "fabmap"
    uses_vocabulary: ClassVar[bool] = True
    variant: ClassVar[str] = "fabmap"
    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {
        "output": Options(OUTPUTS), "naive_bayes": OfType(bool),
        "normaliser": Options(("sampled", "mean_field")), "n_samples": Interval(int, 0),
        "p_new": Interval(float, 0.0, 1.0, closed="left"), "smoothing": Interval(float, 0.0, 1.0, closed="right"),
        "p_fp": Interval(float, 0.0, 1.0, closed="neither"), "p_fn": Interval(float, 0.0, 1.0, closed="neither"),
        "bailout": OfType(bool), "p_bailout": Interval(float, 0.0, 1.0, closed="neither"), "seed": Interval(int),
        "tours": Options(("merge", "separate")), "confidence": Options(CONFIDENCE_MODES),
    }
    #: A map saved before ``tours`` existed merged every tour into one model per place.
    legacy_defaults: ClassVar[Mapping[str, Any]] = {**PlaceRecognizer.legacy_defaults, "tours": "merge"}
    # A fitted method has one way to be kept: its map file.
    removed_params: ClassVar[Mapping[str, str]] = {"model_path": (
        "a fitted FAB-MAP, model included, is kept in a map file: `topoloc map build --method fabmap ... "
        "--out FILE` or `Map.build(...).save(path)`, reopened with `Map.load(path)`")}

    def __init__(
        self,
        *,
        output: str = "loglik",
        naive_bayes: bool = False,
        normaliser: str = "sampled",
        n_samples: int = 1000,
        p_new: float = 0.9,
        smoothing: float = 1.0,
        p_fp: float = DEFAULT_P_FP,
        p_fn: float = DEFAULT_P_FN,
        bailout: bool = False,
        p_bailout: float = 1e-6,
        seed: int = 0,
        tours: str = "separate",
        confidence: str = "margin",
    ) -> None:
        self.output = output
        self.naive_bayes = naive_bayes
        self.normaliser = normaliser
        self.n_samples = n_samples
        self.p_new = p_new
        self.smoothing = smoothing
        self.p_fp = p_fp
        self.p_fn = p_fn
        self.bailout = bailout
        self.p_bailout = p_bailout
        self.seed = seed
        self.tours = tours
        self.confidence = confidence

    def _fit(self, maps: list[Traverse], resources: Resources) -> None:
        """Train the model and build one appearance model per map place."""
        model = train_model_from_resources(resources)
        if (model.p_fp, model.p_fn) != (self.p_fp, self.p_fn):
            model = model.with_detector(p_fp=self.p_fp, p_fn=self.p_fn)
        self.model_ = model
        words = [np.asarray(w, np.int64) for tr in maps for w in resources.words(tr)]
        self.obs_ptr_ = np.r_[0, np.cumsum([len(w) for w in words])].astype(np.int64)
        self.obs_words_ = np.concatenate(words) if words else np.zeros(0, np.int64)
        self.obs_places_ = np.concatenate([tr.places for tr in maps]).astype(np.int64)
        self._build_places()

    def _add_tour(self, tour: Traverse, resources: Resources) -> None:
        """The tour's images are further observations of their places (Eq. 11); unseen places become new places.

        Observations are kept per image, in the order tours were given, so the
        place models equal those of fitting on all tours at once.
        """
        words = [np.asarray(w, np.int64) for w in resources.words(tour)]
        ends = self.obs_ptr_[-1] + np.cumsum([len(w) for w in words])
        self.obs_ptr_ = np.r_[self.obs_ptr_, ends].astype(np.int64)
        self.obs_words_ = np.concatenate([self.obs_words_, *words]).astype(np.int64)
        self.obs_places_ = np.concatenate([self.obs_places_, tour.places]).astype(np.int64)
        self._build_places()

    def _fit_shard(self, maps: list[Traverse], shard: list[Traverse], positions: np.ndarray,
                   resources: Resources) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The shard's observations (word ids of each image) and their places; no model is trained here."""
        words = [np.asarray(w, np.int64) for tr in shard for w in resources.words(tr)]
        return {}, {"ptr": np.r_[0, np.cumsum([len(w) for w in words])].astype(np.int64),
                    "words": np.concatenate(words) if words else np.zeros(0, np.int64),
                    "places": np.concatenate([tr.places for tr in shard]).astype(np.int64)}

    def _merge_shards(self, parts: list[ShardPart], maps: list[Traverse], resources: Resources) -> None:
        """Observations back in map order, the model trained once, place models as in ``fit``."""
        order = merge_order(parts, sum(len(m) for m in maps))
        lists = [np.split(p.arrays["words"], p.arrays["ptr"][1:-1]) for p in parts]
        words = [w for part in lists for w in part]
        words = [words[i] for i in order]
        model = train_model_from_resources(resources)
        if (model.p_fp, model.p_fn) != (self.p_fp, self.p_fn):
            model = model.with_detector(p_fp=self.p_fp, p_fn=self.p_fn)
        self.model_ = model
        self.obs_ptr_ = np.r_[0, np.cumsum([len(w) for w in words])].astype(np.int64)
        self.obs_words_ = np.concatenate(words) if words else np.zeros(0, np.int64)
        self.obs_places_ = np.concatenate([p.arrays["places"] for p in parts])[order].astype(np.int64)
        self._build_places()

    def _build_places(self) -> None:
        """Place appearance models from the stored observations: prior + Eq. 11 per observation."""
        om = ObservationModel(self.model_, naive_bayes=self.naive_bayes)
        place_ids = np.unique(self.obs_places_)
        rows = np.searchsorted(place_ids, self.obs_places_)
        if self.tours == "separate":
            # One model per image, grouped by place (stable: map order within a place).
            order = np.argsort(rows, kind="stable")
            model_row = rows[order]
        else:
            order = np.arange(len(rows))
            model_row = np.arange(place_ids.size)
        # all observations of each model, in map order (traverse by traverse)
        per_place: list[list[Observation]] = [[] for _ in range(len(model_row))]
        for k, i in enumerate(order):
            w = self.obs_words_[self.obs_ptr_[i]:self.obs_ptr_[i + 1]]
            per_place[k if self.tours == "separate" else int(rows[i])].append(om.observe(w))
        self.model_row_ = model_row.astype(np.int64)
        self._starts = np.flatnonzero(np.r_[True, model_row[1:] != model_row[:-1]])
        pmap = make_map(om, variant=self.variant, normaliser=self.normaliser,
                        n_samples=self.n_samples, seed=self.seed, bailout=self.bailout,
                        p_bailout=self.p_bailout)
        if isinstance(pmap, IndexMap):
            pmap.build(per_place)
        else:
            _build_dense(pmap, om, per_place)
        if self.output in _POSTERIORS:
            pmap.prepare_normaliser()  # not inside the timed queries
        self.obs_model_ = om
        self.map_ = pmap
        self.place_ids_ = place_ids

    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        # The Chow-Liu model and every map observation; the place models follow from them (Eq. 11).
        meta, arrays = object_state(self, only=["obs_ptr_", "obs_words_", "obs_places_"])
        model_meta, model_arrays = self.model_.to_state()
        return {**meta, "model": model_meta}, {**arrays, **{f"model/{k}": v for k, v in model_arrays.items()}}

    def _set_state(self, meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> None:
        restore_state(self, meta, arrays)
        model_arrays = {k.removeprefix("model/"): v for k, v in arrays.items() if k.startswith("model/")}
        self.model_ = FabMapModel.from_state(dict(meta["model"]), model_arrays)
        self._build_places()

    def _encode(self, query: Traverse, resources: Resources) -> list[Any]:
        """Visual-word ids of each query image (sorted, unique, int32)."""
        return [np.unique(np.asarray(w, dtype=np.int64)).astype(np.int32)
                for w in resources.words(query)]

    def _confident(self, S: np.ndarray) -> np.ndarray:
        """The margin of log-likelihoods; a posterior (``output="posterior"``) is returned as it is.

        A posterior is FAB-MAP's own confidence, a probability and so comparable
        across queries; shifting probabilities that span dozens of orders of
        magnitude would also round the small ones to ties in float32, which
        changes which row is best once the metrics mask the best one.
        """
        if self.output in _POSTERIORS:
            return S
        return super()._confident(S)

    def _score(self, items: Sequence[Any]) -> np.ndarray:
        """``S`` of shape (n_map_places, len(items)): log-likelihood or posterior."""
        n_models = len(self.model_row_)
        grouped = n_models != len(self.place_ids_)
        # Log-odds are formed per place (a place's images summed in the log domain), the others per model.
        S = np.empty((len(self.place_ids_) if self.output == "logodds" else n_models, len(items)), dtype=np.float32)
        for j, words in enumerate(items):
            obs = self.obs_model_.observe(words)
            if self.output == "loglik":
                S[:, j] = self.map_.log_likelihood(obs)
                continue
            ll, new_ll = self.map_.log_likelihood_and_new(obs)
            if self.output == "posterior":
                S[:, j] = location_posterior(ll, None, new_ll, p_new=self.p_new,
                                             smoothing=self.smoothing)[:n_models]
            else:
                S[:, j] = location_log_odds(ll, None, new_ll, p_new=self.p_new, smoothing=self.smoothing,
                                            starts=self._starts if grouped else None)
        if grouped and self.output != "logodds":
            # Several models per place: the place's probability, or its best image's likelihood.
            reduce = np.add if self.output == "posterior" else np.maximum
            S = reduce.reduceat(S, self._starts, axis=0)
        return S


class FabMap2(FabMap):
    """FAB-MAP 2.0: the same model with two-level place models and an inverted index.

    Parameters are those of :class:`FabMap` (``bailout`` is ignored: the index
    already only touches the words whose state differs from their default).
    """

    name: ClassVar[str] = "fabmap2"
    variant: ClassVar[str] = "fabmap2"


def train_model_from_resources(resources: Resources, **kwargs: Any) -> FabMapModel:
    """Train a model on ``resources.training_words()`` with ``resources.vocabulary``.

    Raises
    ------
    TopolocError
        If the resources cannot provide training images.
    """
    words = resources.training_words()
    if len(words) < 2:
        raise ParameterError("vocabulary.train", "needs at least 2 training images that are not the map: FAB-MAP "
                                                 "learns its word statistics from them")
    voc = resources.vocabulary
    with stage(resources.progress, f"FAB-MAP model: Chow-Liu tree on {len(words)} training images"):
        return FabMapModel.train(list(words), n_words=int(voc.n_words_), vocabulary=voc, **kwargs)


def _build_dense(pmap: DenseMap, om: ObservationModel, per_place: list[list[Observation]]) -> None:
    """Dense place models in place-id order: prior + Eq. 11 for each observation."""
    block: list[np.ndarray] = []
    for obs_list in per_place:
        if not obs_list:  # pragma: no cover - map_place_ids only lists observed places
            raise TopolocError("a map place has no image")
        e = om.new_place(obs_list[0])
        for o in obs_list[1:]:
            e = om.update(e, o)
        block.append(e)
        if len(block) == 256:
            pmap.add_beliefs(np.stack(block))
            block = []
    if block:
        pmap.add_beliefs(np.stack(block))


__all__ = ["FabMap", "FabMap2", "FabMapModel"]
