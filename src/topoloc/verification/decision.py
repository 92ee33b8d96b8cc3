"""What verifies an answer, and the confidence of every answer: the one home of the rule.

An answer (a query's place, after the reranking of
:mod:`topoloc.verification.rerank`) is **verified** when three things hold
(``docs/protocol.md``, "Verification", with the numbers of
``docs/results/verification.md``):

1. **Support.**  Its support ``n`` (inliers that are distinctive matches,
   :mod:`topoloc.verification.pairs`) reaches the floor ``n_min`` = 25: on the
   development data no frame of a place the map does not hold reached 13, and
   with 25 no wrong answer and one hard negative (each query against its best
   place outside the tolerance) of about 1,300 is verified, against three
   wrong answers and eight hard negatives with 20 (``docs/results/verification.md``, part ``floor``, where every
   floor from 12 to 30 is measured).  The floor is the same at any feature
   cap (``--max-features``): the support chance reaches does not follow the
   features there are to match (with fewer, more matches pass Lowe's ratio
   by chance, their second-nearest neighbours farther off), and neither does
   a right answer's (part ``caps``: a floor in proportion to the cap, 13 at
   500 features, verified 2 wrong answers, 16 hard negatives and 1 off-map
   frame, and 50 at 2000 left gardens_point's verified-right at night at
   0.54, against none of those and 0.80 with 25).
2. **The map's own confusion.**  ``n`` exceeds ``c_p``, the most support a
   map image of another place reached at this place when the map checked its
   own images against itself at build time (:mod:`topoloc.maps.confusion`):
   a place that looks like another place of the same map (repeated
   structure, the same scene stored twice, a loop the map did not close)
   needs more than that look-alike gets.  It needs no labels and follows each
   map.  A look-alike the query itself tells apart from the answer does not
   count (:func:`query_confusion`): where the map recorded which places
   reached ``c_p`` (:class:`LookAlikes`), the query is checked against each
   whose support reaches ``n``, and one at which the query has clearly less
   support than at the answer (:func:`tells_apart`) is set aside.  ``c_p`` is
   learned between map images, taken in the same conditions; a query taken
   in others (at night against a day map) reaches less at the right place
   and at its look-alike alike, so the query's own comparison is the fairer
   one (verified-right at night with Cooc-Map 0.80 with it, 0.77 without;
   bag of words 0.79 and 0.75; no wrong answer either way:
   ``docs/results/verification.md``, part ``quality``, against the page as
   of commit 351f9dc0).
3. **A peak of the evidence.**  Neither route neighbour of the place (the
   places next to it in place-id order) has more support; where one has, the
   answer moves there (at most :data:`CLIMB` steps) and is verified there, and
   a neighbour the query may not be (a score of ``-inf``) leaves it
   unverified: a place a few steps away along the route still shares much of
   the view, and the support says which side the query is on.  An answer
   climbs from half the floor (:attr:`VerificationRule.climb_from`): the
   candidate a method ranks best is often a step beside the place the query
   shares most with, where it has less support than there (verified-right
   with Cooc-Map at night 0.77, on the crowded map 0.45, where climbing from
   the floor itself gave 0.73 and 0.37, with no wrong answer in either:
   ``docs/results/verification.md``, part ``quality``, as of commits 22671b2c
   and 857fafc3, both with the confusion learned from 300 map images).

    verified = (n >= n_min) and (n > c_q) and peak

with ``c_q`` the map's confusion ``c_p`` less the look-alikes the query tells apart (step 2; ``c_q = c_p`` where the
map recorded no look-alikes).

The **strength** of the answer is ``x = n / max(n_min, c_q + 1)`` (>= 1
exactly when the first two hold), and its **confidence** an estimate of the
probability that it is right::

    confidence = 1 / (1 + exp(-(a + b log x + c [verified])))

with ``(a, b, c)`` fitted by logistic regression on labelled answers: the
development data's by default (:data:`DEFAULT_CONFIDENCE`), a map's own
labelled tour after ``map calibrate`` (:meth:`ConfidenceModel.fit`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from topoloc.verification.pairs import MIN_SAMPLE, RATIO

#: Support an answer needs, at any feature cap (decision step 1; verification.md, parts ``floor`` and ``caps``).
MIN_SUPPORT: Final = 25

#: Steps an answer may move along the route to the peak of the evidence (decision step 3).
CLIMB: Final = 3

#: RANSAC iterations per candidate: they bound the stage's time on wrong pairs, which run all of them (each
#: candidate is fitted in full: ``docs/protocol.md``, "Verification", step 4).
DEFAULT_MAX_ITERS: Final = 1000


@dataclass(frozen=True)
class VerificationRule:
    """The settings of the decision (:class:`topoloc.spec.VerificationSpec` makes one).

    Parameters
    ----------
    min_support : int
        The floor ``n_min``.
    ratio : float
        Lowe's ratio of a distinctive match (:data:`topoloc.verification.pairs.RATIO`).
    max_iters : int
        RANSAC iterations per candidate.
    climb : int
        Steps along the route to the peak of the evidence (0: no route neighbour is checked).
    """

    min_support: int = MIN_SUPPORT
    ratio: float = RATIO
    max_iters: int = DEFAULT_MAX_ITERS
    climb: int = CLIMB

    @property
    def climb_from(self) -> int:
        """The support from which an answer climbs to the peak of the evidence: half the floor (step 3)."""
        return max(MIN_SAMPLE + 1, self.min_support // 2)

    def __post_init__(self) -> None:
        for name, value, low in (("min_support", self.min_support, MIN_SAMPLE + 1), ("max_iters", self.max_iters, 1),
                                 ("climb", self.climb, 0)):
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"{name} must be a whole number >= {low}, got {value!r}")
        if not 0 < self.ratio <= 1:
            raise ValueError(f"ratio must be in (0, 1], got {self.ratio!r}")


def verified(support: np.ndarray, confusable: np.ndarray, peak: np.ndarray, min_support: int) -> np.ndarray:
    """The decision (module docstring): ``(n >= n_min) & (n > c_q) & peak``, element by element.

    Parameters
    ----------
    support : ndarray of int, shape (n,)
        Each answer's support ``n``.
    confusable : ndarray, shape (n,)
        The confusion ``c_q`` at each answer's place (:func:`query_confusion`; 0 where unknown).
    peak : ndarray of bool, shape (n,)
        Whether no route neighbour has more support (decision step 3).
    min_support : int
        ``n_min``.

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    n = np.asarray(support)
    return np.asarray((n >= min_support) & (n > np.asarray(confusable)) & np.asarray(peak, bool), bool)


