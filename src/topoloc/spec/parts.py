"""The parts a run is made of, each validated once, when it is made.

A command (``evaluate``, ``map build``, ``localize``, ...) is described by a
few small frozen dataclasses composed together (:mod:`topoloc.spec.runs`):

* :class:`FeatureSpec` -- which local features, at what image scale;
* :class:`VocabularySpec` -- a vocabulary file, or folders to train one on;
* :class:`InputSpec` -- how recordings (ROS bags, videos) are turned into frames;
* :class:`GroundTruthSpec` -- what counts as the right place;
* :class:`SequenceSpec` -- sequence matching over the last frames;
* :class:`ExecutionSpec` -- where per-image work runs and what it caches.

Every check of a user's value lives here, once: a bad value raises
:class:`~topoloc.errors.ParameterError` naming the parameter by its dotted
name (``features.max_side``), before any image is read.  The command line
names the flag instead (``topoloc.cli.options``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from topoloc.errors import ParameterError, TopolocError
from topoloc.verification.decision import MIN_SUPPORT, VerificationRule

log = logging.getLogger(__name__)

if TYPE_CHECKING:  # numpy and the readers are not imported when the command line starts
    import numpy as np

    from topoloc.datasets.groundtruth import GroundTruth
    from topoloc.datasets.traverse import Traverse
    from topoloc.features import FeatureConfig

SEQUENCE_MODES = ("constant", "acceleration")


def _positive(param: str, value: float | None, *, what: str = "a positive number") -> float | None:
    """``value`` itself when it is None or a finite number > 0; else one line naming ``param``."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
        raise ParameterError(param, f"must be {what}, got {value!r}")
    return float(value)


def _paths(value: Any) -> tuple[Path, ...]:
    if value is None:
        return ()
    if isinstance(value, str | Path):
        return (Path(value),)
    return tuple(Path(v) for v in value)


def distinct_paths(param: str, paths: Sequence[Path]) -> tuple[Path, ...]:
    """``paths``, refused with one line naming ``param`` where one names the same file or folder twice.

    Compared resolved (links followed), as every command compares what it reads (issue #49: a
    folder given twice counted its images twice).
    """
    import os

    seen: dict[str, Path] = {}
    for p in paths:
        real = os.path.realpath(p)
        if real in seen:
            shown = str(p) if str(seen[real]) == str(p) else f"{seen[real]} and {p}"
            raise ParameterError(param, f"names the same folder twice ({shown}): give each once")
        seen[real] = p
    return tuple(paths)


def _opt_path(value: Any) -> Path | None:
    return None if value is None or value == "" else Path(value)


def parse_recall_at(text: str | Sequence[int]) -> tuple[int, ...]:
    """``"1,5,10,20"`` -> ``(1, 5, 10, 20)``: the N of R@N, each a positive integer.

    Raises
    ------
    ParameterError
        For an empty list, a value that is not an integer, or N < 1.
    """
    items = [str(t).strip() for t in (text.split(",") if isinstance(text, str) else text)]
    try:
        ks = tuple(sorted({int(t) for t in items if t}))
    except ValueError:
        raise ParameterError("recall_at", f"{text!r} is not a comma-separated list of integers") from None
    if not ks or ks[0] < 1:
        raise ParameterError("recall_at", f"{text!r} needs one or more N >= 1")
    return ks


# -- features -------------------------------------------------------------------------------------------
#: Longer image side ``max_side="auto"`` extracts features at: larger images are downscaled to it,
#: smaller ones kept.  A rule per image, so a map's scale does not depend on which tours it was built
#: from first; it also brings cameras of different sizes above it to one scale (gardens_point:
#: 960 x 540 by day, 640 x 360 at night) and, at about half the pixels of 960 x 540, keeps SIFT
#: within a camera's frame time on 2 cores (benchmarks/bench_camera_rate.py, docs/results/performance.md).
AUTO_MAX_SIDE = 640


def parse_max_side(value: int | str) -> int | str:
    """``"auto"`` or a number of pixels >= 0 (0 = no resizing), from a user's text or number."""
    text = str(value).strip().lower()
    if text == "auto":
        return "auto"
    try:
        side = int(text)
    except ValueError:
        raise ParameterError("features.max_side", f"must be 'auto' or a number of pixels, got {value!r}") from None
    if side < 0:
        raise ParameterError("features.max_side", f"must be >= 0 (0 = no resizing), got {side}")
    return side


