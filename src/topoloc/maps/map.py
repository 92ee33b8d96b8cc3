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
import logging
import math
import os
import threading
import time
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from topoloc._parallel import n_workers
from topoloc.cluster import Executor
from topoloc.datasets.frames import frame_index
from topoloc.datasets.groundtruth import GroundTruth
from topoloc.datasets.traverse import Traverse, check_distinct_tours, load_traverse
from topoloc.errors import ParameterError, TopolocError, input_error
from topoloc.features import FeatureConfig, FeatureSet
from topoloc.io.lock import file_lock
from topoloc.io.scratch import spill_to
from topoloc.maps.frame_resources import Described, FrameResources, describe
from topoloc.maps.mapfile import STATE_PREFIX, read_map_file, write_map_file
from topoloc.maps.place_images import PlaceImages
from topoloc.maps.prefetch import ahead, prefetch_depth, single_threaded_libraries
from topoloc.methods import get_method
from topoloc.methods.base import PlaceRecognizer, map_place_ids
from topoloc.methods.shard_build import build_from_shards
from topoloc.progress import ProgressFactory
from topoloc.ranking import threshold_sweep, top_rows
from topoloc.resources import CachedResources, InMemoryResources, Resources
from topoloc.spec import (
    FeatureSpec,
    GroundTruthSpec,
    MapBuildSpec,
    SequenceSpec,
    VerificationSpec,
    VocabularySpec,
    spec_to_dict,
)
from topoloc.spec.parts import NOT_BOTH, verify_from_env
from topoloc.spec.runs import check_prefetch
from topoloc.spec.setup import build_method, build_verifier, make_resources
from topoloc.verification import Verifier, confirmed, demote_unconfirmed
from topoloc.vocabulary import Vocabulary
from topoloc.vocabulary.vocab import vocabulary_fingerprint

log = logging.getLogger(__name__)


def tour_record(tour: Traverse) -> dict[str, Any]:
    """What a map remembers of a tour: name, size, times and a fingerprint of its images and places.

    ``place_images`` (:class:`~topoloc.maps.place_images.PlaceImages`, saved as arrays) maps each
    place of the tour to its first image (:func:`topoloc.evaluation.pairs.image_name`), what
    ``localize --pairs-out`` writes for the place.
    """
    rec: dict[str, Any] = {
        "name": tour.name, "root": _tour_root(tour),
        "n_images": len(tour), "n_places": len(np.unique(tour.places)), "fingerprint": tour.fingerprint(),
        "median_hour": tour.median_time_of_day(), "start": None, "end": None,
        "place_images": PlaceImages.of_tour(tour),
    }
    if tour.times is not None and len(tour.times):
        rec["start"], rec["end"] = str(tour.times.min()), str(tour.times.max())
    if tour.source is not None:
        rec["source"] = dict(tour.source)  # a recording: its file and frame selection
        if "file" in rec["source"]:
            rec["source"]["file"] = os.path.abspath(rec["source"]["file"])
    return rec


def reload_tour(rec: dict[str, Any], *, purpose: str = "to add a tour") -> Traverse:
    """The tour a map's tour record names, read again from its folder or recording.

    Raises
    ------
    TopolocError
        One line naming the tour: it was held in memory, is gone, or its images or
        places differ from those the map was built from (another fingerprint).
    """
    root = str(rec.get("root", ""))
    if root.startswith("<"):
        raise TopolocError(f"tour {rec.get('name')!r} of the map was built from images in memory, which cannot "
                           f"be read again {purpose}: build the map from all tours")
    src = rec.get("source") or {}
    if src:
        from topoloc.datasets.sources import load_input

        t = load_input(Path(src["file"]), topic=src.get("topic"), every_s=src.get("every_s"),
                       every_m=src.get("every_m"), pose_topic=src.get("pose_topic"))
    else:
        if not Path(root).is_dir():
            where = ("" if Path(root).is_absolute() else
                     f" from {Path.cwd()} (the map recorded it relative to the folder it was built in; run from "
                     "there, or build it again)")
            raise input_error(f"tour {rec.get('name')!r} of the map is needed again {purpose}, but its "
                              f"folder is gone{where}", root)
        t = load_traverse(root)
    if t.fingerprint() != rec["fingerprint"]:
        raise input_error(f"tour {rec.get('name')!r} has changed since the map was built (other images or "
                          "places): build the map again", root)
    return t