def tells_apart(n_a: np.ndarray | float, n_b: np.ndarray | float) -> np.ndarray:
    """Whether a count ``n_a`` is clearly more than ``n_b``: ``n_a - n_b > sqrt(n_a + n_b)``.

    One standard deviation of the difference of two counts: what
    :func:`~topoloc.verification.rerank.choose_winner` calls as good as the
    same, and where a query tells its answer from a look-alike (step 2).

    Parameters
    ----------
    n_a, n_b : float or ndarray
        Counts (inliers or support), broadcast together.

    Returns
    -------
    ndarray of bool
    """
    a = np.asarray(n_a, np.float64)
    b = np.asarray(n_b, np.float64)
    return np.asarray(a - b > np.sqrt(np.maximum(a + b, 0.0)), bool)


@dataclass(frozen=True)
class LookAlikes:
    """Which places reached each place's confusion: the ``k`` strongest look-alikes of every place of a map.

    Attributes
    ----------
    rows : ndarray of int64, shape (n_places, k)
        Each place's look-alike place rows, most support first; -1 for an empty slot.
    support : ndarray of float32, shape (n_places, k)
        The support each reached there (0 for an empty slot).
    """

    rows: np.ndarray
    support: np.ndarray

    def __post_init__(self) -> None:
        rows, sup = np.asarray(self.rows), np.asarray(self.support)
        if rows.ndim != 2 or rows.shape != sup.shape:
            raise ValueError(f"look-alike rows {rows.shape} and support {sup.shape} must be equal 2-D shapes")
        if not np.isfinite(sup).all():
            raise ValueError("look-alike support must be finite")
        if ((rows < 0) != (sup <= 0)).any():
            raise ValueError("a look-alike slot has a row exactly when it has support")

    def __len__(self) -> int:
        return int(self.rows.shape[0])


def query_confusion(c_p: float, alike_support: np.ndarray, query_support: np.ndarray, n: int) -> float:
    """``c_q``: the map's confusion at the answer's place, less the look-alikes this query tells apart (step 2).

    Parameters
    ----------
    c_p : float
        The map's confusion at the answer's place.
    alike_support : ndarray, shape (k,)
        The support each of its stored look-alikes reached there (:class:`LookAlikes`, most first; 0: empty slot).
    query_support : ndarray, shape (k,)
        The query's own support at each look-alike; negative where it was not checked.
    n : int
        The query's support at the answer.

    Returns
    -------
    float
        The largest of: the support of a look-alike the query does not tell apart (:func:`tells_apart`),
        the ``k``-th look-alike's support when every slot is taken (look-alikes beyond the ``k`` stored reach
        at most that), and ``c_p`` itself where no stored look-alike reached it.
    """
    s = np.asarray(alike_support, np.float64)
    q = np.asarray(query_support, np.float64)
    if s.shape != q.shape or s.ndim != 1:
        raise ValueError(f"look-alike support {s.shape} and the query's {q.shape} must be equal 1-D shapes")
    if len(s) == 0 or float(s.max()) < c_p:
        return float(c_p)
    told = (q >= 0) & tells_apart(n, np.maximum(q, 0.0))
    kept = float(np.where(told, 0.0, s).max())
    rest = float(s[-1])  # 0 unless every slot is taken
    return max(kept, rest)


def strength(support: np.ndarray, confusable: np.ndarray, min_support: int) -> np.ndarray:
    """``x = n / max(n_min, c_q + 1)``: >= 1 when the support passes decision steps 1 and 2."""
    c = np.asarray(confusable, np.float64)
    return np.asarray(support, np.float64) / np.maximum(float(min_support), c + 1.0)


