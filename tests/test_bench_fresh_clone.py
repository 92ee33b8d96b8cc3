"""benchmarks/bench_fresh_clone.py: a new user's conditions, the README's commands, the figures and targets."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def bench(benchmark_module: Callable[[str], ModuleType]) -> ModuleType:
    return benchmark_module("bench_fresh_clone")


def test_the_commands_are_the_readmes(bench: ModuleType) -> None:
    commands = bench.readme_commands((ROOT / "README.md").read_text())
    assert commands["demo"] == ("python3 -m venv .venv && .venv/bin/pip install -e .", ".venv/bin/topoloc demo")
    assert commands["tests"][1] == ".venv/bin/python -m pytest -q"
    assert commands["tests"][0].startswith("python3 -m venv .venv && ")
    with pytest.raises(SystemExit, match="no command for tests"):
        bench.readme_commands("## Quick start\n\n```bash\npython3 -m venv .venv && .venv/bin/topoloc demo\n```\n")


def test_the_new_users_shell_takes_packages_from_the_registry_only(bench: ModuleType, tmp_path: Path) -> None:
    """This machine's local wheel folders and indexes (pip.conf, PIP_* settings) are out of pip's sight."""
    home = tmp_path / "home"
    (home / ".config" / "pip").mkdir(parents=True)
    (home / ".config" / "pip" / "pip.conf").write_text("[global]\nfind-links = /opt/wheels\n"
                                                       "extra-index-url = file:///opt/pypi/simple\n")
    base = {**os.environ, "PIP_FIND_LINKS": "/opt/wheels", "PIP_INDEX_URL": "file:///opt/pypi/simple",
            "PIP_CONSTRAINT": "/etc/c.txt", "PIP_CERT": "/etc/ssl/ca.crt", "TOPOLOC_FEATURES": "sift",
            "NUMBA_CACHE_DIR": "/tmp/n", "VIRTUAL_ENV": str(ROOT / ".venv"), "XDG_CONFIG_HOME": str(home / ".config"),
            "PATH": f"{ROOT / '.venv' / 'bin'}{os.pathsep}{os.environ.get('PATH', '')}"}
    env = bench.new_user_env(base, home, tmp_path / "cache", tmp_path / "report.json")
    assert env["PIP_CONFIG_FILE"] == os.devnull and env["PIP_NO_CACHE_DIR"] == "1"
    assert env["PIP_CERT"] == "/etc/ssl/ca.crt"  # the network's certificate is no package source
    for gone in ("PIP_FIND_LINKS", "PIP_INDEX_URL", "PIP_CONSTRAINT", "TOPOLOC_FEATURES", "NUMBA_CACHE_DIR",
                 "VIRTUAL_ENV", "XDG_CONFIG_HOME"):
        assert gone not in env
    assert env["TOPOLOC_CACHE_DIR"] == str(tmp_path / "cache") and env["HOME"] == str(home)
    assert str(ROOT / ".venv" / "bin") not in env["PATH"].split(os.pathsep)
    # pip itself, asked in that shell, sees no package source but its default index.
    seen = subprocess.run([sys.executable, "-m", "pip", "config", "list"], env=env, capture_output=True, text=True,
                          check=True).stdout
    assert not any(word in seen for word in ("find-links", "index-url", "constraint", "/opt/")), seen


def _item(name: str, url: str, direct: bool = False) -> dict[str, Any]:
    return {"metadata": {"name": name}, "download_info": {"url": url}, "is_direct": direct}


def test_a_package_from_anywhere_but_an_https_index_refuses_the_run(bench: ModuleType, tmp_path: Path) -> None:
    clone = tmp_path / "topoloc"
    registry = [_item("topoloc", clone.as_uri(), direct=True),
                _item("numpy", "https://files.pythonhosted.org/packages/aa/numpy-2.0-cp311.whl"),
                _item("scipy", "https://files.pythonhosted.org/packages/bb/scipy-1.14-cp311.whl")]
    assert bench.package_sources({"install": registry}, clone) == {"downloaded": 2,
                                                                    "hosts": {"files.pythonhosted.org": 2}}
    for bad in (_item("torch", "file:///opt/wheels/torch-2.13.0+cpu-cp311.whl"),
                _item("idna", "file:///opt/pypi-more/simple/idna/idna-3.7-py3-none-any.whl"),
                _item("x", "https://example.org/x-1.0.whl", direct=True)):
        with pytest.raises(SystemExit, match=f"not a registry-only install: {bad['metadata']['name']} from"):
            bench.package_sources({"install": [*registry, bad]}, clone)


def _demo(install: float = 40.0, first: float = 45.0, later: tuple[float, ...] = (20.0, 22.0), env_mb: float = 950.0,
          load: float = 0.5) -> dict[str, Any]:
    def step(name: str, s: float) -> dict[str, Any]:
        return {"step": name, "command": "c", "seconds": s, "exit": 0, "load_before": 0.1, "load_after": load,
                "tail": []}
    env = {"mb": env_mb, "distributions": 40, "torch": False, "opencv": ["opencv-contrib-python-headless"],
           "largest": [{"name": "llvmlite", "version": "0.44", "mb": 172.1},
                       {"name": "scipy", "version": "1.14", "mb": 113.0}],
           "network_files": {"xfeat.onnx": 2_654_622, "xfeat.npz": 2_664_748}}
    return {"commit": "0123456789abc", "tree_had_uncommitted_changes": False, "machine": "x86_64, 2 cores, Python 3.11",
            "time": "2026-11-29T10:00:00+00:00", "date": "2026-11-29", "received_mb": 250.0, "numba_cache_files": 28,
            "sources": {"downloaded": 39, "hosts": {"files.pythonhosted.org": 39}}, "environment": env,
            "steps": [step("install", install), step("first run", first), *(step("later run", s) for s in later),
                      step("later run, numba's cache removed", 41.0)]}


def test_the_targets_and_numbas_cache_from_the_steps(bench: ModuleType) -> None:
    f = bench.demo_figures(_demo())
    assert (f["install_demo_s"], f["later_s"], f["env_met"], f["install_demo_met"]) == (85.0, 21.0, True, True)
    page = bench.page({"parts": {"demo": _demo()}})
    assert "the environment <= 1.1 GB: 950 MB, met." in page
    assert "the install and the first demo <= 90 s on 2 cores: 40 + 45 = 85 s, met." in page
    assert "Numba's disk cache saves a later process 20 s (41 s without it, 21 s with it)" in page
    assert "| llvmlite | 0.44 | 172.1 |" in page and "`xfeat.onnx` 2.7 MB, `xfeat.npz` 2.7 MB" in page
    assert "39 downloaded, from files.pythonhosted.org (39), none from a local file or folder" in page
    assert "beside other jobs" not in page
    slow = bench.page({"parts": {"demo": _demo(first=60.0, env_mb=1200.0, load=3.0)}})
    assert "the environment <= 1.1 GB: 1200 MB, **NOT met**." in slow
    assert "40 + 60 = 100 s, **NOT met** (measured beside other jobs" in slow


def test_a_run_of_one_part_keeps_the_others_figures(bench: ModuleType) -> None:
    tests = {**_demo(), "date": "2026-12-01", "ros": False,
             "steps": [{"step": "install", "command": "c", "seconds": 70.0, "exit": 0, "load_before": 0.1,
                        "load_after": 0.2, "tail": []},
                       {"step": "tests", "command": "c", "seconds": 600.0, "exit": 0, "load_before": 0.2,
                        "load_after": 1.9, "tail": ["2200 passed, 19 skipped, 3 warnings in 597.00s (0:09:57)"]}]}
    both = bench.merged(bench.merged(None, "demo", _demo()), "tests", tests)
    assert list(both["parts"]) == ["demo", "tests"]
    said = bench.readme_sentences(both)
    assert "measured on 2026-11-29" in said["demo"] and "measured on 2026-12-01" in said["tests"]
    assert "its install took 70 s and its tests 10.0 min (2200 passed, 19 skipped)" in said["tests"]
    assert "without the shared data and ROS" in said["tests"]
    again = bench.merged(both, "demo", {**_demo(), "date": "2026-12-02"})
    assert again["parts"]["tests"] is tests and again["parts"]["demo"]["date"] == "2026-12-02"
    assert bench.readme_sentences(bench.merged(None, "demo", _demo()))["tests"] == bench.NOT_MEASURED