def _tour_root(tour: Traverse) -> str:
    """A tour's folder, the recording it was read from, or ``<images in memory>``."""
    # Absolute: ``map add`` may run from another folder than ``map build`` (issue #41).
    if tour.kind == "files":
        return os.path.abspath(tour.root)
    if tour.source is not None and "file" in tour.source:
        return os.path.abspath(tour.source["file"])
    return f"<{tour.kind} in memory>"


def _xy_sums(tours: Sequence[Traverse], place_ids: np.ndarray) -> np.ndarray:
    """Per place: sum of x, sum of y and number of the tours' images with a position, shape (n_places, 3)."""
    sums = np.zeros((len(place_ids), 3))
    for t in tours:
        if t.xy is None:
            continue
        # A frame without a position (NaN, as recordings give it) adds nothing: summed, it would
        # make its place's mean position NaN for good, whatever later tours add.
        known = np.isfinite(t.xy).all(axis=1)
        rows = np.searchsorted(place_ids, t.places[known])
        np.add.at(sums, rows, np.c_[t.xy[known], np.ones(int(known.sum()))])
    return sums


def _json_calibration(calibration: dict[str, Any] | None) -> dict[str, Any] | None:
    """A stored calibration with a threshold JSON can hold: maps saved before null stood for "none reached"
    wrote ``Infinity``, which Python's reader accepts but strict JSON does not (``map info --json``)."""
    if calibration is None or not isinstance(calibration.get("threshold"), float):
        return calibration
    if math.isfinite(calibration["threshold"]):
        return calibration
    return {**calibration, "threshold": None}


def check_feature_kind(traverse: Traverse, features: FeatureConfig, where: str | Path | None = None) -> None:
    """Refuse a traverse of features extracted elsewhere that are not of the map's kind (one line naming it).

    Images are described with the map's ``features``; a traverse of
    :class:`~topoloc.features.FeatureSet` is used as it is, so its descriptors
    must have the map's columns and be binary (uint8) exactly when the map's
    are.  Otherwise a method without a vocabulary (landmarks, voting) would fail
    deep in its index search, or a map would record features it was not built from.
    """
    if traverse.kind != "features":
        return
    dim, binary = features.descriptor_dim, features.descriptor_dtype == np.uint8
    for k, fs in enumerate(traverse.frames or ()):
        d = np.asarray(fs.descriptors)
        if len(d) and (d.shape[1] != dim or (d.dtype == np.uint8) != binary):
            raise input_error(f"traverse {traverse.name!r} holds descriptors of {d.shape[1]} {d.dtype} columns "
                              f"(image {k}), not the map's {features.descriptor_kind} features", where)