_told_missing_extra = False


def default_feature_method() -> str:
    """The features ``method="auto"`` means: ``"xfeat"`` where its runtime is installed, else ``"sift"``.

    ``$TOPOLOC_FEATURES`` (a method name) overrides it, e.g. ``sift`` for a site
    whose vocabularies and maps are SIFT's (the test suite sets it so, and tests
    the learned default on its own).  Otherwise decided by whether XFeat's runtime (ONNX Runtime, a dependency of
    topoloc) and its network file can be found, without importing the runtime.  Without them, one
    warning line per process names what is missing.
    """
    global _told_missing_extra
    import os

    from topoloc.features import learned
    from topoloc.features.xfeat import runtimes

    chosen = os.environ.get("TOPOLOC_FEATURES", "").strip().lower()
    if chosen and chosen != "auto":
        from topoloc.features.local import METHODS

        if chosen not in METHODS:
            raise ParameterError("features.method", f"from TOPOLOC_FEATURES must be auto or one of "
                                                    f"{', '.join(METHODS)}, got {chosen!r}")
        return chosen
    if learned.is_installed():
        return "xfeat"
    if not _told_missing_extra:
        _told_missing_extra = True
        log.warning("features: sift, as XFeat's runtime is not installed; XFeat, the default where it is, "
                    "localises far better at night and across seasons: %s", runtimes.INSTALL["onnxruntime"])
    return "sift"


@dataclass(frozen=True)
class FeatureSpec:
    """Which local features a run extracts, and at what scale.

    Parameters
    ----------
    method : {"auto", "sift", "rootsift", "orb", "akaze", "xfeat"}
        ``"auto"`` (the default of every command and of ``Map.build``) is
        :func:`default_feature_method`: XFeat where its runtime (ONNX Runtime,
        a dependency) is installed, which beats SIFT by day, at night and across seasons on the
        development data (``docs/results/learned_features.md``), else SIFT with
        one warning line naming the extra.  It is resolved here, so runs, maps and
        caches record the features actually used.
    max_features : int
        Strongest keypoints kept per image.
    max_side : int or "auto"
        Longer image side to downscale to before extraction (0 = never);
        ``"auto"`` downscales every image whose longer side exceeds
        :data:`AUTO_MAX_SIDE` to that side (:meth:`config`).
    preprocess : {"auto", "none", "clahe", "equalize"}
        Photometric preprocessing (:class:`~topoloc.features.FeatureConfig`).
    """

    method: str = "auto"
    max_features: int = 1000
    max_side: int | str = "auto"
    preprocess: str = "auto"

    def __post_init__(self) -> None:
        # Whether the method was named or left to "auto" (not a field: it is no setting of the run). A saved
        # map's features stand unless a run names other ones, which is then an error, not ignored.
        auto = str(self.method).strip().lower() == "auto"
        object.__setattr__(self, "_named_method", not auto)
        if auto:
            object.__setattr__(self, "method", default_feature_method())
        object.__setattr__(self, "max_side", parse_max_side(self.max_side))
        self._config(0)  # method, max_features and preprocess are FeatureConfig's own checks

    @property
    def method_named(self) -> bool:
        """True when the method was named (``"xfeat"``), False when it came from ``"auto"``."""
        return bool(self.__dict__.get("_named_method", True))

    def _config(self, side: int) -> FeatureConfig:
        from topoloc.features import FeatureConfig

        try:
            return FeatureConfig(method=self.method, max_features=self.max_features, max_side=side,
                                 preprocess=self.preprocess)
        except ParameterError as exc:
            raise ParameterError(f"features.{exc.param.rsplit('.', 1)[-1]}", exc.template, exc.refs) from None

    def config(self) -> FeatureConfig:
        """The feature settings this spec resolves to: ``"auto"`` is :data:`AUTO_MAX_SIDE`.

        One rule per image, whatever other images a run or a map holds, so a
        map built from tours A and B describes every image as one built from A
        and then given B does, and a query is described as it would be in any
        other run (issue 27).  Images whose longer side is at most
        :data:`AUTO_MAX_SIDE` are not resized.
        """
        return self._config(AUTO_MAX_SIDE if self.max_side == "auto" else int(self.max_side))


