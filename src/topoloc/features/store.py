"""The feature store: the local features of a traverse of image files, in blocks, written in parallel.

One store holds the features of one traverse (an ordered list of image files)
for one set of feature settings.  The images are cut into blocks of
:data:`BLOCK_IMAGES` consecutive images; one task extracts one block and
writes it as one file, so a traverse of 100,000 images is about 800 files
instead of 100,000, and the tasks can run on the threads of this process or on
the workers of a Dask cluster (:mod:`topoloc.cluster`).

Layout (under the cache root, ``$TOPOLOC_CACHE_DIR`` or ``~/.cache/topoloc``)::

    features/<settings key>/store/<store id>/
        store.json          what the store is for: schema, settings, block size, image names
        blocks/000000.tlb   block 0: images 0 .. B-1 (a topoloc container of kind "feature-block")
        blocks/000001.tlb   block 1: images B .. 2B-1
        ...

``<settings key>`` is :meth:`FeatureConfig.key` (the same folder as the
per-image cache of single frames); ``<store id>`` hashes the traverse's folder,
its file names and the block size.  A block file holds the block's features
ragged: all keypoints of its images concatenated, shape (N, 5) float32; all
descriptors, shape (N, d); ``offsets`` of shape (n + 1,) (image ``i`` owns rows
``offsets[i]:offsets[i+1]``); each image's ``(height, width)``, its
``extract_ms`` and, in the metadata, the SHA-1 of its bytes.

Guarantees
----------
* **Atomic blocks.**  A block is written to a temporary file and renamed into
  place: the file's existence is the block's completion marker, written only
  after all of its data.  Two workers writing different blocks touch different
  files; two writing the same block write the same bytes and the last rename
  wins.  A run killed or interrupted mid-way leaves complete blocks and no
  half block, and the next run recomputes only the missing ones.
* **Validated on load.**  The container's checksums (header and payload),
  its kind and schema version (:data:`STORE_SCHEMA`), the settings key, the
  shapes and the image SHA-1s are checked; an image edited in place changes
  its SHA-1 and so invalidates its block.  A block that fails any check is
  extracted again (one warning), never used.
* **Compact, bit-identical.**  OpenCV's SIFT descriptors are integers 0..255
  held as float32; a block whose float32 descriptors are all such integers is
  stored as uint8 (4x smaller) and converted back on load, bit for bit.
  RootSIFT (not integral) stays float32; ORB and AKAZE are uint8 already.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from topoloc.errors import TopolocError, input_error
from topoloc.features.cache import STORE_GLOB, cache_root, file_sha1, store_last_used, walk_no_links
from topoloc.features.local import FeatureConfig, FeatureExtractor, FeatureSet, extract_features
from topoloc.io import atomic_write_bytes, read_container, write_container

if TYPE_CHECKING:
    from topoloc.cluster import Executor

log = logging.getLogger(__name__)

STORE_SCHEMA = 1
"""Version of the store layout and of the ``feature-block`` container; part of every store id."""

BLOCK_KIND = "feature-block"

BLOCK_IMAGES = 128
"""Images per block.  SIFT describes 15.5 images of 640 x 480 per second and thread
(``docs/results/performance.md``, from ``benchmarks/bench_performance.py``), so a block is a task of
about 8 s: long enough that Dask's per-task overhead (milliseconds) does not count, short enough
that a lost worker costs little.  At the default cap of 1,000 SIFT features per image a block file
is at most 128 x 1,000 x (128 + 20) bytes = 19 MB (uint8 descriptors and float32 keypoints)."""

STORE_DIR = "store"


def store_id(root: Path, names: Sequence[str], block_size: int) -> str:
    """Identifier of the store of a traverse: hash of its folder, its file names in order and the block size."""
    h = hashlib.sha1()
    h.update(f"{STORE_SCHEMA}\0{Path(root).resolve()}\0{block_size}\n".encode("utf-8", "surrogateescape"))
    for name in names:
        h.update(name.encode("utf-8", "surrogateescape") + b"\n")
    return h.hexdigest()[:16]


@dataclass(frozen=True)
class BlockTask:
    """One block to fill: sent to a worker, so it holds only strings, numbers and the settings.

    Attributes
    ----------
    path : str
        The block file.
    block : int
        Block index.
    images : tuple of str
        The block's image files, in order.
    config : FeatureConfig
        Feature settings.
    threads : int
        Threads to extract the block's images with (1 on a cluster, whose
        workers already run one task per thread).
    keep : bool
        Return the block's features with the result (a local run reads them
        without opening the file again).
    force : bool
        Extract even if a valid block file exists.
    """

    path: str
    block: int
    images: tuple[str, ...]
    config: FeatureConfig
    threads: int = 1
    keep: bool = False
    force: bool = False


@dataclass
class BlockResult:
    """What filling a block returns: small, except ``features`` when the task was asked to keep them.

    Attributes
    ----------
    block : int
    sha1 : list of str
        SHA-1 of each image's bytes.
    n_features : ndarray of int64, shape (n_images,)
    extract_ms : ndarray of float64, shape (n_images,)
    extracted : int
        Images extracted by this task (0 when the block was already complete; images found
        in the per-image cache are not extracted again).
    features : list of FeatureSet or None
    """

    block: int
    sha1: list[str]
    n_features: np.ndarray
    extract_ms: np.ndarray
    extracted: int
    features: list[FeatureSet] | None = field(default=None, repr=False)


def _extract_one(path: str, config: FeatureConfig) -> FeatureSet:
    """Decode one image file and extract its features; ``extract_ms`` includes decoding (as the cache does)."""
    from topoloc.datasets.decode import read_image

    t0 = time.perf_counter()
    fs = extract_features(read_image(path), config)
    return FeatureSet(keypoints=fs.keypoints, descriptors=fs.descriptors, image_shape=fs.image_shape,
                      extract_ms=1e3 * (time.perf_counter() - t0))


def _compact(descriptors: np.ndarray) -> np.ndarray:
    """uint8 copy of float32 descriptors that are all integers 0..255 (bit-exact round trip), else themselves."""
    if descriptors.dtype != np.float32 or descriptors.size == 0:
        return descriptors
    if not (float(descriptors.min()) >= 0.0 and float(descriptors.max()) <= 255.0):
        return descriptors  # also false for NaN
    small = descriptors.astype(np.uint8)
    # Compared as bit patterns: -0.0 or a fraction would not survive the round trip.
    if np.array_equal(small.astype(np.float32).view(np.uint32), descriptors.view(np.uint32)):
        return small
    return descriptors


def write_block(task: BlockTask, sets: Sequence[FeatureSet], sha1: Sequence[str]) -> None:
    """Write one block file atomically (temporary file, fsync, rename): the rename marks it complete."""
    dim, dtype = task.config.descriptor_dim, task.config.descriptor_dtype
    counts = np.array([len(fs) for fs in sets], np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    kp = np.concatenate([fs.keypoints for fs in sets]) if sets else np.empty((0, 5), np.float32)
    desc = np.concatenate([fs.descriptors for fs in sets]) if sets else np.empty((0, dim), dtype)
    stored = _compact(np.ascontiguousarray(desc, dtype=dtype))
    write_container(
        task.path, BLOCK_KIND, STORE_SCHEMA,
        {"keypoints": np.ascontiguousarray(kp, np.float32), "descriptors": stored, "offsets": offsets,
         "image_shape": np.array([fs.image_shape for fs in sets], np.int64).reshape(len(sets), 2),
         "extract_ms": np.array([fs.extract_ms for fs in sets], np.float64)},
        meta={"config_key": task.config.key(), "descriptor_kind": task.config.descriptor_kind,
              "block": task.block, "images": [Path(p).name for p in task.images], "image_sha1": list(sha1)},
    )


def read_block(path: str | Path, config: FeatureConfig, sha1: Sequence[str] | None = None) -> list[FeatureSet]:
    """The FeatureSets of one block file, checked (see the module docstring).

    Parameters
    ----------
    path : path-like
        Block file.
    config : FeatureConfig
        Settings the block must have been written with.
    sha1 : sequence of str, optional
        SHA-1 of each image the block must describe, in order.

    Returns
    -------
    list of FeatureSet
        Read-only arrays; descriptors in ``config.descriptor_dtype``.

    Raises
    ------
    TopolocError
        One line naming the block file: missing, truncated, corrupt, another
        schema, other settings, other images, or inconsistent arrays.
    """
    meta, arrays = read_container(path, BLOCK_KIND, STORE_SCHEMA)
    try:
        if meta.get("config_key") != config.key():
            raise input_error("feature block was written for other settings", path)
        names = list(meta["image_sha1"])
        if sha1 is not None and names != list(sha1):
            raise input_error("feature block does not describe the current images (an image was changed?)", path)
        kp, desc, off = arrays["keypoints"], arrays["descriptors"], arrays["offsets"]
        shapes, ms = arrays["image_shape"], arrays["extract_ms"]
        n, total = len(names), len(kp)
        dim, dtype = config.descriptor_dim, config.descriptor_dtype
        if (kp.ndim != 2 or kp.shape[1] != 5 or kp.dtype != np.float32 or desc.ndim != 2 or desc.shape != (total, dim)
                or desc.dtype not in (dtype, np.uint8) or off.shape != (n + 1,) or shapes.shape != (n, 2)
                or ms.shape != (n,) or int(off[0]) != 0 or int(off[-1]) != total or np.any(np.diff(off) < 0)):
            raise input_error("feature block has inconsistent arrays", path)
    except (KeyError, TypeError, ValueError) as exc:
        raise input_error(f"feature block is malformed ({type(exc).__name__})", path) from None
    if desc.dtype != dtype:
        desc = desc.astype(dtype)  # uint8 -> float32 is exact: the integers written
        desc.flags.writeable = False
    out = []
    for i in range(n):
        a, b = int(off[i]), int(off[i + 1])
        out.append(FeatureSet(keypoints=kp[a:b], descriptors=desc[a:b],
                              image_shape=(int(shapes[i, 0]), int(shapes[i, 1])), extract_ms=float(ms[i])))
    return out


def _result(task: BlockTask, sha1: list[str], sets: list[FeatureSet], extracted: int) -> BlockResult:
    return BlockResult(block=task.block, sha1=sha1, n_features=np.array([len(f) for f in sets], np.int64),
                       extract_ms=np.array([f.extract_ms for f in sets], np.float64), extracted=extracted,
                       features=sets if task.keep else None)


def fill_block(task: BlockTask) -> BlockResult:
    """Make sure the block file of ``task`` is complete and current; extract its images if not.

    A pure function of the image bytes and the settings (the unit of work sent
    to a Dask worker, retried there on failure).  The images' SHA-1s are
    computed first; a valid block describing exactly those images is kept,
    anything else (missing, truncated, corrupt, stale) is extracted again and
    rewritten atomically.

    Raises
    ------
    TopolocError
        If an image cannot be read or decoded (naming it).
    """
    sha1 = [file_sha1(p) for p in task.images]
    path = Path(task.path)
    if not task.force and path.is_file():
        try:
            sets = read_block(path, task.config, sha1)
            return _result(task, sha1, sets, 0)
        except TopolocError as exc:
            log.warning("feature block is unusable, extracting it again (%s)", exc)
    # An image already in the per-image cache (described alone, e.g. by vocabulary training, or by an
    # earlier topoloc) is taken from there: its entry is checked against the image's SHA-1 and settings.
    single = FeatureExtractor(task.config, cache_dir=path.parents[5])  # <cache>/features/<key>/store/<id>/blocks
    fresh = [0]

    def one(k: int) -> FeatureSet:
        entry = single.feature_dir / f"{sha1[k]}.tlf"
        cached = single._load_entry(entry, sha1[k]) if entry.is_file() else None
        if cached is not None:
            return cached
        fresh[0] += 1
        return _extract_one(task.images[k], task.config)

    if task.threads > 1 and len(task.images) > 1:
        pool = ThreadPoolExecutor(max_workers=min(task.threads, len(task.images)))
        try:
            sets = list(pool.map(one, range(len(task.images))))
        finally:
            # Interrupted (Ctrl-C) or failed: drop the images not started; nothing of the block is written.
            pool.shutdown(wait=True, cancel_futures=True)
    else:
        sets = [one(k) for k in range(len(task.images))]
    try:
        write_block(task, sets, sha1)
    except OSError as exc:
        # A full or read-only cache disk must not stop a local run: the features are still returned.
        if not task.keep:
            raise TopolocError(f"cannot write feature block {path} ({exc.strerror or type(exc).__name__})") from None
        log.warning("cannot write feature block %s, features are kept in memory (%s)", path, exc)
    return _result(task, sha1, sets, fresh[0])


class FeatureStore:
    """The feature store of one traverse of image files for one feature setting.

    Parameters
    ----------
    config : FeatureConfig
        Feature settings.
    images : sequence of path-like
        The traverse's image files, in order.
    root : path-like
        The traverse's folder (part of the store id).
    cache_dir : path-like, optional
        Cache root (default ``$TOPOLOC_CACHE_DIR`` or ``~/.cache/topoloc``).
        On a cluster every worker writes here: it must be on a file system the
        workers see at the same path.
    block_size : int
        Images per block (default :data:`BLOCK_IMAGES`).
    """

    def __init__(self, config: FeatureConfig, images: Sequence[str | Path], *, root: str | Path,
                 cache_dir: str | Path | None = None, block_size: int = BLOCK_IMAGES) -> None:
        if block_size < 1:
            raise TopolocError(f"block_size must be >= 1, got {block_size}")
        self.config = config
        # Absolute: the tasks may run in worker processes with another working directory.
        self.images = [Path(p).absolute() for p in images]
        self.block_size = int(block_size)
        self.cache_dir = cache_root(cache_dir).absolute()
        names = [p.name for p in self.images]
        self.id = store_id(Path(root), names, self.block_size)
        self.path = self.cache_dir / "features" / config.key() / STORE_DIR / self.id

    def __repr__(self) -> str:
        return f"FeatureStore({self.path}, {len(self.images)} images, {self.n_blocks} blocks)"

    @property
    def n_blocks(self) -> int:
        return -(-len(self.images) // self.block_size)

    def block_range(self, b: int) -> range:
        """Image indices of block ``b``."""
        return range(b * self.block_size, min((b + 1) * self.block_size, len(self.images)))

    def block_path(self, b: int) -> Path:
        return self.path / "blocks" / f"{b:06d}.tlb"

    def task(self, b: int, *, threads: int = 1, keep: bool = False, force: bool = False) -> BlockTask:
        return BlockTask(path=str(self.block_path(b)), block=b,
                         images=tuple(str(self.images[k]) for k in self.block_range(b)),
                         config=self.config, threads=threads, keep=keep, force=force)

    def _write_manifest(self) -> None:
        manifest = {"schema": STORE_SCHEMA, "config_key": self.config.key(), "config": _config_dict(self.config),
                    "block_size": self.block_size, "n_images": len(self.images),
                    "root": str(self.images[0].parent.resolve()) if self.images else "",
                    "images": [p.name for p in self.images]}
        path = self.path / "store.json"
        text = json.dumps(manifest, sort_keys=True).encode()
        try:
            if path.is_file() and path.read_bytes() == text:
                return
            atomic_write_bytes(path, text)
        except OSError as exc:
            log.warning("cannot write feature store manifest %s (%s)", path, exc)

    def fill(self, executor: Executor, *, advance: Callable[[int], None] | None = None,
             keep: bool = False, threads: int = 1) -> list[BlockResult]:
        """Complete every block (extracting only what is missing or stale) through ``executor``.

        Parameters
        ----------
        executor : Executor
            Where the block tasks run (:func:`topoloc.cluster.connect`).
        advance : callable, optional
            Called with a number of images as blocks complete.
        keep : bool
            Return each block's features with its result (local runs).
        threads : int
            Threads per block task.

        Returns
        -------
        list of BlockResult, one per block, in order
        """
        if not self.images:
            return []
        self._write_manifest()
        sizes = [len(self.block_range(b)) for b in range(self.n_blocks)]
        done = [0]

        def step(_: int) -> None:
            # Blocks complete in any order; the counts add up to the number of images either way.
            if advance is not None:
                k = done[0]
                done[0] += 1
                advance(sizes[k] if k < len(sizes) else 0)

        tasks = [self.task(b, threads=threads, keep=keep) for b in range(self.n_blocks)]
        return executor.map(fill_block, tasks, advance=step)

    def read(self, results: Sequence[BlockResult]) -> list[FeatureSet]:
        """Features of every image, in order, from the blocks ``fill`` completed.

        A block whose file fails its checks now (changed since it was filled)
        is extracted again here, once; if it still fails, the error is raised.
        """
        out: list[FeatureSet] = []
        for res in results:
            if res.features is not None:
                out.extend(res.features)
                continue
            try:
                sets = read_block(self.block_path(res.block), self.config, res.sha1)
            except TopolocError as exc:
                log.warning("feature block is unusable, extracting it again (%s)", exc)
                sets = read_block(self.block_path(res.block), self.config,
                                  fill_block(self.task(res.block, force=True)).sha1)
            out.extend(sets)
        return out


def _sees(token: str) -> bool:
    """Whether this process (a worker) reads the token file the client wrote."""
    try:
        return Path(token).read_text() == Path(token).name
    except OSError:
        return False


def check_shared_cache(executor: Executor, cache_dir: str | Path) -> None:
    """Check that the executor's workers see ``cache_dir`` at the same path as this process.

    Workers write the feature store there and this process reads it back, so
    the folder must be on a file system shared by both.  A token file is
    written and one task per worker thread reads it back.

    Raises
    ------
    TopolocError
        When a worker cannot read the token (naming the folder and the fix).
    """
    import uuid

    root = Path(cache_dir).expanduser().resolve()
    token = root / f".shared-check-{uuid.uuid4().hex}"
    try:
        atomic_write_bytes(token, token.name.encode())
    except OSError as exc:
        raise input_error(f"cannot write to the cache folder ({exc.strerror or type(exc).__name__})", root) from None
    try:
        seen = executor.map(_sees, [str(token)] * max(1, executor.n_workers))
    finally:
        token.unlink(missing_ok=True)
    if not all(seen):
        raise input_error("the Dask workers do not see the cache folder at this path (workers write the feature "
                          "store there): put it on a file system shared with every worker, at the same path "
                          "(cache_dir or TOPOLOC_CACHE_DIR)", root)


def _config_dict(config: FeatureConfig) -> dict[str, Any]:
    from dataclasses import asdict

    return asdict(config)


def store_usage(cache_dir: str | Path | None = None) -> list[dict[str, Any]]:
    """Every feature store under the cache: settings, traverse folder, images, blocks, bytes, last use.

    Returns
    -------
    list of dict
        ``{"path", "settings", "root", "images", "blocks", "complete_blocks", "bytes", "last_used"}``;
        ``last_used`` is a Unix time (the latest access or modification of its files).
    """
    root = cache_root(cache_dir)
    out = []
    for store in sorted(root.glob(STORE_GLOB)):
        # Never through a link: what a planted link points at is not the cache's (issue #41).
        if (not store.is_dir() or store.name.startswith(".")  # hidden: being removed by clean_cache
                or any(p.is_symlink() for p in (store, store.parent, store.parent.parent))):
            continue
        files = [sub / n for sub, _, names in walk_no_links(store) for n in names
                 if not os.path.islink(sub / n)]
        stats = [f.stat() for f in files]
        try:
            manifest = json.loads((store / "store.json").read_text())
        except (OSError, ValueError):
            manifest = {}
        n_images = int(manifest.get("n_images", 0))
        block_size = int(manifest.get("block_size", BLOCK_IMAGES)) or BLOCK_IMAGES
        out.append({
            "path": str(store), "settings": store.parent.parent.name, "root": manifest.get("root", ""),
            "images": n_images, "blocks": -(-n_images // block_size),
            "complete_blocks": sum(1 for f in files if f.suffix == ".tlb" and f.parent.name == "blocks"),
            "bytes": sum(st.st_size for st in stats),
            "last_used": store_last_used(files),
        })
    return out


__all__ = ["BLOCK_IMAGES", "STORE_SCHEMA", "BlockResult", "BlockTask", "FeatureStore", "check_shared_cache",
           "fill_block", "read_block", "store_usage", "write_block"]
