"""An environment of its own for ROS 2: where the ROS 2 node's tests and benchmark run it.

``python -m topoloc.ros.environment [FOLDER]`` (``.ci/run`` runs it) builds, or
finds up to date, a virtual environment with topoloc installed from this source
tree with its ``ros2`` and ``ros`` extras (``pip install -e 'SOURCE[ros2,ros]'``, what a
user installs), and prints its Python.  The tests and
``benchmarks/bench_ros_latency.py`` start the node and the probe with that
Python; the test suite's own environment never gets rclpy.

Why apart: the ROS 2 wheels' ``ros-wheels-bootstrapper`` installs a ``.pth`` hook
that starts every Python process of its environment a second time, with
``LD_LIBRARY_PATH`` pointing at ROS's bundled libraries and a guard variable
that every child process inherits.  In the suite's environment that would be
every pytest run, every ``topoloc`` subprocess and Dask worker the tests start
(twice the start-up), all of them with ROS's libraries (FastDDS, spdlog, yaml
and their dependencies) first on the library path of OpenCV, ONNX Runtime and
faiss; and a child started from such a process in another environment would
inherit the guard and not find its own.  In an environment of its own only the
ROS 2 processes pay for it, and their environment is the user's.

A file ``topoloc-ros2.json`` in the folder records what it was built from (the
source tree, the extra's requirements, the Python); a build is redone when that
changes, under a lock, so that two test runs never build it at once.
"""

from __future__ import annotations

import fcntl
import json
import os
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path

from topoloc.errors import TopolocError

STAMP = "topoloc-ros2.json"

#: The extras installed: the ROS 2 node's, and the bags' (the probe replays a ROS 2 bag).
EXTRAS = "ros2,ros"

#: How long a build may take (topoloc's dependencies and 260 MB of ROS 2 wheels: 1 to 2 minutes with pip's cache).
BUILD_TIMEOUT_S = 900.0


def source_tree() -> Path | None:
    """This topoloc's source tree (the folder of its ``pyproject.toml``), None for an installed copy."""
    root = Path(__file__).resolve().parents[3]
    return root if (root / "pyproject.toml").is_file() and (root / "src" / "topoloc").is_dir() else None


def default_folder() -> Path:
    """``.venv-ros2`` beside the source tree (``$TOPOLOC_ROS2_ENV`` wins)."""
    given = os.environ.get("TOPOLOC_ROS2_ENV")
    if given:
        return Path(given)
    src = source_tree()
    if src is None:
        raise TopolocError("topoloc is not installed from a source tree: give the folder, or set TOPOLOC_ROS2_ENV")
    return src / ".venv-ros2"


def ros2_requirements() -> list[str]:
    """The ``ros2`` extra's requirements, as this installation of topoloc declares them."""
    out = []
    for req in metadata.requires("topoloc") or []:
        name, _, marker = req.partition(";")
        if marker.replace(" ", "").replace("'", '"') == 'extra=="ros2"':
            out.append(name.strip())
    return sorted(out)


def clean_env(env: dict[str, str] | None = None) -> dict[str, str]:
    """An environment for a process of the ROS 2 environment: without another's bootstrap guard and libraries.

    The hook of the ROS 2 wheels sets ``LD_LIBRARY_PATH`` only where its guard
    variable is not set already: a process started from one of its processes
    (or from a shell that sourced one) would otherwise run without its libraries.
    """
    out = dict(os.environ if env is None else env)
    out.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    out.pop("LD_LIBRARY_PATH", None)
    return out


#: Fast DDS's own size of a shared-memory segment: best-effort messages larger than it do not arrive.
FASTDDS_DEFAULT_SEGMENT = 512 * 1024

#: The segment the tests and the benchmark use: room for a few raw 1080p frames.
LOOPBACK_SEGMENT = 16 * 1024 * 1024

_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<!-- topoloc: Fast DDS on this machine only. UDP on 127.0.0.1 alone (discovery included: no packet leaves the
     machine) and shared memory with segments of {segment} bytes (best-effort messages larger than a segment
     never arrive). Used through FASTDDS_DEFAULT_PROFILES_FILE. -->
<dds xmlns="http://www.eprosima.com">
  <profiles>
    <transport_descriptors>
      <transport_descriptor>
        <transport_id>loopback_udp</transport_id>
        <type>UDPv4</type>
        <interfaceWhiteList><address>127.0.0.1</address></interfaceWhiteList>
      </transport_descriptor>
      <transport_descriptor>
        <transport_id>shared_memory</transport_id>
        <type>SHM</type>
        <segment_size>{segment}</segment_size>
        <maxMessageSize>{segment}</maxMessageSize>
      </transport_descriptor>
    </transport_descriptors>
    <participant profile_name="topoloc_loopback" is_default_profile="true">
      <rtps>
        <userTransports>
          <transport_id>shared_memory</transport_id>
          <transport_id>loopback_udp</transport_id>
        </userTransports>
        <useBuiltinTransports>false</useBuiltinTransports>
      </rtps>
    </participant>
  </profiles>