#: One vocabulary source: a file (or one in memory) or folders to train on.
NOT_BOTH = "is either a file or folders to train one on, not both"


# -- vocabulary -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class VocabularySpec:
    """Where a run's visual vocabulary comes from: a file, or folders to train one on (cached).

    With neither, a method that needs a vocabulary gets the default: one trained on the
    map's own tours (:func:`topoloc.spec.setup.tours_vocabulary`), with ``words`` and ``seed``.

    Parameters
    ----------
    file : Path, optional
        A vocabulary written by ``topoloc vocab train``.
    train : tuple of Path
        Folders (searched recursively) to train one on, never the map or query images.
    words : int
        Words when training.
    seed : int
        Seed of the training's k-means.
    """

    file: Path | None = None
    train: tuple[Path, ...] = ()
    words: int = 10000
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "file", _opt_path(self.file))
        object.__setattr__(self, "train", distinct_paths("vocabulary.train", _paths(self.train)))
        if self.file is not None and self.train:
            raise ParameterError("vocabulary", NOT_BOTH)
        if isinstance(self.words, bool) or not isinstance(self.words, int) or self.words < 1:
            raise ParameterError("vocabulary.words", f"must be a whole number >= 1, got {self.words!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise ParameterError("vocabulary.seed", f"must be a whole number, got {self.seed!r}")

    @property
    def given(self) -> bool:
        """Whether a file or training folders were named."""
        return self.file is not None or bool(self.train)


# -- recordings and image inputs ------------------------------------------------------------------------
@dataclass(frozen=True)
class InputSpec:
    """How ROS bags and videos become frames (image folders need none of it).

    Parameters
    ----------
    topic : str, optional
        Image topic of ROS bags; needed when a bag has several.
    every_s : float, optional
        Keep one frame every T seconds (bags and videos).
    every_m : float, optional
        Keep one frame every D metres of the bag's odometry, pose or GPS topic.
    pose_topic : str, optional
        That topic (default: the bag's first).
    """

    topic: str | None = None
    every_s: float | None = None
    every_m: float | None = None
    pose_topic: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "every_s", _positive("inputs.every_s", self.every_s))
        object.__setattr__(self, "every_m", _positive("inputs.every_m", self.every_m))

    def _given(self) -> list[str]:
        return [f"inputs.{k}" for k in ("topic", "every_s", "every_m", "pose_topic") if getattr(self, k) is not None]

    def check(self, paths: Sequence[Path]) -> None:
        """Refuse recording settings when no input is a bag or a video (they would do nothing)."""
        from topoloc.datasets.sources import is_stream_input

        given = self._given()
        # A missing input is left to the loaders, whose message names it.
        if given and all(Path(p).exists() for p in paths) and not any(
                is_stream_input(Path(p), images_are_files=False) for p in paths):
            verb = "applies" if len(given) == 1 else "apply"
            raise ParameterError("/".join(given), f"{verb} to ROS bags and videos only, and no input is one")

    def load(self, paths: Sequence[str | Path]) -> list[Traverse]:
        """Traverses from folders, bags and videos (a recording's keyframes held in memory)."""
        from topoloc.datasets.sources import load_input

        items = [Path(p) for p in paths]
        self.check(items)
        return [load_input(p, topic=self.topic, every_s=self.every_s, every_m=self.every_m,
                           pose_topic=self.pose_topic) for p in items]

    def frames(self, inputs: Sequence[str | Path], *, on_frame: Callable[[str], None] | None = None,
               check_name: Callable[[str, Path], None] | None = None,
               ) -> tuple[int, Iterator[tuple[str, float | None, np.ndarray, int]]]:
        """``(frames at most, iterator of (name, time_s or None, grey image, index))``: files, folders, recordings.

        Every input is opened and checked before the first frame; bags and
        videos are then streamed (one frame decoded at a time, nothing kept);
        ``index`` is the frame's number in the inputs (:func:`topoloc.datasets.frames.frame_index`).
        ``on_frame``, ``check_name``: see :func:`topoloc.datasets.frames.frame_stream`.
        """
        from topoloc.datasets.frames import frame_stream

        items = [Path(p) for p in inputs]
        self.check(items)
        return frame_stream(items, topic=self.topic, every_s=self.every_s, every_m=self.every_m,
                            pose_topic=self.pose_topic, on_frame=on_frame, check_name=check_name)


