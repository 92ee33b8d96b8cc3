"""Bag-of-words baseline: tf-idf weighting, inverted file, cosine similarity.

Sivic & Zisserman, "Video Google" (ICCV 2003).  Each map image is a document
whose words are the visual words of its local features.  With ``n_id`` the
count of word ``i`` in document ``d``, ``n_d`` the number of words in ``d``,
``N`` the number of map images and ``N_i`` the number of map images containing
word ``i``, the weights are

    t_id = (n_id / n_d) * log(N / N_i),

each document vector is L2-normalised and the similarity of a query to a map
image is the cosine (dot product of normalised vectors).  The product is
evaluated through the inverted file (word -> map images), so a query touches
only the postings of its own words.

Several images of one place (from one or several map traverses) are merged
per place by ``merge``: ``"max"`` keeps the best-matching image (a night query
can match the night tour), ``"sum"`` pools the images' word counts into one
document per place.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np
import scipy.sparse as sp

from topoloc._params import Constraint, Options
from topoloc.bow.tfidf import (
    cosine_scores,
    inverse_document_frequency,
    inverted_file,
    merge_documents,
    term_counts,
)
from topoloc.confidence import CONFIDENCE_MODES
from topoloc.datasets.traverse import Traverse
from topoloc.errors import TopolocError
from topoloc.io.state import new_object, object_state, restore_state
from topoloc.methods.base import PlaceRecognizer
from topoloc.methods.shards import ShardPart, merge_order
from topoloc.resources import Resources


class BagOfWords(PlaceRecognizer):
    """tf-idf bag-of-words with an inverted file (Sivic & Zisserman 2003).

    Parameters
    ----------
    merge : {"max", "sum"}
        How images of the same place are combined (see module docstring).
    confidence : {"margin", "raw"}
        ``"margin"`` (default): each query's column is shifted so that its
        best score is its margin over the best place outside the best
        place's peak, a confidence comparable across queries (same order
        within a column; :mod:`topoloc.confidence`).
        ``"raw"``: the cosine similarities.

    Attributes
    ----------
    place_ids_ : ndarray of int64, shape (n_places,)
    idf_ : ndarray of float32, shape (n_words,)
    inverted_ : scipy.sparse.csr_matrix, shape (n_words, n_documents)
        The inverted file: row ``i`` lists the documents containing word ``i``
        with their normalised tf-idf weights.
    doc_place_ : ndarray of int64, shape (n_documents,)
        Row of ``S`` of each document.
    counts_ : scipy.sparse.csr_matrix, shape (n_documents, n_words)
        Word counts of every map image (the documents), kept so that tours can be added.
    doc_places_ : ndarray of int64, shape (n_documents,)
        Place id of each document.
    """

    name: ClassVar[str] = "bow"
    uses_vocabulary: ClassVar[bool] = True
    parameter_constraints: ClassVar[Mapping[str, Constraint]] = {
        "merge": Options(("max", "sum")), "confidence": Options(CONFIDENCE_MODES),
    }

    def __init__(self, *, merge: str = "max", confidence: str = "margin") -> None:
        self.merge = merge
        self.confidence = confidence

    def _fit(self, maps: list[Traverse], resources: Resources) -> None:
        words = [w for m in maps for w in resources.words(m)]
        self.n_words_ = int(resources.vocabulary.n_words_)
        self.counts_ = term_counts(words, self.n_words_)
        self.doc_places_ = np.concatenate([m.places for m in maps]).astype(np.int64)
        self._index()

    def _add_tour(self, tour: Traverse, resources: Resources) -> None:
        """A further tour's images become further documents; idf and the inverted file are recomputed.

        The same documents as fitting on all tours at once, so the same map.
        """
        counts = term_counts(resources.words(tour), self.n_words_)
        self.counts_ = sp.csr_matrix(sp.vstack([self.counts_, counts]))
        self.doc_places_ = np.concatenate([self.doc_places_, tour.places]).astype(np.int64)
        self._index()

    def _fit_shard(self, maps: list[Traverse], shard: list[Traverse], positions: np.ndarray,
                   resources: Resources) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The shard's documents (word counts of its images) and their places."""
        part = BagOfWords(merge=self.merge)
        part.n_words_ = int(resources.vocabulary.n_words_)
        part.counts_ = term_counts([w for m in shard for w in resources.words(m)], part.n_words_)
        part.doc_places_ = np.concatenate([m.places for m in shard]).astype(np.int64)
        return object_state(part, only=["n_words_", "counts_", "doc_places_"])

    def _merge_shards(self, parts: list[ShardPart], maps: list[Traverse], resources: Resources) -> None:
        """Documents in map order; idf and the inverted file recomputed from the merged counts."""
        docs = [restore_state(new_object(BagOfWords), p.meta, p.arrays) for p in parts]
        order = merge_order(parts, sum(len(m) for m in maps))
        self.n_words_ = int(docs[0].n_words_)
        self.counts_ = merge_documents([d.counts_ for d in docs], order)
        self.doc_places_ = np.concatenate([d.doc_places_ for d in docs])[order].astype(np.int64)
        self._index()

    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        # The documents are the state; idf and the inverted file follow from them.
        return object_state(self, only=["n_words_", "counts_", "doc_places_"])

    def _set_state(self, meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> None:
        restore_state(self, meta, arrays)
        # Checked before _index allocates along the words: a stored shape costs nothing in the file.
        n_words = self.n_words_
        res = getattr(self, "resources_", None)
        if res is not None and res.has_vocabulary and n_words != res.vocabulary.n_words_:
            raise TopolocError(f"bow: stored state has {n_words!r} words, its vocabulary {res.vocabulary.n_words_}")
        if (isinstance(n_words, bool) or not isinstance(n_words, int) or not sp.issparse(self.counts_)
                or self.counts_.shape != (len(self.doc_places_), n_words)):
            raise TopolocError(f"bow: stored word counts of shape {getattr(self.counts_, 'shape', None)} do not "
                               f"match {len(self.doc_places_)} documents of {n_words!r} words")
        self._index()

    def _index(self) -> None:
        """idf, the inverted file and the document order from ``counts_`` and ``doc_places_``."""
        place_ids = np.unique(self.doc_places_)
        rows = np.searchsorted(place_ids, self.doc_places_)
        counts = self.counts_
        if self.merge == "sum":
            pool = sp.csr_matrix(
                (np.ones(len(rows), np.float32), (rows, np.arange(len(rows)))),
                shape=(len(place_ids), len(rows)),
            )
            counts = sp.csr_matrix(pool @ counts)
            rows = np.arange(len(place_ids))
        self.idf_ = inverse_document_frequency(counts)
        self.inverted_ = inverted_file(counts, self.idf_)
        order = np.argsort(rows, kind="stable")
        self.doc_order_ = order
        self.doc_place_ = rows
        # Start offset of each place's run of documents after sorting by place.
        self.place_start_ = np.searchsorted(rows[order], np.arange(len(place_ids)))
        self.place_ids_ = place_ids

    def _encode(self, query: Traverse, resources: Resources) -> list[Any]:
        return resources.words(query)

    def _score(self, items: Sequence[Any]) -> np.ndarray:
        """Cosine similarity per place, shape (n_places, len(items))."""
        per_doc = cosine_scores(items, self.idf_, self.inverted_)
        S = np.maximum.reduceat(per_doc[self.doc_order_], self.place_start_, axis=0)
        return S.astype(np.float32)
