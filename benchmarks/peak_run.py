"""Run one ``topoloc`` command and write its peak resident memory (VmHWM) to a JSON file when it exits.

    python -m benchmarks.peak_run OUT.json -- vocab train FOLDER --out V.tlv ...

The peak is the process's own (``/proc/self/status`` VmHWM, reset by ``exec``), not
the parent's: the benchmark's client column is what the command itself held.
Linux only (elsewhere ``peak_mib`` is null).
"""

from __future__ import annotations

import atexit
import json
import sys
import time
from pathlib import Path


def proc_mib(path: str, field: str) -> float | None:
    """A ``kB`` field of a /proc file (``/proc/self/status``, ``/proc/meminfo``) in MiB, or None where there is none."""
    try:
        for line in Path(path).read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def vm_hwm_mib() -> float | None:
    """This process's peak resident memory in MiB (``VmHWM``), or None where /proc has none."""
    return proc_mib("/proc/self/status", "VmHWM")


def vm_rss_mib() -> float | None:
    """This process's resident memory now in MiB (``VmRSS``), or None where /proc has none."""
    return proc_mib("/proc/self/status", "VmRSS")


def reset_vm_hwm() -> None:
    """Reset this process's VmHWM to its current RSS (Linux ``clear_refs`` 5; nothing elsewhere)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def main() -> None:
    out, sep, *args = sys.argv[1:]
    if sep != "--":
        raise SystemExit("usage: python -m benchmarks.peak_run OUT.json -- TOPOLOC ARGS...")
    t0 = time.perf_counter()
    atexit.register(lambda: Path(out).write_text(json.dumps(
        {"peak_mib": vm_hwm_mib(), "seconds": time.perf_counter() - t0, "args": args})))
    from topoloc.cli.main import app

    sys.argv = ["topoloc", *args]
    app(prog_name="topoloc")


if __name__ == "__main__":
    main()
