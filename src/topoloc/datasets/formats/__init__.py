"""Readers of public place-recognition dataset formats, written as traverses.

``convert(FORMAT, SRC, OUT)`` (``topoloc convert``) reads a dataset and writes the
project's traverse format (:mod:`topoloc.datasets.formats.base`): ``OUT/map/`` and
``OUT/query/`` for formats that hold both, one traverse at ``OUT`` for those that hold
one folder or sequence.  Each format is one module with ``read(src, options) -> Dataset``;
:data:`FORMATS` is the registry.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path

from topoloc.datasets.formats.base import ConvertOptions, ConvertResult, Dataset, TraverseData, write_dataset
from topoloc.errors import TopolocError


@dataclass(frozen=True)
class FormatInfo:
    """A registered format: its reader module, what SRC is, and a one-line description."""

    module: str
    source: str
    description: str


FORMATS: dict[str, FormatInfo] = {
    "vpr-bench": FormatInfo("vpr_bench", "folder", "VPR-Bench: ref/, query/, ground_truth_new.npy -> map, query"),
    "utm-names": FormatInfo("utm_names", "folder",
                            "images named @east@north@... (deep geo-localisation benchmarks) -> one traverse"),
    "dbstruct": FormatInfo("dbstruct", ".mat file", "Pittsburgh / Tokyo 24/7 dbStruct .mat -> map, query"),
    "msls": FormatInfo("msls", "city folder", "Mapillary SLS city: database/, query/ with lat/lon CSVs -> map, query"),
    "kitti": FormatInfo("kitti", "sequence folder", "KITTI odometry: image_2/ and poses/XX.txt -> one traverse"),
    "latlon-csv": FormatInfo("latlon_csv", "CSV file", "any CSV of image, latitude, longitude -> one traverse"),
}


def available_formats() -> list[str]:
    """Names ``convert`` accepts."""
    return list(FORMATS)


def read_dataset(fmt: str, src: str | Path, options: ConvertOptions | None = None) -> Dataset:
    """Read ``src`` in format ``fmt`` without writing anything.

    Raises
    ------
    TopolocError
        For an unknown format or bad input (one line naming the file and the problem).
    """
    info = FORMATS.get(fmt)
    if info is None:
        raise TopolocError(f"unknown dataset format {fmt!r}; choose one of {', '.join(FORMATS)}")
    module = importlib.import_module(f"{__name__}.{info.module}")
    dataset: Dataset = module.read(Path(src), options or ConvertOptions())
    return dataset


def convert(
    fmt: str, src: str | Path, out: str | Path, options: ConvertOptions | None = None
) -> ConvertResult:
    """Read ``src`` in format ``fmt`` and write it as traverses under ``out``.

    Parameters
    ----------
    fmt : str
        One of :func:`available_formats`.
    src : path
        The dataset: a folder, ``.mat`` or CSV file, as the format takes.
    out : path
        Output folder (created); ``out/map`` and ``out/query``, or one traverse at ``out``.
    options : ConvertOptions, optional
        Image root, KITTI poses, CSV column names, copy instead of link.

    Raises
    ------
    TopolocError
        For an unknown format or bad input (one line naming the file and the problem).
    """
    opts = options or ConvertOptions()
    dataset = read_dataset(fmt, src, opts)
    return write_dataset(dataset, Path(out), fmt=fmt, source=Path(src), copy=opts.copy)


__all__ = [
    "FORMATS", "ConvertOptions", "ConvertResult", "Dataset", "FormatInfo", "TraverseData", "available_formats",
    "convert", "read_dataset",
]