# -- ground truth ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GroundTruthSpec:
    """What counts as the right place for a query.

    Parameters
    ----------
    tolerance : str
        ``"HARD:SOFT"`` in place ids: a map place within HARD of the query's is
        right, one within SOFT is neither right nor wrong.
    tolerance_m : str, optional
        The same in metres (needs x, y in ``places.csv``); replaces ``tolerance``.
    file : Path, optional
        A VPR-Bench ``ground_truth_new.npy`` or an ``.npz`` with GThard/GTsoft;
        replaces both.
    """

    tolerance: str = "0:8"
    tolerance_m: str | None = None
    file: Path | None = None

    def __post_init__(self) -> None:
        from topoloc.datasets.groundtruth import parse_tolerance

        object.__setattr__(self, "file", _opt_path(self.file))
        for name in ("tolerance", "tolerance_m"):
            value = getattr(self, name)
            if value is None:
                continue
            try:
                parse_tolerance(value)
            except TopolocError as exc:
                raise ParameterError(f"ground_truth.{name}", str(exc).removeprefix("tolerance ")) from None
        if self.file is not None and not self.file.is_file():
            from topoloc.io.paths import kind_problem

            raise ParameterError("ground_truth.file", f"{kind_problem(self.file, 'file')}: {self.file}")

    @classmethod
    def for_calibration(cls, tolerance: str = "8", tolerance_m: str | None = None) -> GroundTruthSpec:
        """The ground truth of ``map calibrate``: a single number N is ``N:N``, "within N is right"."""
        from topoloc.datasets.groundtruth import calibration_tolerance

        return cls(tolerance=calibration_tolerance(tolerance),
                   tolerance_m=None if tolerance_m is None else calibration_tolerance(tolerance_m))

    def words(self) -> str:
        """What counts as right, as a user reads it: ``"within 8 places"``, ``"within 5 m"``."""
        from topoloc.datasets.groundtruth import parse_tolerance, tolerance_words

        if self.file is not None:
            return f"as in {self.file}"
        if self.tolerance_m is not None:
            return tolerance_words(*parse_tolerance(self.tolerance_m), "m")
        return tolerance_words(*parse_tolerance(self.tolerance), "places")

    def make(self, place_ids: np.ndarray, query: Traverse, *, maps: Sequence[Traverse] = (),
             map_xy: np.ndarray | None = None) -> GroundTruth:
        """Ground truth of shape (n_places, len(query)) from the file, the metric or the place-id tolerance.

        ``map_xy`` (shape (n_places, 2)) gives the places' positions when there
        are no map traverses (a saved map); else they are the mean over the map images.
        """
        from topoloc.datasets.groundtruth import (
            ground_truth_from_file,
            ground_truth_from_places,
            ground_truth_from_xy,
            parse_tolerance,
            place_positions,
        )
        from topoloc.errors import input_error

        if self.file is not None:
            if not maps:
                raise ParameterError("ground_truth.file", "indexes the map's images: give map tours ({maps}), not "
                                                          "a saved map", ("maps",))
            return ground_truth_from_file(self.file, map_traverse=maps[0], place_ids=place_ids,
                                          n_queries=len(query))
        if self.tolerance_m is not None:
            hard, soft = parse_tolerance(self.tolerance_m)
            if query.xy is None:
                raise input_error("a tolerance in metres needs x,y columns in places.csv", query.root)
            positions = map_xy if map_xy is not None else place_positions(list(maps), place_ids)
            return ground_truth_from_xy(positions, query.xy, hard, soft)
        hard, soft = parse_tolerance(self.tolerance)
        return ground_truth_from_places(place_ids, query.places, hard, soft)