def check_precision(precision: float) -> None:
    """Refuse a precision outside (0, 1] (one line naming the parameter)."""
    if isinstance(precision, bool) or not isinstance(precision, int | float) or not 0 < precision <= 1:
        raise ParameterError("precision", f"must be in (0, 1], got {precision!r}")


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
    """

    def __init__(self, recognizer: PlaceRecognizer, *, features: FeatureConfig, vocabulary: Vocabulary | None,
                 tours: list[dict[str, Any]], xy_sums: np.ndarray, calibration: dict[str, Any] | None = None,
                 created: str | None = None, path: Path | None = None, spec: dict[str, Any] | None = None) -> None:
        self.recognizer = recognizer
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
        m.spec = spec_to_dict(MapBuildSpec(
            method=method, params=rec.get_params(), shards=shards,
            maps=tuple(Path(t.root) if t.kind == "files" else Path(_tour_root(t)) if t.source is not None
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
                   xy_sums=_xy_sums(tours, recognizer.place_ids_))

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
            sums = _xy_sums([t], self.place_ids)
            sums[np.searchsorted(self.place_ids, old_ids)] += self.xy_sums
            self.xy_sums = sums
        self.tours.append(rec)
        self._mark_stale(rec["name"])
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
        """Keep the calibration, marked stale: a tour added since changes the scores it was chosen on.

        ``stale_since`` names the first tour added after it, ``tours_added_since`` all of them;
        :meth:`calibrate` again clears both.
        """
        if self.calibration is None:
            return
        added = [*self.calibration.get("tours_added_since", []), tour_name]
        self.calibration = {**self.calibration, "stale": True,
                            "stale_since": self.calibration.get("stale_since", tour_name),
                            "tours_added_since": added}

    @property
    def calibration_stale(self) -> bool:
        """Whether tours were added after the calibration (its threshold was chosen on other scores)."""
        return bool(self.calibration and self.calibration.get("stale"))

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
        header = {
            "method": self.recognizer.name, "params": self.recognizer.get_params(),
            "features": asdict(self.features), "vocabulary": voc_meta,
            "tours": [{key: v for key, v in t.items() if key != "place_images"} for t in self.tours],
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
            return cls(rec, features=features, vocabulary=voc, tours=tours,
                       xy_sums=np.array(arrays["places/xy_sums"]),
                       calibration=_json_calibration(meta.get("calibration")),
                       created=meta.get("created"), path=path, spec=meta.get("spec"))
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
        if self.calibration is None:
            return None
        value = self.calibration.get("threshold")
        return math.inf if value is None else float(value)

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
            "tours": [{k: v for k, v in t.items() if k != "place_images"} for t in self.tours],
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
    def verification_blocker(self) -> str:
        """Why answers against this map cannot be verified, or "" when they can.

        Verification matches a query's local features against the map images of
        its candidate places, which the map reaches through its tours' folders
        or recordings (their features come from the feature cache, extracted once).
        """
        for rec in self.tours:
            root = str(rec.get("root", ""))
            src = rec.get("source") or {}
            if root.startswith("<"):
                return f"tour {rec.get('name')!r} was built from images in memory, which cannot be read again"
            where = Path(src["file"]) if src else Path(root)
            if not where.exists():
                return f"tour {rec.get('name')!r} is gone: {where}"
        return ""

    @property
    def default_verify(self) -> bool | None:
        """Whether answers are verified when no one says: as the threshold was calibrated, else as the map was built.

        A map calibrated with verification recorded keeps that setting (the
        threshold holds for those scores only); a map built before verification
        existed, or calibrated before it was recorded, scores as it always did
        (False); else None: wherever it can.
        """
        cal = self.calibration or {}
        if "verify" in cal:
            return bool(cal["verify"])
        if self.calibration is not None or not self.spec or "verification" not in self.spec:
            return False
        return (self.spec.get("verification") or {}).get("enabled")

    def verifier(self, *, candidates: int | None = None, resources: Resources | None = None,
                 cache_dir: str | Path | None = None, sequence: int = 0) -> Verifier:
        """The verification stage against this map (:mod:`topoloc.verification`).

        The tours are read again from their folders or recordings (checked
        against their fingerprints) and each tour's features are taken from the
        feature cache when a candidate first needs them: in memory, about
        ``n_images * max_features * (20 + descriptor bytes)`` once every tour has been
        needed (``map info``'s ``verification``).

        Raises
        ------
        TopolocError
            One line naming the tour that cannot be read again.
        """
        why = self.verification_blocker()
        where = f"the map {self.path}" if self.path is not None else "the map"
        if why:
            raise TopolocError(f"{where} cannot verify answers: {why} (use --no-verify)")
        tours = [reload_tour(rec, purpose="to verify answers") for rec in self.tours]
        res = resources if resources is not None else self.resources(cache_dir=cache_dir)
        v = build_verifier(VerificationSpec(enabled=True, candidates=candidates), self.place_ids, tours, res,
                           what=where, sequence=sequence)
        assert v is not None
        return v

    def verification_info(self) -> dict[str, Any]:
        """Whether the map can verify answers, and the memory its map images' features then take."""
        why = self.verification_blocker()
        n_images = sum(int(t.get("n_images", 0) or 0) for t in self.tours)
        # keypoints: 5 float32 columns; descriptors: descriptor_dim columns of descriptor_dtype
        f = self.features
        per_image = int(f.max_features) * (20 + f.descriptor_dim * np.dtype(f.descriptor_dtype).itemsize)
        return {"can_verify": not why, **({"why_not": why} if why else {}),
                "default": self.default_verify, "map_images": n_images,
                "features_bytes_at_most": n_images * per_image}

    @property
    def calibrated_sequence(self) -> SequenceSpec:
        """The sequence matching the threshold was calibrated with (single images: length 0).

        Calibrations made before sequence matching was recorded (and an
        uncalibrated map) give single images, so such maps score as before.
        """
        seq = (self.calibration or {}).get("sequence") or {}
        return SequenceSpec(length=int(seq.get("length", 0)), mode=str(seq.get("mode", "constant")))

    def localizer(self, *, top_k: int = 5, sequence: int | None = None,
                  sequence_mode: str | None = None, prefetch: int = -1, verify: bool | None = None,
                  candidates: int | None = None, confirm: bool = False) -> Localizer:
        """An online localiser: feed it frames one at a time (:meth:`Localizer.step`).

        ``sequence`` / ``sequence_mode`` None: those of :attr:`calibrated_sequence`,
        whose scores the stored threshold applies to.  ``prefetch``: frames
        :meth:`Localizer.stream` reads and describes ahead (:class:`Localizer`).
        ``verify`` None: :attr:`default_verify` (and where that is None, wherever
        the map can verify); True where it cannot is a one-line error.
        """
        cal = self.calibrated_sequence
        return Localizer(self, top_k=top_k, sequence=cal.length if sequence is None else sequence,
                         sequence_mode=(cal.mode if sequence is None else "constant")
                         if sequence_mode is None else sequence_mode, prefetch=prefetch,
                         verify=self.resolve_verify(verify), candidates=candidates, confirm=confirm)

    def resolve_verify(self, verify: bool | None) -> bool:
        """Whether to verify: as asked; else as the threshold was calibrated; else ``$TOPOLOC_VERIFY``; else
        :attr:`default_verify`; else whether the map can verify.  A calibration's record comes before the
        environment: its threshold holds for the scores it was chosen on only."""
        if verify is None and "verify" in (self.calibration or {}):
            verify = bool((self.calibration or {})["verify"])
        if verify is None:
            verify = verify_from_env()
        if verify is not None:
            return verify
        default = self.default_verify
        if default is not None:
            return default
        if self.recognizer.tags.verifies_geometry:
            return False
        why = self.verification_blocker()
        if why:
            log.info("%s cannot verify answers (%s): they are not verified", self.path or "the map", why)
        return not why

    def localize(self, image: np.ndarray, *, top_k: int = 5) -> dict[str, Any]:
        """The place one camera frame shows.

        Parameters
        ----------
        image : ndarray of uint8, shape (H, W) grey or (H, W, 3) BGR

        Returns
        -------
        dict
            ``place`` (best place id), ``score``, ``accepted`` (score above the
            calibrated threshold; always True before calibration), ``top``
            (``[[place, score], ...]``, best first) and ``x``, ``y`` when the
            map has positions.
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
        check_precision(precision)
        if S.shape != gt.shape:
            raise TopolocError(f"scores of shape {S.shape} do not match the ground truth {gt.shape}")
        has_pos = gt.hard.any(axis=0)
        if not has_pos.any():
            raise TopolocError("calibration needs a tour with ground truth: no query has a correct map place")
        best = np.argmax(S, axis=0)
        cols = np.arange(S.shape[1])
        score = S[best, cols].astype(np.float64)
        right = gt.hard[best, cols]
        counted = right | ~gt.soft[best, cols]
        s, tp, fp, last = threshold_sweep(score, right, counted)
        n_counted = tp + fp
        prec = np.where(n_counted > 0, tp / np.maximum(n_counted, 1), 1.0)
        ok = last & (prec >= precision) & (n_counted > 0)
        n_pos = int(has_pos.sum())
        if ok.any():
            k = int(np.flatnonzero(ok)[-1])
            threshold, rec = float(s[k]), float(tp[k] / n_pos)
            reached = float(prec[k])
        else:
            # JSON has no infinity: null stands for "no threshold reached", which accepts nothing.
            threshold, rec, reached = None, 0.0, 1.0
            log.warning("calibration on %s: no score threshold reaches precision %g, so the map now accepts no "
                        "localisation; calibrate on a longer tour or ask for a lower --precision",
                        query or gt.description, precision)
        self.calibration = {
            "threshold": threshold, "precision_asked": precision, "precision": reached, "recall": rec,
            "query": query, "ground_truth": ground_truth or gt.description,
            "tolerance": tolerance or gt.description, "n_queries": int(S.shape[1]),
            "n_with_right_place": n_pos,
            "sequence": {"length": (sequence or SequenceSpec()).length, "mode": (sequence or SequenceSpec()).mode},
            "recall_of": "queries with a right place in the map (n_with_right_place)",
            "date": datetime.now(UTC).isoformat(timespec="seconds"),
        }
        return self.calibration

    def calibrate_on(self, tour: Traverse | str | Path, *, ground_truth: GroundTruthSpec | None = None,
                     precision: float = 0.99, label: str = "", cache_dir: str | Path | None = None,
                     progress: ProgressFactory | None = None, executor: Executor | None = None,
                     sequence: SequenceSpec | None = None, verify: bool | None = None) -> dict[str, Any]:
        """Score a labelled tour against the map and :meth:`calibrate` on it.

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
        verify = self.resolve_verify(verify)  # not told: as localize would match (recorded with the threshold)
        res = self.resources(cache_dir=cache_dir, progress=progress, executor=executor)
        # Fails before the tour is scored.
        verifier = self.verifier(resources=res, sequence=sequence.length if sequence else 0) if verify else None
        S = self.recognizer.similarity(q, resources=res)
        if sequence is not None and sequence.length:
            from topoloc.sequence import sequence_similarity

            sequence.check_memory(S.shape[0])
            S = sequence_similarity(S, ds=sequence.length, mode=sequence.mode)  # type: ignore[arg-type]
        if verifier is not None:
            S = verifier.verify(S, res.features(q, timed=False)).S
        cal = self.calibrate(S, gt, precision=precision, tolerance=spec.words(), sequence=sequence,
                             query=label or (str(q.root) if q.kind == "files" else q.name))
        cal["verify"] = bool(verify)
        return cal

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


def _through_link(path: Path) -> Path:
    """The file a link named as the map points at: it is replaced there, and the link kept (issue #41)."""
    return Path(os.path.realpath(path)) if path.is_symlink() else path


class Localizer:
    """Online localisation against a :class:`Map`, one frame at a time, with bounded memory.

    With ``sequence = N > 0`` each frame is matched together with the ``N``
    frames before it (causal: frame ``i`` uses only frames ``<= i``), by the
    same search as ``evaluate --sequence`` on the last ``N + 1`` score
    columns, so its result equals the batch result for that frame; its
    ``score`` is then the sequence confidence (the best path's margin over
    the best path elsewhere on the route, :mod:`topoloc.sequence.confidence`),
    which :meth:`Map.calibrate_on` with the same ``sequence`` calibrates.  Methods
    that score whole sequences (SeqSLAM) keep their own last ``ds + 1`` frames.

    Parameters
    ----------
    m : Map
    top_k : int
        Places listed per frame.
    sequence, sequence_mode
        Online sequence matching (off with 0).
    verify : bool
        Verify each frame's candidates against the map images (:mod:`topoloc.verification`):
        its line then says ``verified`` and ``inliers``, and its score is the
        verified confidence.
    confirm : bool
        Temporal consistency (:mod:`topoloc.verification.consistency`): a
        frame's answer not confirmed by the previous frame's ranks below every
        confirmed one; its line says ``confirmed``.
    candidates : int, optional
        Distinct peaks verified per frame (default: 3 for single images, the
        best place with ``sequence``: :func:`topoloc.verification.default_candidates`).
    prefetch : int
        Frames :meth:`stream` reads and describes ahead of the one being
        matched, on a pool of one thread per core (at most ``prefetch``): the
        next frames' decoding, features and quantisation run while this frame
        is matched, and the lines come out in the same order with the same
        content.  -1 (default): two per core; 0: every frame read, described
        and matched in turn on this thread.  Memory holds at most this many
        frames beyond the one being matched.
    """

    def __init__(self, m: Map, *, top_k: int = 5, sequence: int = 0, sequence_mode: str = "constant",
                 prefetch: int = -1, verify: bool = False, candidates: int | None = None,
                 confirm: bool = False) -> None:
        if isinstance(top_k, bool) or not isinstance(top_k, int) or top_k < 1:
            raise ParameterError("top_k", f"must be a whole number >= 1, got {top_k!r}")
        check_prefetch(prefetch)
        # One-line errors naming the parameter; the last N + 1 columns it keeps are bounded too.
        SequenceSpec(length=sequence, mode=sequence_mode).check_memory(len(m.place_ids), online=True)
        self.map = m
        self.top_k = top_k
        self.sequence = sequence
        self.sequence_mode = sequence_mode
        self.prefetch = prefetch
        self.frames = 0
        # Built before the first frame: a map whose tours cannot be read again fails here, in one line.
        self.verifier: Verifier | None = m.verifier(candidates=candidates, sequence=sequence) if verify else None
        self.ms_verify = 0.0
        self.n_verified = 0
        self.confirm = confirm
        self._previous_best: int | None = None
        rec = m.recognizer
        self._items: deque[Any] = deque(maxlen=int(rec.get_params().get("ds", 0)) + 1)
        self._columns: deque[np.ndarray] = deque(maxlen=sequence + 1)
        # Running sums (ms over all frames so far), not lists: memory must not grow with a long recording.
        self.ms_decode = 0.0
        self.ms_features = 0.0
        self.ms_quantise = 0.0
        self.ms_matching = 0.0
        self.ms_wait = 0.0
        self.wall_s = 0.0
        self.start_s = 0.0
        self.cpu_s = 0.0
        self.workers = 1
        self.threads = 1
        self.ms_overlap = 0.0
        self._tls = threading.local()

    def describe(self, image: np.ndarray, *, name: str = "") -> Described:
        """``(items, ms features, ms quantisation, features)`` of one frame: the recogniser's ``encode``.

        ``features`` (the frame's local features, for verification) is None when
        the localiser does not verify.  Safe on any thread.
        """
        res: FrameResources | None = getattr(self._tls, "res", None)
        if res is None:  # one per thread: a feature detector is not shared between threads
            res = self._tls.res = FrameResources(self.map.features, self.map.vocabulary)
        return describe(self.map.recognizer, res, image, name, keep_features=self.verifier is not None)

    def stream(self, frames: Iterable[tuple[Any, ...]], *,
               executor: Executor | None = None) -> Iterator[dict[str, Any]]:
        """Result lines of ``frames`` (``(name, time_s or None, image[, index])``, as :meth:`InputSpec.frames` gives).

        A frame's ``index`` (its number in its input, frames not answered leaving
        gaps) is its line's ``frame``; without one, ``frame`` counts the lines.

        On this process (``executor`` None or local) frames are read and
        described ``prefetch`` ahead on a thread pool while this thread matches
        them in order (:func:`topoloc.maps.prefetch.ahead`), so a recording is
        never held in memory; with ``prefetch=0`` one at a time.  On a Dask
        executor they are described and scored in batches by the workers
        (:func:`topoloc.maps.batch.localize_on`), with the same lines.  The
        stage times and the wall time accumulate for :meth:`summary`.
        """
        it = iter(frames)
        voc = self.map.vocabulary
        if voc is not None and self.map.recognizer.uses_vocabulary:
            # The word index (HNSW) is built on its first use, once per process like opening the map: built
            # and timed here (``s_start``), it no longer inflates the first frame's quantisation and ``fps``.
            t0 = time.perf_counter()
            voc.quantize(voc.words_[:1])
            self.start_s += time.perf_counter() - t0
        t_start, cpu_start = time.perf_counter(), time.process_time()
        try:
            if executor is not None and executor.name != "local":
                from topoloc.maps.batch import localize_on

                for line, seconds in localize_on(executor, self, it):
                    self.ms_decode += 1e3 * seconds
                    yield line
                return
            depth = prefetch_depth(self.prefetch)
            if depth == 0:
                yield from self._one_at_a_time(it)
                return
            first = self.frames

            def work(k: int, item: tuple[Any, ...]) -> Described:
                return self.describe(item[2], name=item[0] or f"frame{first + k}")

            done = ahead(it, work, depth=depth)
            self.threads = max(self.threads, min(n_workers(-1), depth))
            with single_threaded_libraries():
                try:
                    for a in done:
                        items, ms_f, ms_q, feats = a.result
                        self.ms_wait += a.wait_ms
                        yield self._match(items, name=a.item[0], time_s=a.item[1], ms_decode=a.decode_ms,
                                          ms_features=ms_f, ms_quantise=ms_q, features=feats,
                                          index=frame_index(a.item))
                finally:
                    done.close()  # stops the reader and the pool before OpenCV's threads come back
        finally:
            self.wall_s += time.perf_counter() - t_start
            self.cpu_s += time.process_time() - cpu_start

    def _one_at_a_time(self, it: Iterator[tuple[Any, ...]]) -> Iterator[dict[str, Any]]:
        while True:
            t0 = time.perf_counter()
            item = next(it, None)
            decode_ms = 1e3 * (time.perf_counter() - t0)
            if item is None:
                return
            name, time_s, frame = item[:3]
            items, ms_f, ms_q, feats = self.describe(frame, name=name or f"frame{self.frames}")
            self.ms_wait += 1e3 * (time.perf_counter() - t0)
            yield self._match(items, name=name, time_s=time_s, ms_decode=decode_ms, ms_features=ms_f,
                              ms_quantise=ms_q, features=feats, index=frame_index(item))

    def summary(self) -> dict[str, Any]:
        """Frames, frames per second and mean milliseconds per frame of each stage.

        ``ms_decode_mean`` (reading and decoding the frame), ``ms_extract_mean``
        (local features or the method's own per-image transform),
        ``ms_quantise_mean`` (visual words) and ``ms_matching_mean`` (scoring the
        frame against the map, the sequence search, the top places) are each
        frame's own time on the thread that did it; ``ms_features_mean`` is the
        first three together, as ``evaluate``'s ``ms_features`` counts decoding.
        ``fps`` is counted on the wall clock.  With prefetch (``threads``: the
        describing threads) frames are described while others are matched, so
        the stages add up to more than the wall time; ``ms_wait_mean`` is how
        long matching waited for the next frame to be described (near 0: the
        matching is the bottleneck), and the overhead is the wall time per frame
        beyond that wait and the matching (building and writing the lines).
        ``s_start`` is the time spent before the first frame, outside ``fps``:
        building the vocabulary's word index, once per process.
        ``ms_cpu_mean`` is the processor time of the whole process per frame, every
        thread together: unlike the wall clock it hardly grows when other
        processes share the cores, so ``cores * 1000 / ms_cpu_mean`` bounds the
        frames/s the same run reaches on idle cores.  On
        a cluster (``workers``: the worker threads) features and matching are
        each frame's own time on a worker, and frames run side by side, so the
        overhead is the wall time per frame less the part of that work the wall
        clock saw (``ms_overlap``, the work done alongside other frames, is
        given back); never negative.
        """
        n = max(self.frames, 1)
        match_ms = self.ms_matching / n
        decode_ms, extract_ms, quantise_ms = self.ms_decode / n, self.ms_features / n, self.ms_quantise / n
        features_ms = decode_ms + extract_ms + quantise_ms
        wall = self.wall_s
        if self.workers > 1:
            overhead = 1e3 * wall / n - features_ms - match_ms + self.ms_overlap / n
        else:
            overhead = 1e3 * wall / n - self.ms_wait / n - match_ms
        out = {"frames": self.frames, "fps": round(self.frames / wall, 2) if wall else None,
               "fps_without_features": round(1e3 / match_ms, 2) if match_ms else None,
               "ms_features_mean": round(features_ms, 2), "ms_decode_mean": round(decode_ms, 2),
               "ms_extract_mean": round(extract_ms, 2), "ms_quantise_mean": round(quantise_ms, 2),
               "ms_matching_mean": round(match_ms, 2),
               # Clock readings of different threads and machines: a few hundredths below zero is noise.
               "ms_overhead_mean": round(max(overhead, 0.0), 2),
               "calibrated": self.map.threshold is not None, "s_start": round(self.start_s, 3)}
        if self.verifier is not None:
            out["ms_verify_mean"] = round(self.ms_verify / n, 2)
            out["verified"] = self.n_verified
        if self.workers > 1:
            out["workers"] = self.workers
        else:
            out["ms_wait_mean"] = round(self.ms_wait / n, 2)
            out["threads"] = self.threads
            out["ms_cpu_mean"] = round(1e3 * self.cpu_s / n, 2)
        return out

    def step(self, image: np.ndarray, *, name: str = "", time_s: float | None = None,
             index: int | None = None) -> dict[str, Any]:
        """Localise the next frame (a NumPy image) and return its result line (see :meth:`Map.localize`)."""
        items, ms_f, ms_q, feats = self.describe(image, name=name or f"frame{self.frames}")
        return self._match(items, name=name, time_s=time_s, ms_decode=0.0, ms_features=ms_f, ms_quantise=ms_q,
                           features=feats, index=index)

    def _match(self, items: list[Any], *, name: str, time_s: float | None, ms_decode: float, ms_features: float,
               ms_quantise: float, features: FeatureSet | None = None, index: int | None = None) -> dict[str, Any]:
        """The result line of the next frame from its described ``items``, in frame order."""
        rec = self.map.recognizer
        t1 = time.perf_counter()
        if rec.scores_whole_sequence:
            self._items.append(items[0])
            col = rec.score(list(self._items))[:, -1]
        else:
            col = rec.score(items)[:, 0]
        self.ms_decode += ms_decode
        self.ms_quantise += ms_quantise
        return self.step_scores(col, name=name, time_s=time_s, ms_features=ms_features,
                                ms_matching=1e3 * (time.perf_counter() - t1), features=features, index=index)

    def step_scores(self, col: np.ndarray, *, name: str = "", time_s: float | None = None,
                    ms_features: float = 0.0, ms_matching: float = 0.0,
                    features: FeatureSet | None = None, index: int | None = None) -> dict[str, Any]:
        """The result line of the next frame from its score column, shape (n_places,), computed elsewhere.

        What :meth:`step` does after scoring (the sequence search over the last
        columns, the top places, the threshold); a batch localisation scores
        frames on a cluster (:mod:`topoloc.maps.batch`) and feeds the columns
        here in frame order, so the lines are the same.
        """
        t2 = time.perf_counter()
        if self.sequence:
            from topoloc.sequence import sequence_similarity

            self._columns.append(np.asarray(col, np.float32))
            window = np.stack(self._columns, axis=1)
            col = sequence_similarity(window, ds=self.sequence, mode=self.sequence_mode)[:, -1]  # type: ignore[arg-type]
        self.ms_features += ms_features
        self.ms_matching += ms_matching + 1e3 * (time.perf_counter() - t2)
        block = None
        if self.verifier is not None:
            if features is None:
                raise ValueError("this localiser verifies: give the frame's local features")
            block = self.verifier.verify(np.asarray(col)[:, None], [features])
            col = block.S[:, 0]
            self.ms_verify += float(block.ms[0])
            self.n_verified += int(block.verified[0])
        ok = None
        if self.confirm:
            col2 = np.asarray(col, np.float32)[:, None]
            ok = bool(confirmed(col2, self._previous_best)[0])
            self._previous_best = int(np.argmax(col2[:, 0]))
            col = demote_unconfirmed(col2, np.array([ok]))[:, 0]
        out = self._result(np.asarray(col, np.float64), name, time_s, index)
        if ok is not None:
            out["confirmed"] = ok
        if block is not None:
            out["verified"] = bool(block.verified[0])
            out["inliers"] = int(block.inliers[0])
        self.frames += 1
        return out

    def _result(self, col: np.ndarray, name: str, time_s: float | None, index: int | None = None) -> dict[str, Any]:
        m = self.map
        top = top_rows(col[:, None], self.top_k)[0][0]  # best first, ties by row as argmax
        best = int(top[0])
        score = float(col[best])
        threshold = m.threshold
        out: dict[str, Any] = {
            "frame": self.frames if index is None else int(index), "image": name, "place": int(m.place_ids[best]),
            "score": score,
            "accepted": bool(threshold is None or score >= threshold),
            "top": [[int(m.place_ids[i]), float(col[i])] for i in top],
        }
        if time_s is not None:
            out["time"] = time_s
        x, y = m.place_xy[best] if len(m.place_xy) else (np.nan, np.nan)
        if np.isfinite(x) and np.isfinite(y):
            out["x"], out["y"] = float(x), float(y)
        return out


__all__ = ["Localizer", "Map", "tour_record"]