@dataclass(frozen=True)
class ConfidenceModel:
    """``confidence = sigmoid(a + b u + c [verified])``: the probability an answer is right (module docstring).

    Attributes
    ----------
    a, b, c : float
    on : {"strength", "score"}
        What ``u`` is: ``log x`` of a verified run's answer (its strength), or
        the method's own score of an unverified run's (``map calibrate --no-verify``).
    source : str
        What it was fitted on, in words (shown by ``map info`` and reports).
    n : int
        Labelled answers it was fitted on.
    """

    a: float
    b: float
    c: float
    on: str = "strength"
    source: str = ""
    n: int = 0

    def inputs(self, *, strength: np.ndarray | None = None, score: np.ndarray | None = None) -> np.ndarray:
        """``u`` of answers of these strengths (``on="strength"``) or method scores (``on="score"``)."""
        if self.on == "score":
            if score is None:
                raise ValueError("this confidence model reads the method's score")
            return np.asarray(score, np.float64)
        if strength is None:
            raise ValueError("this confidence model reads the answers' strength")
        return np.log(np.maximum(np.asarray(strength, np.float64), 1e-3))

    def __call__(self, u: np.ndarray, is_verified: np.ndarray) -> np.ndarray:
        """The confidence of answers of inputs ``u`` (shape (n,), :meth:`inputs`), verified or not; in (0, 1)."""
        z = self.a + self.b * np.asarray(u, np.float64) + self.c * np.asarray(is_verified, np.float64)
        with np.errstate(over="ignore"):
            return np.asarray(1.0 / (1.0 + np.exp(-z)), np.float64)

    @classmethod
    def fit(cls, u: np.ndarray, is_verified: np.ndarray, right: np.ndarray, *, on: str = "strength",
            source: str = "", prior: ConfidenceModel | None = None) -> ConfidenceModel:
        """Fit ``(a, b, c)`` by logistic regression on labelled answers (inputs ``u``, :meth:`inputs`).

        Where the answers hold fewer than 10 right or 10 wrong ones (nothing
        to tell apart), only ``a`` is fitted: the mean confidence then equals
        the fraction right (with one pseudo-count of each kind), ``b`` and
        ``c`` kept from the ``prior`` (default :data:`DEFAULT_CONFIDENCE` for
        ``on="strength"``; a flat slope of 0 for scores).
        """
        from sklearn.linear_model import LogisticRegression

        y = np.asarray(right, bool)
        u = np.asarray(u, np.float64)
        v = np.asarray(is_verified, np.float64)
        if prior is None:
            prior = DEFAULT_CONFIDENCE if on == "strength" else cls(0.0, 0.0, 0.0, on)
        if min(int(y.sum()), int((~y).sum())) < 10:
            z = prior.b * u + prior.c * v
            target = (y.sum() + 1.0) / (len(y) + 2.0)
            lo, hi = -40.0, 40.0
            for _ in range(80):  # bisection: the mean confidence is the fraction right
                mid = 0.5 * (lo + hi)
                if float(np.mean(1.0 / (1.0 + np.exp(-(mid + z))))) < target if len(y) else mid < 0:
                    lo = mid
                else:
                    hi = mid
            return cls(0.5 * (lo + hi), prior.b, prior.c, on, source, len(y))
        X = np.c_[u, v] if v.any() and not v.all() else u[:, None]
        clf = LogisticRegression(C=10.0, max_iter=1000).fit(X, y)
        c = float(clf.coef_[0, 1]) if X.shape[1] == 2 else (prior.c if on == "strength" else 0.0)
        return cls(float(clf.intercept_[0]), float(clf.coef_[0, 0]), c, on, source, len(y))

    def to_dict(self) -> dict[str, Any]:
        return {"a": self.a, "b": self.b, "c": self.c, "on": self.on, "source": self.source, "n": self.n}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ConfidenceModel:
        on = str(d.get("on", "strength"))
        if on not in ("strength", "score"):
            raise ValueError(f"a confidence model reads 'strength' or 'score', not {on!r}")
        return cls(float(d["a"]), float(d["b"]), float(d["c"]), on, str(d.get("source", "")), int(d.get("n", 0)))


#: Fitted on the development data's Cooc-Map answers, every set pooled (gardens_point day and night, the webcams,
#: michigan_seasons, the crowded map, and frames of no mapped place against a gardens_point and a webcam map:
#: 2,422 answers; verification.md, part ``confidence``, which also scores it leaving each set out).
DEFAULT_CONFIDENCE = ConfidenceModel(a=3.649, b=3.047, c=2.495, on="strength",
                                     source="development data (verification.md)")


__all__ = ["CLIMB", "DEFAULT_CONFIDENCE", "DEFAULT_MAX_ITERS", "MIN_SUPPORT", "ConfidenceModel",
           "LookAlikes", "VerificationRule", "query_confusion", "strength", "tells_apart", "verified"]