# -- sequence matching ----------------------------------------------------------------------------------
#: The sequence matching ``map calibrate`` calibrates by default, which ``localize`` then applies to an
#: ordered input (a folder, bag or video): each frame with the 10 before it along SeqSLAM's constant-velocity
#: lines.  Chosen on the development data (``benchmarks/bench_daynight.py``, docs/results/daynight.md): on
#: gardens_point day_left + day_right -> night_right it lifts coocmap from single images' R@1 0.27 to 0.40 with
#: R@100P 0.00 -> 0.24, and on nordland_64x32 summer -> winter seqslam-single from R@1 0.06 to 0.83; the
#: acceleration search is better on gardens_point (coocmap R@1 0.50) but falls to R@1 0.40 on nordland.
#: Length 10 is SeqSLAM's d_s.
STREAM_SEQUENCE_LENGTH = 10
STREAM_SEQUENCE_MODE = "constant"


def travels_the_route(places: np.ndarray) -> bool:
    """Whether a labelled tour moves along its places, frame after frame, as sequence matching assumes.

    True when at least half of the steps between consecutive frames advance by 1 to 3 place ids:
    a route driven or walked at the map's pace (gardens_point and nordland advance by one place per
    frame).  A stationary camera filmed at several times (the webcam queries: 96% of steps stay at
    one place) or frames of unrelated places are not a sequence.

    Parameters
    ----------
    places : ndarray of int, shape (n_frames,)
        The tour's place id of every frame, in frame order.
    """
    import numpy as np

    steps = np.diff(np.asarray(places, np.int64))
    return bool(steps.size) and float(np.mean((steps >= 1) & (steps <= 3))) >= 0.5


def stream_sequence_for(places: np.ndarray) -> SequenceSpec:
    """The sequence matching ``map calibrate`` calibrates on a tour when not told: the stream default
    (:data:`STREAM_SEQUENCE_LENGTH`, :data:`STREAM_SEQUENCE_MODE`) on a tour that travels the route
    (:func:`travels_the_route`), single images otherwise."""
    if travels_the_route(places):
        return SequenceSpec(length=STREAM_SEQUENCE_LENGTH, mode=STREAM_SEQUENCE_MODE)
    return SequenceSpec()


@dataclass(frozen=True)
class SequenceSpec:
    """Sequence matching: each query with the ``length`` before it (0 = single images).

    Parameters
    ----------
    length : int
        Frames before each query that take part (0 = off).
    mode : {"constant", "acceleration"}
        SeqSLAM's constant-velocity lines, or Cooc-Map's forward paths (II-F).
    """

    length: int = 0
    mode: str = "constant"

    def __post_init__(self) -> None:
        if isinstance(self.length, bool) or not isinstance(self.length, int) or self.length < 0:
            raise ParameterError("sequence.length", f"must be a whole number >= 0 (0 = off), got {self.length!r}")
        if self.mode not in SEQUENCE_MODES:
            raise ParameterError("sequence.mode", f"must be one of {', '.join(SEQUENCE_MODES)}, got {self.mode!r}")
        if self.length:
            self.check_memory()

    def check_memory(self, n_places: int | None = None, *, online: bool = False) -> None:
        """Refuse a length whose search would take more than :data:`~topoloc.sequence.SEQUENCE_MEMORY_BUDGET`.

        Checked before anything is allocated: the search's tiles grow with the
        square (constant velocity) or cube (acceleration) of the length.

        Parameters
        ----------
        n_places : int, optional
            Places of the map (unknown: a full tile is counted).
        online : bool
            Also count what an online localiser keeps: the last ``length + 1``
            score columns of ``n_places`` float32 each, and their stacked copy.

        Raises
        ------
        ParameterError
            Naming ``sequence.length``.
        """
        from topoloc.sequence import SEQUENCE_MEMORY_BUDGET, search_memory_bytes

        need = search_memory_bytes(self.length, mode=self.mode, n_db=n_places)  # type: ignore[arg-type]
        if online and n_places is not None:
            need += 2 * 4 * n_places * (self.length + 1)
        if need > SEQUENCE_MEMORY_BUDGET:
            where = f" over {n_places} places" if n_places is not None else ""
            raise ParameterError("sequence.length", (
                f"{self.length} is too long: its {self.mode} search{where} would need {need / 2**30:.1f} GiB, "
                f"more than the budget of {SEQUENCE_MEMORY_BUDGET / 2**30:.0f} GiB (SEQUENCE_MEMORY_BUDGET)"))


