"""A map's confusion: the support a map image of another place reaches at each place, learned at build.

Verification (:mod:`topoloc.verification.decision`, step 2) asks of a
verified answer more support than a look-alike gets.  Which places look alike
is a property of the map, learned from its own images without labels: each
map image (at most :data:`SAMPLE`, spread evenly over the tours) is scored
against the map by the method, as a query would be; the places within
:data:`BAND` place ids of its own (the same place, or the same stretch of the
route) are set aside, and the best places of the :data:`CANDIDATES` highest
distinct peaks of the rest (the method's hard negatives) are checked as
verification checks a query's candidates.  The confusion ``c_p`` of a place
is the most support any such check reached at it, or from it: both places of
a look-alike pair are confusable.  Which places reached it is kept too, the
:data:`LOOK_ALIKES` strongest per place (:class:`~topoloc.verification.LookAlikes`):
a query whose answer only the confusion refuses is checked against them, and
a look-alike it tells apart does not count (``verification.decision``, step 2).

A map that stores one scene under two place ids (a loop that was not closed,
tours of the same places given other ids) learns a high confusion at both, and
answers there are not verified: which of the two ids is meant, the images
cannot say.
"""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from topoloc.datasets.traverse import Traverse
from topoloc.methods.base import PlaceRecognizer
from topoloc.progress import ProgressFactory
from topoloc.resources import Resources
from topoloc.verification import LookAlikes, Verifier, candidate_rows

log = logging.getLogger(__name__)

#: Map images checked at most: every image of a map of up to this many, an even spread of a larger one (3 pair
#: checks of about 5 ms each per image: 45 s at most).  With 300, a map of 931 places (the crowded map) learned
#: no confusion at a quarter of its places, never a source and never a look-alike of one; with every image, at
#: all of them, at the cost of two of its 100 verified right answers and none elsewhere
#: (``docs/results/verification.md``, set ``crowded``, against this page as of commit 22671b2c).
SAMPLE: Final = 3000
#: Places within this many ids of an image's own place are its place (the default calibration tolerance).
BAND: Final = 8
#: The method's best distinct peaks outside the band checked per image.
CANDIDATES: Final = 3
#: Look-alike places kept per place, strongest first (a query is checked against those whose support reaches its
#: own; beyond them, the last one's support bounds the rest).
LOOK_ALIKES: Final = 3
#: Cells of ``S`` scored at once (256 MB of float64): a map of 100,000 places scores its sampled images in
#: blocks of 320 rather than all 3,000 at once (2.4 GB); every map of the development data in one block.
BLOCK_CELLS: Final = 32_000_000


@dataclass(frozen=True)
class Confusion:
    """The confusion of each place of a map and how it was learned.

    Attributes
    ----------
    values : ndarray of float32, shape (n_places,)
        ``c_p`` of each place row (0: no look-alike found).
    images : int
        Map images checked.
    band : int
        Place ids around an image's own that counted as its place.
    candidates : int
        Distinct peaks checked per image.
    seconds : float
        Time it took.
    look_alikes : LookAlikes or None
        The places that reached each value (None for maps saved before they were kept).
    """

    values: np.ndarray
    images: int
    band: int = BAND
    candidates: int = CANDIDATES
    seconds: float = 0.0
    look_alikes: LookAlikes | None = None

    def __post_init__(self) -> None:
        if self.look_alikes is not None and len(self.look_alikes) != len(self.values):
            raise ValueError(f"look-alikes of {len(self.look_alikes)} places for a confusion of {len(self.values)}")

    def record(self) -> dict[str, Any]:
        """What a map's header says of it (the values are an array of the file)."""
        v = self.values
        return {"images": self.images, "band": self.band, "candidates": self.candidates,
                "seconds": round(self.seconds, 2), "places_confusable": int((v > 0).sum()),
                "max": float(v.max()) if len(v) else 0.0,
                "look_alikes": 0 if self.look_alikes is None else int(self.look_alikes.rows.shape[1])}

    def install(self, verifier: Verifier) -> None:
        """Give ``verifier`` this confusion and its look-alikes (the one way a map's confusion reaches a verifier)."""
        verifier.confusable, verifier.look_alikes = self.values, self.look_alikes

    @classmethod
    def from_record(cls, values: np.ndarray, record: dict[str, Any], look_alikes: LookAlikes | None = None
                    ) -> Confusion:
        return cls(np.asarray(values, np.float32), int(record.get("images", 0)), int(record.get("band", BAND)),
                   int(record.get("candidates", CANDIDATES)), float(record.get("seconds", 0.0)), look_alikes)


