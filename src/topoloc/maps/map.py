"""A saved map: built once from one or more tours, queried many times, extended with later tours.

:class:`Map` binds a fitted recogniser to everything needed to use it again in
another process: the feature settings, the vocabulary (embedded), the place
ids with their positions, the tours it was built from, and the calibrated
acceptance threshold.  ``Map.build`` fits, ``save``/``load`` go through one
:mod:`map file <topoloc.maps.mapfile>`, ``localize`` takes a camera frame (a
NumPy array) and returns the place it shows with a confidence, and
``add_tour`` extends the map the way each method's paper updates its model.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from topoloc._parallel import n_workers
from topoloc.cluster import Executor
from topoloc.datasets.groundtruth import GroundTruth
from topoloc.datasets.traverse import Traverse, check_distinct_tours, load_traverse
from topoloc.errors import ParameterError, TopolocError, input_error
from topoloc.features import FeatureConfig
from topoloc.features.local import check_method_available
from topoloc.io.lock import file_lock
from topoloc.io.scratch import spill_to
from topoloc.maps import calibration as _cal
from topoloc.maps import verify_policy as _policy
from topoloc.maps.calibration import check_precision
from topoloc.maps.confusion import Confusion
from topoloc.maps.localizer import Localizer
from topoloc.maps.mapfile import STATE_PREFIX, read_map_file, write_map_file
from topoloc.maps.place_images import PlaceImages
from topoloc.maps.tour_images import TourImages
from topoloc.maps.tours import (
    check_feature_kind,
    header_record,
    reload_tour,
    tour_record,
    tour_root,
    xy_sums,
)
from topoloc.methods import get_method
from topoloc.methods.base import PlaceRecognizer, map_place_ids
from topoloc.methods.shard_build import build_from_shards
from topoloc.progress import ProgressFactory
from topoloc.resources import CachedResources, InMemoryResources, Resources
from topoloc.spec import (
    FeatureSpec,
    GroundTruthSpec,
    LocalizeSpec,
    MapBuildSpec,
    NodeSpec,
    SequenceSpec,
    VerificationSpec,
    VocabularySpec,
    spec_to_dict,
)
from topoloc.spec.parts import NOT_BOTH, VerifyChoice
from topoloc.spec.setup import build_method, build_verifier, make_resources
from topoloc.verification import DEFAULT_CONFIDENCE, ConfidenceModel, LookAlikes, Verifier
from topoloc.vocabulary import Vocabulary
from topoloc.vocabulary.vocab import vocabulary_fingerprint

log = logging.getLogger(__name__)

#: The array of a map file holding its confusion (:mod:`topoloc.maps.confusion`).
CONFUSION_ARRAY = "verification/confusion"
#: ... and the arrays of its look-alike places (:class:`topoloc.verification.LookAlikes`): rows, then support.
LOOK_ALIKE_ARRAYS = ("verification/look_alikes", "verification/look_alike_support")


class Map:
    """A fitted recogniser with everything needed to localise against it later.

    Build with :meth:`build`, reopen with :meth:`load`.

    Attributes
    ----------
    recognizer : PlaceRecognizer
        The fitted method.
    features : FeatureConfig
        Feature settings of every map image (queries use the same).
    vocabulary : Vocabulary or None
    tours : list of dict
        What the map was built from (:func:`tour_record`), in the order added.
    place_xy : ndarray of float64, shape (n_places, 2)
        Mean position of each place in metres over the map images that have
        one (NaN where none has).
    spec : dict or None
        How it was built (:func:`topoloc.spec.spec_to_dict` of a
        :class:`~topoloc.spec.MapBuildSpec`); None for maps saved before it was recorded.
    calibration : dict or None
        ``{"threshold", "precision", "recall", "query", "ground_truth", "date"}``
        from :meth:`calibrate`; without it every localisation is accepted, and
        with a null ``threshold`` (no threshold reached the precision) none is.
    path : Path or None
        The file it was loaded from or last saved to.
    confusion : Confusion or None
        How much support look-alike places of the map reach at each place, learned at build
        (:mod:`topoloc.maps.confusion`); None for maps saved before it was, or built without verification.
    """

    def __init__(self, recognizer: PlaceRecognizer, *, features: FeatureConfig, vocabulary: Vocabulary | None,
                 tours: list[dict[str, Any]], xy_sums: np.ndarray, calibration: dict[str, Any] | None = None,
                 created: str | None = None, path: Path | None = None, spec: dict[str, Any] | None = None,
                 confusion: Confusion | None = None) -> None:
        self.recognizer = recognizer
        self.confusion = confusion
        self.spec = spec
        self.features = features
        self.vocabulary = vocabulary
        self.tours = tours
        self.xy_sums = np.asarray(xy_sums, np.float64)
        self.calibration = calibration
        self.created = created or datetime.now(UTC).isoformat(timespec="seconds")
        self.path = path
        self._frame_resources: InMemoryResources | None = None
        if vocabulary is not None:
            # Frames are described with ``features`` and quantised with ``vocabulary``: a map holding a
            # vocabulary of other features (a file edited by hand, a map made in code) could localise nothing.
            vocabulary.check_compatible(features.descriptor_kind, path)

    # -- building ---------------------------------------------------------------------------
    @classmethod
    def build(
        cls,
        *,
        method: str,
        tours: Sequence[Traverse | str | Path],
        params: dict[str, Any] | None = None,
        vocabulary: Vocabulary | str | Path | None = None,
        vocab_train: Sequence[str | Path] = (),
        vocab_words: int = 10000,
        features: FeatureConfig | FeatureSpec | None = None,
        cache_dir: str | Path | None = None,
        progress: ProgressFactory | None = None,
        seed: int = 0,
        shards: int = 1,
        executor: Executor | None = None,
        learn_confusion: bool = True,
    ) -> Map:
        """Fit ``method`` on ``tours`` and return the map (not yet saved).

        Parameters
        ----------
        method : str
            A registered method name (``topoloc.available_methods()``).
        tours : sequence of Traverse or folder
            The map tours (image folders or in-memory traverses).
        params : dict, optional
            The method's parameters.
        vocabulary : Vocabulary or path, optional
            A vocabulary, or a vocabulary file (``topoloc vocab train``).
        vocab_train : sequence of folders
            Train a vocabulary on these images instead (cached); FAB-MAP also
            learns its word statistics from them.
        features : FeatureConfig or FeatureSpec, optional
            Default ``FeatureSpec()``: ``method="auto"`` (XFeat where the ``learned`` extra is installed,
            else SIFT), 1000 per image, ``max_side="auto"``
            (every image's longer side at most
            :data:`~topoloc.spec.parts.AUTO_MAX_SIDE`, whatever the tours).
        shards : int
            Build the map as this many partial models of contiguous place
            ranges (one task each on ``executor``) and merge them; the map
            equals the one built in one piece (``docs/map_shards.md``).
        executor : Executor, optional
            Where the shard tasks run (:func:`topoloc.cluster.connect`;
            default: threads of this process).
        learn_confusion : bool
            Learn which places look alike (:mod:`topoloc.maps.confusion`), what
            verification needs of the map; False for a map that will not be verified.

        Notes
        -----
        The map is built in this process's memory.  For a long route, build
        and save it within :func:`topoloc.spill_to` (as ``topoloc map build``
        does): its large arrays are then scratch files beside the map until it
        is saved, and the process holds chunks of the map, not all of it
        (``docs/results/cluster.md``).  :meth:`update` does that by itself.

        Examples
        --------
        >>> with topoloc.spill_to("maps"):  # doctest: +SKIP
        ...     Map.build(method="coocmap", tours=["route/day"], vocabulary="v.tlv", shards=40).save("maps/route.tlm")
        """
        maps = [t if isinstance(t, Traverse) else load_traverse(t) for t in tours]
        if not maps:
            raise ParameterError("maps", "needs at least one tour")
        check_distinct_tours(maps)  # as map add refuses a tour the map holds (issue #49)
        if isinstance(shards, bool) or not isinstance(shards, int) or shards < 1:
            raise ParameterError("shards", f"must be a whole number >= 1, got {shards!r}")
        rec = build_method(method, params or {})  # before any feature is extracted
        cls_ = type(rec)
        if shards > 1 and not cls_.tags.builds_shards:  # before any image is read
            raise TopolocError(f"method {method!r} cannot be built from shards: build it in one piece")
        voc_source: VocabularySpec | Vocabulary | None
        if isinstance(vocabulary, Vocabulary):
            if vocab_train:
                raise ParameterError("vocabulary", NOT_BOTH)
            voc_source = vocabulary
        else:
            voc_source = VocabularySpec(file=None if vocabulary is None else Path(vocabulary),
                                        train=tuple(Path(f) for f in vocab_train), words=vocab_words,
                                        seed=seed)
        spec = features if isinstance(features, FeatureSpec) else None
        config = features if isinstance(features, FeatureConfig) else (spec or FeatureSpec()).config()
        for t in maps:  # features extracted elsewhere must be those the map records (and describes frames with)
            check_feature_kind(t, config)
        res, _ = make_resources(config, voc_source, cache_dir=cache_dir, progress=progress, executor=executor,
                                needs_vocabulary=f"method {method!r}" if rec.uses_vocabulary else "", tours=maps)
        if shards > 1:
            # One partial model per range of places, as independent tasks, merged into the same map
            # (topoloc.methods.shards; docs/map_shards.md says what is exact).
            n_parts = min(shards, len(map_place_ids(maps)))
            rec = build_from_shards(cls_, maps, params=rec.get_params(), resources=res, n_shards=shards,
                                    executor=executor if executor is not None else getattr(res, "executor", None),
                                    advance=progress("map shards", n_parts)
                                    if progress is not None else None)
        else:
            rec.fit(maps, resources=res)
        # A vocabulary given by folders is trained on first use; a method that uses none still keeps it.
        voc = res.vocabulary if res.has_vocabulary else None
        m = cls.from_fitted(rec, maps, features=config, vocabulary=voc)
        if learn_confusion and executor is not None and executor.name != "local":
            # Learning it reads map images' features here; a map built on a cluster never gathers them on the
            # client (tests/maps/test_cluster_client_memory.py), so it verifies without a confusion (c_p = 0).
            log.info("the map's confusion is not learned on a cluster: its answers are verified without it")
        elif learn_confusion:
            m.confusion = confusion_of(rec, maps, res, progress=progress)
        m.spec = spec_to_dict(MapBuildSpec(
            method=method, params=rec.get_params(), shards=shards,
            maps=tuple(Path(t.root) if t.kind == "files" else Path(tour_root(t)) if t.source is not None
                       else Path(f"<{t.name} in memory>") for t in maps),
            features=spec or FeatureSpec(method=config.method, max_features=config.max_features,
                                         max_side=config.max_side, preprocess=config.preprocess),
            vocabulary=voc_source if isinstance(voc_source, VocabularySpec) else VocabularySpec()))
        return m

    @classmethod
    def from_fitted(cls, recognizer: PlaceRecognizer, tours: Sequence[Traverse], *, features: FeatureConfig,
                    vocabulary: Vocabulary | None) -> Map:
        """The map of a recogniser already fitted on ``tours`` (with these feature settings and vocabulary)."""
        return cls(recognizer, features=features, vocabulary=vocabulary, tours=[tour_record(t) for t in tours],
                   xy_sums=xy_sums(tours, recognizer.place_ids_))

    def add_tour(self, tour: Traverse | str | Path, *, cache_dir: str | Path | None = None,
                 progress: ProgressFactory | None = None, executor: Executor | None = None) -> Map:
        """Add a tour without revisiting the earlier images (each method's own update; see its ``_add_tour``).

        Raises
        ------
        TopolocError
            If the tour was added before (same fingerprint), or the method cannot add it.
        """
        t = tour if isinstance(tour, Traverse) else load_traverse(tour)
        check_feature_kind(t, self.features, self.path)
        rec = tour_record(t)
        if any(old["fingerprint"] == rec["fingerprint"] for old in self.tours):
            raise input_error(f"tour {t.name!r} is already in the map (same images and places)",
                              self.path or t.root)
        own_vocabulary = self.vocabulary is not None and self.vocabulary.provenance_.get("source") == "map tours"
        if self.add_rebuilds:
            # Adding online would make another map than building from all tours: the default
            # vocabulary is trained on the map's own tours (and FAB-MAP's word statistics with it),
            # and some methods cannot add exactly.  Build again from the earlier tours (read
            # again, checked unchanged) and this one; their features come from the cache.
            tours = [reload_tour(old) for old in self.tours] + [t]
            voc = self.vocabulary
            built = Map.build(method=self.recognizer.name, tours=tours, params=self.recognizer.get_params(),
                              vocabulary=None if own_vocabulary else voc, features=self.features,
                              vocab_words=voc.n_words if voc is not None else 10000,
                              seed=voc.seed if voc is not None else 0, cache_dir=cache_dir, progress=progress,
                              executor=executor)
            self.recognizer, self.vocabulary, self.xy_sums = built.recognizer, built.vocabulary, built.xy_sums
        else:
            res = self.resources(cache_dir=cache_dir, progress=progress, executor=executor)
            old_ids = self.place_ids
            self.recognizer.add_tour(t, resources=res)
            sums = xy_sums([t], self.place_ids)
            sums[np.searchsorted(self.place_ids, old_ids)] += self.xy_sums
            self.xy_sums = sums
        self.tours.append(rec)
        self._mark_stale(rec["name"])
        if self.confusion is not None:  # the places it compared have changed: learned again over every tour
            readable = self.verification_tours()
            self.confusion = None if readable is None else confusion_of(
                self.recognizer, readable, self.resources(cache_dir=cache_dir, progress=progress, executor=executor),
                progress=progress)
        return self

    @property
    def add_rebuilds(self) -> bool:
        """Whether :meth:`add_tour` builds the map again from all its tours (and says why in :attr:`add_rebuilds_why`).

        So it does where the vocabulary was trained on the map's own tours (it is trained
        again with the new one, and every place's words change) and for methods that cannot
        add a tour exactly: the map is then what ``map build`` of all the tours gives.
        """
        return bool(self.add_rebuilds_why)

    @property
    def add_rebuilds_why(self) -> str:
        """Why :meth:`add_tour` builds the map again ("" where it adds the tour alone)."""
        if self.vocabulary is not None and self.vocabulary.provenance_.get("source") == "map tours":
            return f"its vocabulary ({self.vocabulary.n_words} words) was trained on its own tours"
        if self.recognizer.add_tour_refits:
            return f"{self.recognizer.name} cannot add a tour to what it learned"
        return ""

    def _mark_stale(self, tour_name: str) -> None:
        """Keep the calibration, marked stale (:func:`topoloc.maps.calibration.mark_stale`)."""
        self.calibration = _cal.mark_stale(self.calibration, tour_name)

    @property
    def calibration_stale(self) -> bool:
        """Whether tours were added after the calibration (its threshold was chosen on other scores)."""
        return _cal.is_stale(self.calibration)

    # -- persistence ------------------------------------------------------------------------
    def save(self, path: str | Path, *, timeout: float | None = None) -> Path:
        """Write the map to one file, atomically; returns the path.

        It waits for another process that is updating the same file (:meth:`update`)
        to finish, up to ``timeout`` seconds (default ``$TOPOLOC_LOCK_TIMEOUT``, else
        an hour), then replaces it.
        """
        path = _through_link(Path(path))
        if path.is_dir():
            raise input_error("map output is a folder, not a file", path)
        with file_lock(path, timeout=timeout):
            self._write(path)
        self.path = path
        return path

    def _write(self, path: Path) -> None:
        meta, arrays = self.recognizer.get_state()
        out: dict[str, np.ndarray] = {STATE_PREFIX + k: v for k, v in arrays.items()}
        out["places/ids"] = np.asarray(self.place_ids, np.int64)
        out["places/xy_sums"] = self.xy_sums
        voc_meta = None
        if self.vocabulary is not None:
            out["vocabulary/words"] = self.vocabulary.words_
            voc_meta = {"fingerprint": vocabulary_fingerprint(self.vocabulary),
                        "descriptor_kind": self.vocabulary.descriptor_kind_,
                        "provenance": self.vocabulary.provenance_,
                        "index": self.vocabulary.index, "ef_search": self.vocabulary.ef_search}
        from topoloc._version import __version__

        for k, tour in enumerate(self.tours):
            pairs = tour.get("place_images")
            if pairs is not None:
                out.update((pairs if isinstance(pairs, PlaceImages) else PlaceImages.of(pairs)).arrays(k))
            if isinstance(tour.get("images"), TourImages):
                out.update(tour["images"].arrays(k))
        if self.confusion is not None:
            out[CONFUSION_ARRAY] = self.confusion.values
            if self.confusion.look_alikes is not None:
                out.update(zip(LOOK_ALIKE_ARRAYS, (self.confusion.look_alikes.rows, self.confusion.look_alikes.support),
                               strict=True))
        header = {
            "method": self.recognizer.name, "params": self.recognizer.get_params(),
            "features": asdict(self.features), "vocabulary": voc_meta,
            "tours": [header_record(t) for t in self.tours],
            "confusion": None if self.confusion is None else self.confusion.record(),
            "state": meta, "calibration": self.calibration, "created": self.created, "spec": self.spec,
            "modified": datetime.now(UTC).isoformat(timespec="seconds"), "topoloc_version": __version__,
        }
        write_map_file(path, header, out)

    @classmethod
    @contextlib.contextmanager
    def update(cls, path: str | Path, *, timeout: float | None = None) -> Iterator[Map]:
        """Load the map at ``path``, let the caller change it, and save it, with no other writer in between.

        Every writer of the file that goes through :meth:`update` or :meth:`save`
        (``map add``, ``map calibrate``, ``map build``, in any process) waits for
        the one holding the file: the next one loads what the last one saved, so
        no tour or calibration is lost.  A writer that waits logs one line; after
        ``timeout`` seconds (default ``$TOPOLOC_LOCK_TIMEOUT``, else an hour) it
        gives up with a one-line error.  Readers (:meth:`load`) never wait: a save
        is an atomic rename, so they read the old file or the new one, whole.  The
        map is saved when the block ends without an exception, and not at all
        otherwise.

        Examples
        --------
        >>> with Map.update("city.tlm") as m:  # doctest: +SKIP
        ...     m.add_tour("tours/night")

        Raises
        ------
        TopolocError
            What :meth:`load` refuses, or another process still holds the file after ``timeout``.
        """
        path = _through_link(Path(path))
        if not path.is_file():
            read_map_file(path)  # the one-line error of a missing map, before any lock
        # Large intermediates of the change (a tour merged into the map, its inverted files) as scratch
        # files beside the map until it is saved (io.scratch): held in memory, they would make the
        # update's peak grow with the map.
        with file_lock(path, timeout=timeout), spill_to(path.parent):
            m = cls.load(path)
            yield m
            m.save(path, timeout=timeout)

    @classmethod
    def load(cls, path: str | Path, *, mmap: bool = True) -> Map:
        """Open a map file; large arrays are memory-mapped (``mmap``), so this costs what it reads.

        Raises
        ------
        TopolocError
            One line naming the file: missing, not a map, another schema version,
            truncated, corrupted, or inconsistent (vocabulary fingerprint, state).
        """
        path = Path(path)
        meta, arrays = read_map_file(path, mmap=mmap)
        try:
            cls_ = get_method(str(meta["method"]))
            # Maps written before ``preprocess`` existed were extracted without any.
            features = FeatureConfig(**{"preprocess": "none", **meta["features"]})
            voc = None
            if meta["vocabulary"] is not None:
                v = meta["vocabulary"]
                voc = Vocabulary.from_words(np.asarray(arrays["vocabulary/words"]),
                                            descriptor_kind=str(v["descriptor_kind"]),
                                            provenance=dict(v.get("provenance") or {}),
                                            index=str(v.get("index", "hnsw")), ef_search=int(v.get("ef_search", 16)))
                if vocabulary_fingerprint(voc) != v["fingerprint"]:
                    raise input_error("map file's vocabulary does not match its fingerprint", path)
            state = {k.removeprefix(STATE_PREFIX): a for k, a in arrays.items() if k.startswith(STATE_PREFIX)}
            frame_res = InMemoryResources(feature_config=features, vocabulary=voc, memoise=False)
            params = cls_.upgrade_params(meta["params"])  # names a method has since renamed
            names = cls_.param_names()
            for key, value in cls_.legacy_defaults.items():
                if key in names:
                    params.setdefault(key, value)
            rec = cls_.from_state(params, meta["state"], state, resources=frame_res)
            place_ids = np.asarray(arrays["places/ids"])
            if not np.array_equal(place_ids, rec.place_ids_):
                raise input_error("map file is inconsistent (place ids differ from the method's)", path)
            tours = [dict(t) for t in meta["tours"]]
            for k, tour in enumerate(tours):
                stored = PlaceImages.from_arrays(arrays, k)
                if stored is not None:
                    tour["place_images"] = stored
                elif tour.get("place_images") is not None:  # a map file with the pairs in its header
                    tour["place_images"] = PlaceImages.of(tour["place_images"])
                images = TourImages.from_arrays(arrays, k)
                if images is not None:  # maps written before image digests were recorded have none
                    tour["images"] = images
            confusion = None
            if meta.get("confusion") is not None and CONFUSION_ARRAY in arrays:
                values = np.array(arrays[CONFUSION_ARRAY])
                if len(values) != len(place_ids):
                    raise input_error("map file is inconsistent (its confusion does not have one value per place)",
                                      path)
                alikes = None
                kept = [k in arrays for k in LOOK_ALIKE_ARRAYS]
                if any(kept) and not all(kept):
                    raise input_error("map file is inconsistent (it has one of its two look-alike arrays)", path)
                if all(kept):  # maps written before they were kept have none
                    rows, sup = (np.array(arrays[k]) for k in LOOK_ALIKE_ARRAYS)
                    if (rows.dtype.kind not in "iu" or rows.ndim != 2 or len(rows) != len(place_ids)
                            or ((rows < -1) | (rows >= len(place_ids))).any()):
                        raise input_error("map file is inconsistent (its look-alike places are not places of it)", path)
                    alikes = LookAlikes(rows.astype(np.int64), sup.astype(np.float32))
                confusion = Confusion.from_record(values, meta["confusion"], alikes)
            return cls(rec, features=features, vocabulary=voc, tours=tours,
                       xy_sums=np.array(arrays["places/xy_sums"]),
                       calibration=_cal.json_calibration(meta.get("calibration")),
                       created=meta.get("created"), path=path, spec=meta.get("spec"), confusion=confusion)
        except TopolocError as exc:
            msg = str(exc)
            raise TopolocError(msg if str(path) in msg else f"{msg}: {path}") from None
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise input_error(f"map file is malformed ({type(exc).__name__}: {exc})", path) from None

    # -- what it holds ----------------------------------------------------------------------
    @property
    def place_ids(self) -> np.ndarray:
        """Sorted place ids: the rows of ``S``, shape (n_places,)."""
        return self.recognizer.place_ids_

    @property
    def place_xy(self) -> np.ndarray:
        """Mean position of each place, shape (n_places, 2); NaN where no map image had one."""
        n = self.xy_sums[:, 2:3]
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(n > 0, self.xy_sums[:, :2] / np.maximum(n, 1), np.nan)

    @property
    def threshold(self) -> float | None:
        """Score above which a localisation is accepted, or None before :meth:`calibrate`.

        A calibration whose ``threshold`` is null reached no threshold: the
        threshold is then infinite and nothing is accepted.
        """
        return _cal.threshold_of(self.calibration)

    @property
    def score_confidence(self) -> ConfidenceModel | None:
        """The confidence of unverified answers: the calibration's model of the method's score (None before one)."""
        return _cal.confidence_model(self.calibration, on="score")

    def accepts(self, *, score: float, confidence: float | None, is_verified: bool | None) -> bool:
        """Whether an answer is accepted (:func:`topoloc.maps.calibration.accepts`)."""
        return _cal.accepts(self.calibration, score=score, confidence=confidence, is_verified=is_verified)

    def place_image_names(self) -> list[str]:
        """The map image each place is written as in a pairs file (:mod:`topoloc.evaluation.pairs`).

        The first image of the place in the first tour recording one; ``place-<id>`` for a
        place no tour record names (maps saved before tours recorded ``place_images``).
        """
        from topoloc.datasets.image_names import place_names

        return place_names(self.place_ids, (t.get("place_images") or {} for t in self.tours))

    def info(self) -> dict[str, Any]:
        """Method, parameters, places, tours, vocabulary, features, calibration and file size."""
        voc = None
        if self.vocabulary is not None:
            fp = vocabulary_fingerprint(self.vocabulary)
            prov = self.vocabulary.provenance_
            # The default vocabulary (#27) records the tours it was trained on, not folders.
            voc = {**fp, "trained_on": prov.get("folders") or (
                [f"map tours: {', '.join(map(str, prov.get('tours', [])))}"] if prov.get("source") == "map tours"
                else None)}
        xy_known = int((~np.isnan(self.place_xy[:, 0])).sum()) if len(self.place_xy) else 0
        return {
            "file": str(self.path) if self.path else None,
            "bytes": self.path.stat().st_size if self.path and self.path.is_file() else None,
            "method": self.recognizer.name, "params": self.recognizer.get_params(),
            "places": len(self.place_ids), "places_with_position": xy_known,
            "place_id_range": [int(self.place_ids.min()), int(self.place_ids.max())] if len(self.place_ids) else None,
            # One image name per place is for pairs files (place_image_names), not for reading here.
            "tours": [header_record(t) for t in self.tours],
            "vocabulary": voc, "features": asdict(self.features),
            "calibration": self.calibration or "none: every localisation is accepted (run `topoloc map calibrate`)",
            "verification": self.verification_info(),
            "created": self.created, "spec": self.spec,
        }

    # -- querying ---------------------------------------------------------------------------
    def resources(self, *, cache_dir: str | Path | None = None, progress: ProgressFactory | None = None,
                   executor: Executor | None = None) -> CachedResources:
        """Resources for whole traverses: the map's features (disk-cached) and vocabulary, run on ``executor``."""
        res, _ = make_resources(self.features, self.vocabulary, cache_dir=cache_dir, progress=progress,
                                executor=executor)
        return res

    def similarity(self, query: Traverse | str | Path, *, resources: Resources | None = None,
                   cache_dir: str | Path | None = None) -> np.ndarray:
        """``S`` of shape (n_places, len(query)) for a whole query traverse."""
        q = query if isinstance(query, Traverse) else load_traverse(query)
        check_feature_kind(q, self.features, self.path)
        return self.recognizer.similarity(q, resources=resources or self.resources(cache_dir=cache_dir))

    # -- verification -----------------------------------------------------------------------
    @property
    def where(self) -> str:
        """How messages name the map."""
        return f"the map {self.path}" if self.path is not None else "the map"

    def verification_blocker(self) -> str:
        """Why answers against this map cannot be verified at all, or "" when they can
        (:func:`topoloc.maps.verify_policy.verification_blocker`)."""
        return _policy.verification_blocker(self.tours)

    def verify_choice(self, verify: bool | None = None) -> VerifyChoice:
        """The choice to verify and what made it (:func:`topoloc.maps.verify_policy.choice_for`)."""
        return _policy.choice_for(verify, calibration=self.calibration, spec=self.spec,
                                  verifies_geometry=self.recognizer.tags.verifies_geometry)

    @property
    def default_verify(self) -> bool | None:
        """What the map records of verification (:func:`topoloc.maps.verify_policy.recorded_verify`)."""
        return _policy.recorded_verify(self.calibration, self.spec)

    def resolve_verify(self, verify: bool | None) -> bool:
        """Whether a run against this map verifies (:func:`topoloc.maps.verify_policy.settle`: asked where it
        cannot is a one-line error, else unverified with one warning line)."""
        return _policy.settle(self.verify_choice(verify), self.verification_blocker(), where=self.where)

    def verification_tours(self) -> list[Traverse] | None:
        """The tours as verification reads them (:func:`topoloc.maps.verify_policy.verification_tours`), or None
        where none can be read (said in one line)."""
        try:
            return _policy.verification_tours(self.tours, where=self.where)
        except TopolocError as exc:
            log.warning("%s", exc)
            return None

    def verifier(self, *, candidates: int | None = None, resources: Resources | None = None,
                 cache_dir: str | Path | None = None, sequence: int = 0,
                 spec: VerificationSpec | None = None) -> Verifier:
        """The verification stage against this map (:mod:`topoloc.verification`).

        The tours are read again from their folders or recordings: only the
        images the map recorded whose content is still the recorded one (one
        warning line names those left out), their features taken from the
        feature cache when a candidate first needs them: in memory, about
        ``n_images * max_features * (20 + descriptor bytes)`` once every tour has been
        needed (``map info``'s ``verification``).  The map's confusion and, once
        calibrated, its confidence model go with it.

        Raises
        ------
        TopolocError
            One line when no image of the map can be read again.
        """
        why = self.verification_blocker()
        if why:  # before any resource is made
            raise TopolocError(f"{self.where} cannot verify answers: {why} (use --no-verify)")
        res = resources if resources is not None else self.resources(cache_dir=cache_dir)
        vspec = _policy.with_map_floor(spec or VerificationSpec(), calibration=self.calibration, built=self.spec,
                                       where=self.where)
        if candidates is not None:
            vspec = dataclasses.replace(vspec, candidates=candidates)
        v = _policy.map_verifier(self.tours, self.place_ids, res, where=self.where, spec=vspec, sequence=sequence,
                                 confidence=_cal.confidence_model(self.calibration))
        if self.confusion is not None:
            self.confusion.install(v)
        return v

    def verifier_for(self, verify: bool | None, *, resources: Resources | None = None,
                     cache_dir: str | Path | None = None, sequence: int = 0, spec: VerificationSpec | None = None,
                     candidates: int | None = None) -> Verifier | None:
        """The verification stage of a run whose option is ``verify``, or None where it does not verify.

        The one door for ``localize``, ``map calibrate``, ``evaluate --map-file``
        and the ROS node: the choice (:meth:`verify_choice`), and a map that
        cannot verify (its tours gone, every image changed) is a one-line error
        where verification was asked for explicitly, else one warning line and no
        verification.
        """
        choice = self.verify_choice(verify)
        if not _policy.settle(choice, self.verification_blocker(), where=self.where):
            return None
        try:
            return self.verifier(candidates=candidates, resources=resources, cache_dir=cache_dir, sequence=sequence,
                                 spec=spec)
        except TopolocError as exc:
            if choice.enabled and choice.explicit:
                raise
            log.warning("%s: answers are not verified (--no-verify: not verified, without this line)", exc)
            return None

    def verification_info(self) -> dict[str, Any]:
        """Whether the map can verify answers, and the memory its map images' features then take."""
        info = _policy.verification_info(self.tours, self.features, self.default_verify)
        info["confusion"] = None if self.confusion is None else self.confusion.record()
        return info

    @property
    def calibrated_sequence(self) -> SequenceSpec:
        """The sequence matching the threshold was calibrated with (single images: length 0).

        Calibrations made before sequence matching was recorded (and an
        uncalibrated map) give single images, so such maps score as before.
        """
        return _cal.calibrated_sequence(self.calibration)

    def localizer(self, *, top_k: int = 5, sequence: int | None = None,
                  sequence_mode: str | None = None, prefetch: int = -1, verify: bool | None = None,
                  candidates: int | None = None, confirm: bool = False,
                  verification: VerificationSpec | None = None) -> Localizer:
        """An online localiser: feed it frames one at a time (:meth:`Localizer.step`).

        The one place a map's localiser is assembled (``localize``, its live
        path and the ROS node come here through :meth:`localizer_for`).
        ``sequence`` / ``sequence_mode`` None: those of :attr:`calibrated_sequence`,
        whose scores the stored threshold applies to.  ``prefetch``: frames
        :meth:`Localizer.stream` reads and describes ahead (:class:`Localizer`).
        ``verify`` None: :meth:`verify_choice` (the environment, the map's
        record, else wherever the map can verify); True where it cannot is a
        one-line error.  ``verification``: the rest of the verification settings.

        Raises
        ------
        TopolocError
            Before the first frame: verification asked for where the map cannot verify, bad settings.
        """
        # The map opens without its features' runtime (map info needs none); localising needs it: said here,
        # before any frame or output, for every caller.
        check_method_available(self.features.method)
        cal = self.calibrated_sequence
        length = cal.length if sequence is None else sequence
        vspec = verification or VerificationSpec()
        verifier = self.verifier_for(verify, candidates=candidates, sequence=length, spec=vspec)
        return Localizer(self, top_k=top_k, sequence=length,
                         sequence_mode=(cal.mode if sequence is None else "constant")
                         if sequence_mode is None else sequence_mode, prefetch=prefetch,
                         verifier=verifier, confirm=confirm)

    def localizer_for(self, spec: LocalizeSpec | NodeSpec) -> Localizer:
        """The localiser of a run's specification: its top K, sequence, prefetch and verification.

        ``localize`` (:class:`LocalizeSpec`) and the ROS nodes (:class:`NodeSpec`,
        whose sequence None is the map's :attr:`calibrated_sequence` and whose
        prefetch None is one frame per core) come here.
        """
        v = spec.verification
        seq = spec.sequence
        prefetch = spec.prefetch if spec.prefetch is not None else n_workers(-1)
        return self.localizer(top_k=spec.top_k, sequence=None if seq is None else seq.length,
                              sequence_mode=None if seq is None else seq.mode, prefetch=prefetch, verify=v.enabled,
                              candidates=v.candidates, confirm=v.confirm, verification=v)

    def localize(self, image: np.ndarray, *, top_k: int = 5) -> dict[str, Any]:
        """The place one camera frame shows.

        Parameters
        ----------
        image : ndarray of uint8, shape (H, W) grey or (H, W, 3) BGR

        Returns
        -------
        dict
            ``place`` (best place id), ``score`` (the method's own), ``accepted``
            (:func:`topoloc.maps.calibration.accepts`: before calibration, whether
            the answer is verified; after it, verified and at least the calibrated
            confidence, or the score for a map calibrated without verification),
            ``verified``, ``inliers`` and ``confidence`` where answers are
            verified, ``top`` (``[[place, score], ...]``, best first) and ``x``,
            ``y`` when the map has positions.
        """
        return self.localizer(top_k=top_k, sequence=0).step(image)

    def localize_many(self, images: Iterable[np.ndarray], *, top_k: int = 5, sequence: int | None = None,
                      sequence_mode: str | None = None) -> list[dict[str, Any]]:
        """:meth:`localize` over a sequence of frames; ``sequence > 0`` matches the last frames online.

        ``sequence`` None: the map's :attr:`calibrated_sequence` (single images when not calibrated).
        """
        loc = self.localizer(top_k=top_k, sequence=sequence, sequence_mode=sequence_mode)
        return [loc.step(img) for img in images]

    # -- confidence -------------------------------------------------------------------------
    def calibrate(self, S: np.ndarray, gt: GroundTruth, *, precision: float = 0.99,
                  query: str = "", ground_truth: str = "", tolerance: str = "",
                  sequence: SequenceSpec | None = None) -> dict[str, Any]:
        """Choose the acceptance threshold from a labelled tour's scores and store it in the map.

        Each query's best place (the raw argmax of its column, as :meth:`localize`
        reports it) is right when it lies in ``gt.hard``; queries whose best place
        is only in ``gt.soft`` are neither right nor wrong (as in the PR curve of
        the protocol).  The threshold is the lowest best-match score at which the
        queries scoring at least that much reach ``precision``; the recall there
        is recorded: right accepted queries over the queries that have a right
        place in the map (``n_with_right_place``; a query whose place the map
        lacks cannot be found, and does not count against recall).  With no
        soft band (``gt.soft == gt.hard``, as ``map calibrate --tolerance N``
        gives) these are exactly the precision and recall that :meth:`localize`
        then reaches on the same tour, counting a match within the tolerance as right.
        Where no threshold reaches it the map accepts nothing: the
        stored ``threshold`` is null (JSON has no infinity; :attr:`threshold`
        reads it as ``inf``) and one warning is logged.

        Parameters
        ----------
        S : ndarray, shape (n_places, n_queries)
            This map's scores of the labelled tour (:meth:`similarity`).
        gt : GroundTruth
            Of the same shape.
        precision : float
            In (0, 1].
        tolerance : str
            What counts as right, in words (``"within 8 places"``); default: ``gt``'s description.
        sequence : SequenceSpec, optional
            The sequence matching ``S`` went through (default: none, single
            images); recorded, so that :meth:`localizer` matches the same way
            and the threshold applies to the scores it compares.

        Returns
        -------
        dict
            The calibration stored in the map (a new one: not stale).
        """
        self.calibration = _cal.choose_threshold(S, gt, precision=precision, query=query,
                                                 ground_truth=ground_truth, tolerance=tolerance, sequence=sequence)
        return self.calibration

    def calibrate_on(self, tour: Traverse | str | Path, *, ground_truth: GroundTruthSpec | None = None,
                     precision: float = 0.99, label: str = "", cache_dir: str | Path | None = None,
                     progress: ProgressFactory | None = None, executor: Executor | None = None,
                     sequence: SequenceSpec | None = None, verify: bool | None = None,
                     verification: VerificationSpec | None = None) -> dict[str, Any]:
        """Score a labelled tour against the map and choose its threshold (on the confidence, when verified).

        Parameters
        ----------
        tour : Traverse or folder
            A tour with ground truth (``places.csv``, or natural order) that is not in the map.
        ground_truth : GroundTruthSpec, optional
            The tolerance (default: within 8 place ids is right,
            ``GroundTruthSpec.for_calibration()``); in metres it uses the map's
            place positions.
        precision : float
            In (0, 1].
        label : str
            How the calibration names the tour (default: its folder or name).
        sequence : SequenceSpec, optional
            Match the tour's frames in sequences (in its order), as
            :meth:`localizer` will; default none (single images).
        verify : bool, optional
            Verify the answers (:mod:`topoloc.verification`) before the
            threshold is chosen, as :meth:`localizer` then does by default
            (recorded); None: :meth:`resolve_verify`.

        Raises
        ------
        TopolocError
            If the tour is one the map was built from (same fingerprint), or no
            image of the tour shows a place of the map.
        """
        check_precision(precision)
        q = tour if isinstance(tour, Traverse) else load_traverse(tour)
        check_feature_kind(q, self.features, self.path)
        fingerprint = q.fingerprint()
        for old in self.tours:
            if old.get("fingerprint") == fingerprint:
                # Scores of the map's own images are near perfect: the threshold would accept anything.
                raise input_error(f"calibration tour {label or q.name!r} is the map's own tour {old['name']!r}: "
                                  "calibrate on a labelled tour the map was not built from",
                                  self.path or (q.root if q.kind == "files" else q.name))
        spec = ground_truth or GroundTruthSpec.for_calibration()
        gt = spec.make(self.place_ids, q, map_xy=self.place_xy)
        if not gt.hard.any():
            raise input_error("calibration tour has no ground truth in this map (no query place is a map place)",
                              q.root)
        res = self.resources(cache_dir=cache_dir, progress=progress, executor=executor)
        # Not told: as localize would match (recorded with the threshold).  Fails before the tour is scored; the
        # confidence is refitted from the development data's default.
        verifier = self.verifier_for(verify, resources=res, sequence=sequence.length if sequence else 0,
                                     spec=verification)
        verify = verifier is not None
        if verifier is not None:
            verifier.confidence_model = DEFAULT_CONFIDENCE
        S = self.recognizer.similarity(q, resources=res)
        if sequence is not None and sequence.length:
            from topoloc.sequence import sequence_similarity

            sequence.check_memory(S.shape[0])
            S = sequence_similarity(S, ds=sequence.length, mode=sequence.mode)  # type: ignore[arg-type]
        block = verifier.verify(S, res.features(q, timed=False)) if verifier is not None else None
        self.calibration = _cal.choose_threshold(
            S, gt, precision=precision, tolerance=spec.words(), sequence=sequence,
            query=label or (str(q.root) if q.kind == "files" else q.name), verified=block,
            confidence=None if verifier is None else verifier.confidence_model, verify=verify,
            min_support=None if verifier is None else verifier.rule.min_support)
        return self.calibration

    def check_compatible(self, *, features: FeatureSpec | None = None, vocabulary: Vocabulary | None = None) -> None:
        """Refuse feature settings or a vocabulary other than the map's (one line naming the parameter and map).

        ``features`` compares only what the map fixes (method, cap, preprocessing).
        """
        where = f": {self.path}" if self.path is not None else ""
        if features is not None:
            for key in ("method", "max_features", "preprocess"):
                given, have = getattr(features, key), getattr(self.features, key)
                if str(given).lower() != str(have).lower():
                    raise ParameterError(f"features.{key}", f"{given} differs from the map's {have}{where}")
        if vocabulary is not None and (self.vocabulary is None or vocabulary_fingerprint(vocabulary)
                                       != vocabulary_fingerprint(self.vocabulary)):
            raise ParameterError("vocabulary", f"is not the one this map was built with{where}")


def confusion_of(recognizer: PlaceRecognizer, tours: Sequence[Traverse], resources: Resources, *,
                 progress: ProgressFactory | None = None) -> Confusion | None:
    """The confusion of a fitted map's places (:func:`topoloc.maps.confusion.learn_confusion`), or None where its
    tours cannot be verified (visual words, a method that cannot score its own images), said in one line."""
    from topoloc.maps.confusion import learn_confusion

    try:
        verifier = build_verifier(VerificationSpec(), recognizer.place_ids_, tours, resources)
        return learn_confusion(recognizer, tours, resources, verifier, progress=progress)
    except TopolocError as exc:
        log.info("the map's confusion is not learned (%s): verification will not know its look-alike places", exc)
        return None


def _through_link(path: Path) -> Path:
    """The file a link named as the map points at: it is replaced there, and the link kept (issue #41)."""
    return Path(os.path.realpath(path)) if path.is_symlink() else path


__all__ = ["Localizer", "Map", "tour_record"]