</dds>
"""


def loopback_profile(path: Path, segment: int = LOOPBACK_SEGMENT) -> Path:
    """Write a Fast DDS profile that keeps every participant on this machine (see :data:`_PROFILE`)."""
    path.write_text(_PROFILE.format(segment=int(segment)))
    return path


class PrivateDomain:
    """A ROS domain id that no other holder on this machine has, held (a lock per id) until :meth:`close`.

    The processes given :meth:`env` talk to each other only, and never off this
    machine: another test run or benchmark takes another id, and Fast DDS is
    given a profile (:func:`loopback_profile`) with UDP on 127.0.0.1 alone and
    shared memory, whose segments (``segment`` bytes) hold the messages sent.
    """

    def __init__(self, first: int = 11, last: int = 100) -> None:
        import tempfile

        for domain in range(first, last + 1):
            fh = open(Path(tempfile.gettempdir()) / f"topoloc-ros2-domain-{domain}.lock", "w")
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                fh.close()
                continue
            self.domain, self._lock = domain, fh
            self._dir = tempfile.TemporaryDirectory(prefix=f"topoloc-ros2-domain-{domain}-")
            return
        raise TopolocError(f"every ROS domain id from {first} to {last} is held by another run on this machine")

    def env(self, base: dict[str, str] | None = None, *, segment: int = LOOPBACK_SEGMENT, **extra: str,
            ) -> dict[str, str]:
        """An environment for a process of the ROS 2 environment on this domain (:func:`clean_env` of ``base``)."""
        profile = loopback_profile(Path(self._dir.name) / f"fastdds_{segment}.xml", segment)
        out = clean_env(base)
        for name in ("FASTDDS_BUILTIN_TRANSPORTS", "FASTRTPS_DEFAULT_PROFILES_FILE", "ROS_LOCALHOST_ONLY",
                     "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_STATIC_PEERS", "ROS_DISCOVERY_SERVER"):
            out.pop(name, None)  # nothing of the caller's may widen (or redirect) discovery
        return {**out, "ROS_DOMAIN_ID": str(self.domain), "FASTDDS_DEFAULT_PROFILES_FILE": str(profile), **extra}

    def close(self) -> None:
        self._dir.cleanup()
        self._lock.close()


def python_of(folder: Path) -> Path:
    return folder / "bin" / "python"


def _record(source: Path) -> dict[str, object]:
    return {"source": str(source), "extras": EXTRAS, "requirements": ros2_requirements(),
            "python": sys.version.split()[0]}


def _works(python: Path) -> str | None:
    """None where rclpy and topoloc import in a process of the environment; else the last line of its error."""
    code = "import rclpy, sensor_msgs.msg, std_srvs.srv, diagnostic_msgs.msg, topoloc.ros.node2"
    try:
        r = subprocess.run([str(python), "-c", code], env=clean_env(), capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return str(exc)
    return None if r.returncode == 0 else ((r.stderr.strip().splitlines() or ["failed"])[-1])


def ensure(folder: Path | None = None, *, source: Path | None = None, build: bool = True) -> Path:
    """The Python of an up-to-date ROS 2 environment in ``folder``, built first where needed.

    Raises
    ------
    TopolocError
        One line naming what is missing: the build failed (no registry, no wheels for this Python),
        or ``build`` is False and there is none.
    """
    folder = Path(folder) if folder is not None else default_folder()
    source = source or source_tree()
    if source is None:
        raise TopolocError("topoloc is not installed from a source tree: the ROS 2 environment installs it from one")
    python = python_of(folder)
    want = _record(source)
    folder.parent.mkdir(parents=True, exist_ok=True)
    with open(folder.parent / f"{folder.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        stamp = folder / STAMP
        if python.exists() and stamp.is_file():
            try:
                same = json.loads(stamp.read_text()) == want
            except ValueError:
                same = False
            if same and _works(python) is None:
                return python
        if not build:
            raise TopolocError(f"no ROS 2 environment in {folder}: python -m topoloc.ros.environment {folder}")
        _build(folder, source)
        problem = _works(python)
        if problem is not None:
            raise TopolocError(f"the ROS 2 environment in {folder} cannot run the node: {problem}")
        stamp.write_text(json.dumps(want) + "\n")
    return python


def _build(folder: Path, source: Path) -> None:
    t0 = time.monotonic()
    print(f"topoloc: building the ROS 2 environment in {folder} (pip install -e '{source}[{EXTRAS}]')",
          file=sys.stderr, flush=True)
    steps = [[sys.executable, "-m", "venv", "--clear", str(folder)],
             [str(python_of(folder)), "-m", "pip", "install", "-q", "-e", f"{source}[{EXTRAS}]"]]
    for cmd in steps:
        try:
            r = subprocess.run(cmd, env=clean_env(), capture_output=True, text=True, timeout=BUILD_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            raise TopolocError(f"building the ROS 2 environment took more than {BUILD_TIMEOUT_S:.0f} s: "
                               f"{' '.join(cmd)}") from None
        if r.returncode != 0:
            last = [x for x in r.stderr.strip().splitlines() if not x.startswith("WARNING: Location")]
            raise TopolocError(f"cannot build the ROS 2 environment ({' '.join(cmd[-3:])}): "
                               f"{(last or ['failed'])[-1]}")
    print(f"topoloc: ROS 2 environment built in {time.monotonic() - t0:.0f} s", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> None:
    """Build (or find up to date) the environment in the folder given (default :func:`default_folder`)."""
    args = sys.argv[1:] if argv is None else argv
    try:
        print(ensure(Path(args[0]) if args else None))
    except TopolocError as exc:
        print(f"topoloc: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