# -- where the work runs --------------------------------------------------------------------------------
@dataclass(frozen=True)
class ExecutionSpec:
    """Where per-image work runs, and the cache it reads and fills.

    Parameters
    ----------
    scheduler : str, optional
        Dask scheduler address (``tcp://host:8786``); default ``$TOPOLOC_SCHEDULER``,
        else this machine's threads.
    scheduler_timeout : float, optional
        Seconds to wait for the scheduler and a worker.
    cache_dir : Path, optional
        Feature and vocabulary cache (default ``~/.cache/topoloc`` or ``$TOPOLOC_CACHE_DIR``).
    """

    scheduler: str | None = None
    scheduler_timeout: float | None = None
    cache_dir: Path | None = None

    def __post_init__(self) -> None:
        if self.scheduler is not None:
            from topoloc.cluster import check_scheduler_address

            if not isinstance(self.scheduler, str):
                raise ParameterError("execution.scheduler", f"must be an address such as tcp://host:8786, "
                                                            f"got {self.scheduler!r}")
            # Checked here, before any file is read: Dask itself fails late, with a traceback, on `http://`.
            # An empty address means $TOPOLOC_SCHEDULER, which cluster.connect checks.
            address = self.scheduler.strip()
            problem = check_scheduler_address(address) if address else None
            if problem is not None:
                raise ParameterError("execution.scheduler", problem)
        object.__setattr__(self, "scheduler_timeout",
                           _positive("execution.scheduler_timeout", self.scheduler_timeout,
                                     what="a positive number of seconds"))
        object.__setattr__(self, "cache_dir", _opt_path(self.cache_dir))

    def connect(self) -> Any:
        """The run's executor (:func:`topoloc.cluster.connect`): a Dask client, or this machine's threads."""
        from topoloc.cluster import connect

        return connect(self.scheduler, timeout_s=self.scheduler_timeout)


def verify_from_env() -> bool | None:
    """``$TOPOLOC_VERIFY`` (``1``/``0``/``auto``): whether answers are verified where no option says; None when
    unset or ``auto``; any other value is refused (one line naming it), whatever else is given."""
    import os

    value = os.environ.get("TOPOLOC_VERIFY", "").strip().lower()
    if not value or value == "auto":
        return None
    if value in ("1", "true", "yes", "on"):
        return True
    if value in ("0", "false", "no", "off"):
        return False
    raise ParameterError("verification.enabled", f"from TOPOLOC_VERIFY must be 1, 0 or auto, got {value!r}")


#: Where a run's choice to verify came from (:func:`choose_verify`), strongest first.
VERIFY_SOURCES = ("option", "TOPOLOC_VERIFY", "the map's calibration", "the map's build", "the map's age",
                  "the method", "default")


@dataclass(frozen=True)
class VerifyChoice:
    """Whether a run verifies its answers, and what said so (:func:`choose_verify`).

    Attributes
    ----------
    enabled : bool or None
        True: verify (a map that cannot is then an error when the source is
        explicit, else unverified with one warning line); False: never; None:
        wherever the map's images can be read.
    source : str
        One of :data:`VERIFY_SOURCES`.
    """

    enabled: bool | None
    source: str

    @property
    def explicit(self) -> bool:
        """Whether the user asked (an option, a ROS parameter, ``$TOPOLOC_VERIFY``), not a record or a default."""
        return self.source in ("option", "TOPOLOC_VERIFY")


def choose_verify(asked: bool | None, *, calibrated: bool | None = None, built: bool | None = None,
                  legacy: bool = False, checks_geometry: bool = False) -> VerifyChoice:
    """The one precedence of the choice to verify (``docs/protocol.md``, "Verification", "The default").

    In order: the run's option (``--verify/--no-verify``, the ROS node's
    ``verify`` parameter, ``verify=`` in Python); ``$TOPOLOC_VERIFY`` (``1``,
    ``0`` or ``auto``; any other value is refused even where an option is
    given); the map's calibration (``map calibrate`` records whether its
    threshold was chosen on verified answers); the map's build
    (``map build --verify/--no-verify``); a map saved before verification
    existed (``legacy``) is not verified; a method that checks geometry itself
    is not verified again; else wherever the map's images can be read.

    Parameters
    ----------
    asked : bool or None
        The run's option (None: not given).
    calibrated, built : bool or None
        What the map records (None: nothing; ``built`` None is also "wherever it can").
    legacy : bool
        A saved map with no record of verification at all.
    checks_geometry : bool
        The method's ``verifies_geometry`` tag.
    """
    env = verify_from_env()  # parsed first: a bad value is refused whatever else is given
    if asked is not None:
        return VerifyChoice(bool(asked), "option")
    if env is not None:
        return VerifyChoice(env, "TOPOLOC_VERIFY")
    if calibrated is not None:
        return VerifyChoice(bool(calibrated), "the map's calibration")
    if built is not None:
        return VerifyChoice(bool(built), "the map's build")
    if legacy:
        return VerifyChoice(False, "the map's age")
    if checks_geometry:
        return VerifyChoice(False, "the method")
    return VerifyChoice(None, "default")


