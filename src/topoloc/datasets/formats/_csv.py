"""Small CSV helpers shared by the readers: rows as dicts, column look-up, times."""

from __future__ import annotations

import csv
from datetime import datetime
from pathlib import Path

import numpy as np

from topoloc.errors import input_error


def read_rows(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    """Header and rows of a CSV file (``utf-8``, a leading BOM ignored).

    Raises
    ------
    TopolocError
        For an unreadable file, no header or no rows.
    """
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            rows = list(reader)
            header = [h.strip() for h in (reader.fieldnames or [])]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise input_error(f"cannot read CSV ({exc.__class__.__name__})", path) from None
    if not header:
        raise input_error("CSV has no header row", path)
    if not rows:
        raise input_error("CSV has no data rows", path)
    clean = [{(k or "").strip(): (v or "").strip() if isinstance(v, str) else "" for k, v in r.items()}
             for r in rows]
    return header, clean


def find_column(header: list[str], candidates: tuple[str, ...], override: str | None) -> str | None:
    """The column named ``override``, else the first of ``candidates`` present (case-insensitive)."""
    lower = {h.lower(): h for h in header}
    if override:
        return lower.get(override.lower())
    for c in candidates:
        if c in lower:
            return lower[c]
    return None


def parse_float(text: str, path: Path, line: int, what: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise input_error(f"{path}:{line}: {what} {text!r} is not a number", None) from None
    if not np.isfinite(v):
        raise input_error(f"{path}:{line}: {what} {text!r} is not finite", None)
    return v


def parse_time(text: str, path: Path, line: int) -> str | None:
    """ISO 8601 text, or Unix time in seconds or milliseconds (> 1e11), -> ISO 8601 seconds; '' -> None."""
    t = text.strip()
    if not t:
        return None
    try:
        v = float(t)
    except ValueError:
        try:
            return str(np.datetime64(datetime.fromisoformat(t).replace(tzinfo=None), "s"))
        except ValueError:
            raise input_error(f"{path}:{line}: time {t!r} is neither ISO 8601 nor Unix time", None) from None
    if not np.isfinite(v):
        raise input_error(f"{path}:{line}: time {t!r} is not finite", None)
    ms = v if abs(v) > 1e11 else v * 1000.0
    return str(np.datetime64(round(ms), "ms").astype("datetime64[s]"))
