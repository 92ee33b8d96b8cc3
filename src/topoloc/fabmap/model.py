"""The trained FAB-MAP appearance model: marginals, Chow-Liu tree, detector model.

What is learned from training images (never the evaluated map):

* the word marginals ``p(z_q = 1)`` (Laplace-smoothed: ``(n_q + 1) / (N + 2)``);
* the Chow-Liu tree (Eq. 4; :mod:`topoloc.fabmap.chowliu`) and its
  conditionals ``p(z_q = 1 | z_{p_q} = s)`` for ``s`` in {0, 1}, shrunk towards
  the marginal with ``prior_strength`` pseudo-images so that a rarely seen
  parent does not produce extreme conditionals:
  ``p(z_q=1 | z_p=1) = (n_{qp} + m p_q) / (n_p + m)``,
  ``p(z_q=1 | z_p=0) = (n_q - n_{qp} + m p_q) / (N - n_p + m)``.
  The root's "parent" is itself, with both conditionals equal to the marginal,
  which makes every formula of Eq. 4-5 reduce to the root term ``p(z_r | L)``
  without a special case;
* the prior of a scene element ``p(e_q = 1)``, used to initialise new places
  before the update of Eq. 11.  Like openFABMAP we take it equal to the word
  marginal ``p(z_q = 1)``: inverting the detector model instead
  (``(p(z) - p_fp) / (1 - p_fn - p_fp)``) is ill-posed for the many words rarer
  than the false-positive rate;
* the training occurrence matrix itself, whose images are the place models
  ``L_u`` sampled for the normaliser of Eq. 10.

The detector model (Eq. 2) is a pair of user-set numbers; the defaults are the
values of Cummins & Newman (IJRR 2008): ``p(z=1 | e=1) = 0.39`` (so
``p_fn = p(z=0 | e=1) = 0.61``) and ``p_fp = p(z=1 | e=0) = 0.005``.

A model is tied to the vocabulary that produced its word ids: its state
(:meth:`FabMapModel.to_state`) records the vocabulary's descriptor kind,
number of words and a SHA-1 fingerprint of its word centres, and
:meth:`FabMapModel.check_vocabulary` refuses a model used with another
vocabulary.  The model is kept in map files (:mod:`topoloc.maps`) and in the
model files of ``topoloc slam`` (:mod:`topoloc.evaluation.slam`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from topoloc.errors import TopolocError, input_error
from topoloc.fabmap.chowliu import ChowLiuTree, as_occurrence, chow_liu_tree
from topoloc.vocabulary.vocab import vocabulary_fingerprint

DEFAULT_P_FP = 0.005
"""Detector false-positive probability ``p(z=1 | e=0)`` (Eq. 2; IJRR 2008)."""
DEFAULT_P_FN = 0.61
"""Detector false-negative probability ``p(z=0 | e=1)`` (Eq. 2; IJRR 2008: ``p(z|e) = 0.39``)."""

_P_MIN = 1e-6  # probabilities are kept in [_P_MIN, 1 - _P_MIN] so that logs stay finite


def _clip(p: np.ndarray) -> np.ndarray:
    return np.clip(p, _P_MIN, 1.0 - _P_MIN)


@dataclass
class FabMapModel:
    """Trained FAB-MAP model (see the module docstring).

    Attributes
    ----------
    n_words : int
        Vocabulary size ``V``.
    parents : ndarray of int64, shape (V,)
        Chow-Liu parent ``p_q`` of each word; the root is its own parent.
    root : int
        Root word of the tree.
    p_z : ndarray of float64, shape (V,)
        Smoothed marginal ``p(z_q = 1)``.
    p_z_given_parent : ndarray of float64, shape (2, V)
        ``p(z_q = 1 | z_{p_q} = s)`` for ``s = 0`` (row 0) and ``s = 1`` (row 1).
    p_e : ndarray of float64, shape (V,)
        Prior ``p(e_q = 1)`` of a scene element at a new place (Eq. 11).
    p_fp, p_fn : float
        Detector model of Eq. 2.
    edge_mi : ndarray of float64, shape (V,)
        Mutual information of each Chow-Liu edge (0 at the root).
    joint_p : ndarray of float64, shape (4, V)
        Empirical ``p(z_q = z, z_{p_q} = s)`` at index ``2 z + s`` (training data);
        used to pick the most frequent observation state of each word (FAB-MAP 2.0 index).
    train_indptr, train_indices : ndarray of int64 / int32
        CSR structure of the binary training occurrence (images x words); the
        sampled place models of Eq. 10.
    vocabulary : dict
        :func:`vocabulary_fingerprint` of the vocabulary, or ``{}`` if unknown.
    """

    n_words: int
    parents: np.ndarray
    root: int
    p_z: np.ndarray
    p_z_given_parent: np.ndarray
    p_e: np.ndarray
    p_fp: float
    p_fn: float
    edge_mi: np.ndarray
    joint_p: np.ndarray
    train_indptr: np.ndarray
    train_indices: np.ndarray
    vocabulary: dict[str, Any]
    prior_strength: float = 1.0

    # -- training ---------------------------------------------------------------------
    @classmethod
    def train(
        cls,
        training: sp.spmatrix | np.ndarray | Sequence[np.ndarray],
        *,
        n_words: int | None = None,
        vocabulary: Any = None,
        p_fp: float = DEFAULT_P_FP,
        p_fn: float = DEFAULT_P_FN,
        prior_strength: float = 1.0,
        root: int | None = None,
    ) -> FabMapModel:
        """Learn marginals, the Chow-Liu tree and its conditionals from training images.

        Parameters
        ----------
        training : list of int arrays, or (n_images, V) binary matrix
            Visual-word ids of each training image (not the evaluated map).
        n_words : int, optional
            Vocabulary size ``V`` (default ``vocabulary.n_words_``).
        vocabulary : Vocabulary, optional
            The vocabulary that produced the word ids; its fingerprint is stored.
        p_fp, p_fn : float
            Detector model (Eq. 2).
        prior_strength : float
            Pseudo-images shrinking the tree conditionals towards the marginal.
        root : int, optional
            Root word of the Chow-Liu tree (default the most frequent word).

        Returns
        -------
        FabMapModel

        Raises
        ------
        TopolocError
            Without a vocabulary size, without training images, or with
            detector probabilities outside (0, 1) or ``p_fp + p_fn >= 1``.
        """
        if n_words is None:
            if vocabulary is None:
                raise TopolocError("FabMapModel.train needs n_words or a vocabulary")
            n_words = int(vocabulary.n_words_)
        _check_detector(p_fp, p_fn)
        x = as_occurrence(training, n_words=n_words)
        n = x.shape[0]
        if n < 2:
            raise TopolocError(f"FAB-MAP training needs at least 2 training images, got {n}")
        tree = chow_liu_tree(x, root=root)
        return cls.from_tree(
            tree,
            x,
            vocabulary=vocabulary_fingerprint(vocabulary) if vocabulary is not None else {},
            p_fp=p_fp,
            p_fn=p_fn,
            prior_strength=prior_strength,
        )

    @classmethod
    def from_tree(
        cls,
        tree: ChowLiuTree,
        x: sp.csr_matrix,
        *,
        vocabulary: dict[str, Any],
        p_fp: float = DEFAULT_P_FP,
        p_fn: float = DEFAULT_P_FN,
        prior_strength: float = 1.0,
    ) -> FabMapModel:
        """Build the model from a tree and its training occurrence (see :meth:`train`)."""
        n = float(tree.n_images)
        v = tree.n_words
        nq = tree.counts.astype(np.float64)
        p_z = _clip((nq + 1.0) / (n + 2.0))
        par = tree.parents
        npar = nq[par]
        n11 = tree.joint_counts.astype(np.float64)
        m = float(prior_strength)
        c1 = (n11 + m * p_z) / (npar + m)
        c0 = (nq - n11 + m * p_z) / (n - npar + m)
        is_root = par == np.arange(v)
        c1[is_root] = p_z[is_root]
        c0[is_root] = p_z[is_root]
        # empirical joint of (z_q, z_p) at index 2 z + s; at the root z_p = z_q
        j11 = n11 / n
        j10 = (nq - n11) / n
        j01 = (npar - n11) / n
        j00 = 1.0 - j11 - j10 - j01
        joint_p = np.stack([j00, j01, j10, j11])
        joint_p[:, is_root] = np.stack([1.0 - nq / n, 0.0 * nq, 0.0 * nq, nq / n])[:, is_root]
        x = sp.csr_matrix(x)
        return cls(
            n_words=v,
            parents=par.astype(np.int64),
            root=int(tree.root),
            p_z=p_z,
            p_z_given_parent=_clip(np.stack([c0, c1])),
            p_e=p_z.copy(),
            p_fp=float(p_fp),
            p_fn=float(p_fn),
            edge_mi=tree.edge_mi.astype(np.float64),
            joint_p=np.clip(joint_p, 0.0, 1.0),
            train_indptr=x.indptr.astype(np.int64),
            train_indices=x.indices.astype(np.int32),
            vocabulary=dict(vocabulary),
            prior_strength=m,
        )

    # -- derived quantities -----------------------------------------------------------
    @property
    def n_train(self) -> int:
        """Number of training images."""
        return int(self.train_indptr.size - 1)

    def training_occurrence(self) -> sp.csr_matrix:
        """Binary training occurrence, shape (n_train, V)."""
        data = np.ones(self.train_indices.size, dtype=np.uint8)
        return sp.csr_matrix(
            (data, self.train_indices, self.train_indptr), shape=(self.n_train, self.n_words)
        )

    def training_words(self) -> list[np.ndarray]:
        """Word ids of each training image (sorted, unique)."""
        ip = self.train_indptr
        return [self.train_indices[ip[i]:ip[i + 1]] for i in range(self.n_train)]

    def with_detector(self, *, p_fp: float, p_fn: float) -> FabMapModel:
        """A copy with another detector model (Eq. 2); training statistics are shared."""
        _check_detector(p_fp, p_fn)
        out = FabMapModel(**{**self.__dict__})
        out.p_fp = float(p_fp)
        out.p_fn = float(p_fn)
        return out

    # -- vocabulary binding -----------------------------------------------------------
    def check_vocabulary(self, vocabulary: Any, *, path: str | Path | None = None) -> None:
        """Raise a one-line :class:`TopolocError` if ``vocabulary`` is not the model's.

        Parameters
        ----------
        vocabulary : Vocabulary
            The vocabulary the caller will quantise with.
        path : path-like, optional
            The model file, named in the message.
        """
        where = f" ({path})" if path is not None else ""
        n = int(vocabulary.n_words_)
        if n != self.n_words:
            raise TopolocError(
                f"FAB-MAP model{where} was trained for {self.n_words} visual words but the "
                f"vocabulary has {n}"
            )
        if not self.vocabulary:
            return
        fp = vocabulary_fingerprint(vocabulary)
        if fp["descriptor_kind"] != self.vocabulary.get("descriptor_kind"):
            raise TopolocError(
                f"FAB-MAP model{where} was trained with {self.vocabulary.get('descriptor_kind')!r} "
                f"words but the vocabulary is for {fp['descriptor_kind']!r}"
            )
        if fp["sha1"] != self.vocabulary.get("sha1"):
            raise TopolocError(
                f"FAB-MAP model{where} belongs to another vocabulary (fingerprint "
                f"{str(self.vocabulary.get('sha1'))[:12]} != {fp['sha1'][:12]}): retrain it"
            )

    # -- persistence ------------------------------------------------------------------
    def to_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The model as JSON metadata and named arrays.

        What map files and :func:`topoloc.evaluation.slam.save_fabmap_model` store.
        """
        meta: dict[str, Any] = {
            "n_words": self.n_words,
            "root": self.root,
            "p_fp": self.p_fp,
            "p_fn": self.p_fn,
            "prior_strength": self.prior_strength,
            "vocabulary": self.vocabulary,
        }
        arrays: dict[str, np.ndarray] = {
            "parents": self.parents.astype(np.int64),
            "p_z": self.p_z.astype(np.float64),
            "p_z_given_parent": self.p_z_given_parent.astype(np.float64),
            "p_e": self.p_e.astype(np.float64),
            "edge_mi": self.edge_mi.astype(np.float64),
            "joint_p": self.joint_p.astype(np.float64),
            "train_indptr": self.train_indptr.astype(np.int64),
            "train_indices": self.train_indices.astype(np.int32),
        }
        return meta, arrays

    @classmethod
    def from_state(
        cls, meta: dict[str, Any], arrays: dict[str, np.ndarray], *, path: str | Path | None = None
    ) -> FabMapModel:
        """The model from :meth:`to_state`'s output, validated (``path`` names the source in errors)."""
        try:
            v = int(meta["n_words"])
            model = cls(
                n_words=v,
                parents=np.array(arrays["parents"], dtype=np.int64),
                root=int(meta["root"]),
                p_z=np.array(arrays["p_z"], dtype=np.float64),
                p_z_given_parent=np.array(arrays["p_z_given_parent"], dtype=np.float64),
                p_e=np.array(arrays["p_e"], dtype=np.float64),
                p_fp=float(meta["p_fp"]),
                p_fn=float(meta["p_fn"]),
                edge_mi=np.array(arrays["edge_mi"], dtype=np.float64),
                joint_p=np.array(arrays["joint_p"], dtype=np.float64),
                train_indptr=np.array(arrays["train_indptr"], dtype=np.int64),
                train_indices=np.array(arrays["train_indices"], dtype=np.int32),
                vocabulary=dict(meta.get("vocabulary") or {}),
                prior_strength=float(meta.get("prior_strength", 1.0)),
            )
        except (KeyError, TypeError, ValueError):
            raise input_error("FAB-MAP model lacks required fields", path) from None
        model._validate(path)
        return model

    def _validate(self, path: str | Path | None = None) -> None:
        v = self.n_words
        ok = (
            self.parents.shape == (v,)
            and self.p_z.shape == (v,)
            and self.p_e.shape == (v,)
            and self.p_z_given_parent.shape == (2, v)
            and self.joint_p.shape == (4, v)
            and self.edge_mi.shape == (v,)
            and 0 <= self.root < v
            and bool(np.all((self.parents >= 0) & (self.parents < v)))
            and self.train_indptr.ndim == 1
            and self.train_indptr.size >= 1
            and int(self.train_indptr[-1]) == self.train_indices.size
        )
        if ok and self.train_indices.size:
            ok = int(self.train_indices.min()) >= 0 and int(self.train_indices.max()) < v
        if not ok:
            raise input_error("FAB-MAP model file is inconsistent (array shapes or ranges)", path)
        _check_detector(self.p_fp, self.p_fn, path)


def _check_detector(p_fp: float, p_fn: float, path: str | Path | None = None) -> None:
    if not (0.0 < p_fp < 1.0 and 0.0 < p_fn < 1.0 and p_fp + p_fn < 1.0):
        msg = (
            f"detector model needs 0 < p_fp, p_fn < 1 and p_fp + p_fn < 1 "
            f"(got p_fp={p_fp}, p_fn={p_fn})"
        )
        raise input_error(msg, path)