@dataclass(frozen=True)
class VerificationSpec:
    """Geometric verification of each answer's candidates (:mod:`topoloc.verification`).

    Parameters
    ----------
    enabled : bool or None
        Re-check the best places of each query's highest distinct peaks by
        local matches and epipolar geometry, and decide whether the answer is
        verified (``docs/protocol.md``, "Verification").  None (the default):
        as :func:`choose_verify` says (wherever the map's images can be read,
        unless ``$TOPOLOC_VERIFY`` or the map's record says otherwise); True:
        verify; False: never.
    candidates : int or None
        Distinct peaks checked per query; None (default): 3 for single images,
        the sequence's best place only with ``--sequence N``
        (:func:`topoloc.verification.default_candidates`).
    confirm : bool
        Temporal consistency for streams (:mod:`topoloc.verification.consistency`):
        an answer not confirmed by the previous frame's ranks below every
        confirmed one.  Off by default: it did not pay on the development data
        (``docs/results/verification.md``, part ``consistency``).
    min_support : int or None
        The support (inliers that are distinctive matches) a verified answer
        needs, at any feature cap (``docs/results/verification.md``, part
        ``caps``).  None (default): against a saved map, the floor its
        calibration's answers were verified with, else the one it was built
        with (:func:`topoloc.maps.verify_policy.with_map_floor`), else
        :data:`topoloc.verification.MIN_SUPPORT`, chosen on the development data
        (``docs/results/verification.md``, part ``floor``); ``--min-support``.
    """

    enabled: bool | None = None
    candidates: int | None = None
    confirm: bool = False
    min_support: int | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.confirm, bool):
            raise ParameterError("verification.confirm", f"must be true or false, got {self.confirm!r}")
        if self.enabled is not None and not isinstance(self.enabled, bool):
            raise ParameterError("verification.enabled", f"must be true or false, got {self.enabled!r}")
        if self.candidates is not None and (isinstance(self.candidates, bool) or not isinstance(self.candidates, int)
                                            or self.candidates < 1):
            raise ParameterError("verification.candidates", f"must be a whole number >= 1, got {self.candidates!r}")
        if self.min_support is not None and (isinstance(self.min_support, bool) or not isinstance(self.min_support, int)
                                             or self.min_support < 8):
            raise ParameterError("verification.min_support", f"must be a whole number >= 8, got {self.min_support!r}")

    def rule(self) -> VerificationRule:
        """The decision's settings (a floor not given: :data:`~topoloc.verification.MIN_SUPPORT`)."""
        return VerificationRule(min_support=MIN_SUPPORT if self.min_support is None else self.min_support)


PARTS: dict[str, type] = {
    "features": FeatureSpec, "vocabulary": VocabularySpec, "inputs": InputSpec, "ground_truth": GroundTruthSpec,
    "sequence": SequenceSpec, "execution": ExecutionSpec,
    "verification": VerificationSpec,
}


__all__ = [
    "AUTO_MAX_SIDE",
    "PARTS",
    "SEQUENCE_MODES",
    "VERIFY_SOURCES",
    "ExecutionSpec",
    "FeatureSpec",
    "GroundTruthSpec",
    "InputSpec",
    "SequenceSpec",
    "VerificationSpec",
    "VerifyChoice",
    "VocabularySpec",
    "choose_verify",
    "parse_max_side",
    "parse_recall_at",
    "stream_sequence_for",
    "travels_the_route",
    "verify_from_env",
]