def note_look_alike(rows: np.ndarray, support: np.ndarray, p: int, b: int, n: float) -> None:
    """Record in place that place row ``b`` reached support ``n`` at place row ``p``.

    ``rows`` and ``support`` (shape (n_places, k)) keep each place's ``k``
    strongest look-alikes, one slot per place row, most support first; a
    look-alike already kept keeps its highest support.
    """
    if n <= 0 or b == p:
        return
    r, s = rows[p], support[p]
    hit = np.flatnonzero(r == b)
    if len(hit):
        s[hit[0]] = max(s[hit[0]], n)
    elif n > s[-1]:
        r[-1], s[-1] = b, n
    else:
        return
    order = np.argsort(-s, kind="stable")
    r[:], s[:] = r[order], s[order]


def sample_images(sizes: Sequence[int], n: int) -> list[np.ndarray]:
    """Indices of at most ``n`` images spread evenly over tours of ``sizes`` images, one array per tour."""
    total = int(sum(sizes))
    pick = np.unique(np.linspace(0, total - 1, min(n, total)).round().astype(np.int64)) if total else np.zeros(0, int)
    starts = np.cumsum([0, *sizes])
    return [pick[(pick >= a) & (pick < b)] - a for a, b in itertools.pairwise(starts)]


def learn_confusion(recognizer: PlaceRecognizer, tours: Sequence[Traverse], resources: Resources,
                    verifier: Verifier, *, sample: int = SAMPLE, band: int = BAND, candidates: int = CANDIDATES,
                    progress: ProgressFactory | None = None) -> Confusion:
    """The confusion of every place of a fitted recogniser's map (module docstring).

    Parameters
    ----------
    recognizer : PlaceRecognizer
        Fitted on ``tours``.
    tours : sequence of Traverse
        The map's tours.
    resources : Resources
        Their features (the run's).
    verifier : Verifier
        The verification stage over the same map (its checks are reused).
    sample, band, candidates : int
        :data:`SAMPLE`, :data:`BAND`, :data:`CANDIDATES`.
    """
    t0 = time.perf_counter()
    place_ids = np.asarray(recognizer.place_ids_)
    values = np.zeros(len(place_ids), np.float32)
    alikes = LookAlikes(np.full((len(place_ids), LOOK_ALIKES), -1, np.int64),
                        np.zeros((len(place_ids), LOOK_ALIKES), np.float32))
    picks = sample_images([len(t) for t in tours], sample)
    n_images = int(sum(len(p) for p in picks))
    advance = progress("map confusion", n_images) if progress is not None and n_images else None
    block = max(1, BLOCK_CELLS // max(len(place_ids), 1))
    for tour, tour_idx in zip(tours, picks, strict=True):
        for start in range(0, len(tour_idx), block):
            _check_block(recognizer, tour.take(tour_idx[start:start + block]), resources, verifier, place_ids,
                         values, alikes, band, candidates, advance)
    c = Confusion(values, n_images, band, candidates, time.perf_counter() - t0, alikes)
    log.info("map confusion: %d images checked in %.1f s, %d places confusable", n_images, c.seconds,
             int((values > 0).sum()))
    return c


def _check_block(recognizer: PlaceRecognizer, sub: Traverse, resources: Resources, verifier: Verifier,
                 place_ids: np.ndarray, values: np.ndarray, alikes: LookAlikes, band: int, candidates: int,
                 advance: Callable[[int], object] | None) -> None:
    """Raise ``values`` and note ``alikes`` (in place) by the checks of the map images of ``sub`` against their
    hard negatives."""
    S = np.array(recognizer.similarity(sub, resources=resources), dtype=np.float64)
    feats = resources.features(sub, timed=False)
    same = np.abs(place_ids[:, None] - np.asarray(sub.places)[None, :]) <= band
    S[same] = -np.inf
    rows, _, _ = candidate_rows(S, candidates)
    own = np.searchsorted(place_ids, sub.places)
    for j, f in enumerate(feats):
        for r in rows[j]:
            if r < 0:
                continue
            n = verifier.check(f, int(r))[0].support
            values[r] = max(values[r], n)
            if own[j] < len(values) and place_ids[own[j]] == sub.places[j]:
                values[own[j]] = max(values[own[j]], n)
                note_look_alike(alikes.rows, alikes.support, int(r), int(own[j]), n)
                note_look_alike(alikes.rows, alikes.support, int(own[j]), int(r), n)
        if advance is not None:
            advance(1)


__all__ = ["BAND", "BLOCK_CELLS", "CANDIDATES", "LOOK_ALIKES", "SAMPLE", "Confusion", "learn_confusion",
           "note_look_alike", "sample_images"]
