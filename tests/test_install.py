"""The package installs: a real (not editable) ``pip install .`` into a fresh venv
runs an experiment from a directory outside the checkout.

This is what a user who installs the project gets: the shipped deployments must
come with the package (package data), every runtime import must be declared
(pip installs only those), and nothing may look for the repository's files.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import venv
from pathlib import Path

import pytest

CHECKOUT = Path(__file__).resolve().parents[1]


def _run(cmd: list[str], cwd: Path, timeout: float) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return subprocess.run(
        cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False
    )


def _copy_checkout(dst: Path) -> Path:
    """The project's files, copied to ``dst``: pip builds in the source tree, so
    builds run from a copy and the checkout stays clean."""
    shutil.copytree(
        CHECKOUT,
        dst,
        ignore=shutil.ignore_patterns(
            ".git", ".venv", "build", "*.egg-info", "out", "__pycache__", ".*_cache"
        ),
    )
    return dst


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_pip_install_runs_an_experiment_outside_the_checkout(tmp_path: Path) -> None:
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    bindir = env_dir / "bin"
    src = _copy_checkout(tmp_path / "src")
    got = _run(
        [str(bindir / "pip"), "install", "-q", "--no-cache-dir", str(src)],
        cwd=tmp_path,
        timeout=840,
    )
    assert got.returncode == 0, got.stderr[-3000:]
    # Installed, not linked to the checkout.
    where = _run(
        [str(bindir / "python"), "-c", "import awaremw; print(awaremw.__file__)"],
        cwd=tmp_path,
        timeout=60,
    )
    assert where.returncode == 0, where.stderr
    installed = Path(where.stdout.strip()).resolve()
    assert env_dir.resolve() in installed.parents

    work = tmp_path / "elsewhere"
    work.mkdir()
    run = _run(
        [str(bindir / "awaremw"), "experiment", "romeo4r", "--virtual"],
        cwd=work,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    out = work / "out" / "romeo4r"
    metrics = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    assert metrics["scenario"] == "romeo4r" and metrics["mode"] == "virtual"
    assert metrics["motes_scored"] == 20
    assert metrics["records_delivered"] > 0
    assert sorted(p.name for p in out.glob("*.png")) == [
        "romeo4r_membership.png",
        "romeo4r_rssi.png",
        "romeo4r_snapshots.png",
    ]
    # The Wireshark dissector is package data: installed, and where sniff says.
    lua = _run([str(bindir / "awaremw"), "sniff", "--dissector"], cwd=work, timeout=60)
    assert lua.returncode == 0, lua.stderr
    path = Path(lua.stdout.strip())
    assert env_dir.resolve() in path.resolve().parents
    assert "register_heuristic" in path.read_text(encoding="utf-8")


@pytest.mark.timeout(300)
def test_compiled_build_refuses_an_editable_install(tmp_path: Path) -> None:
    """``AWAREMW_USE_MYPYC=1`` with ``pip install -e``: compiled modules next to the
    sources would shadow every later edit, so setup.py stops with a clear error
    (before compiling anything) and nothing is installed."""
    src = _copy_checkout(tmp_path / "src")
    target = tmp_path / "site"
    env = {**os.environ, "AWAREMW_USE_MYPYC": "1"}
    got = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-build-isolation", "--no-deps", "-e",
         str(src), "--target", str(target)],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=240, check=False,
    )  # fmt: skip
    assert got.returncode != 0
    assert "AWAREMW_USE_MYPYC=1 is for a regular install" in got.stdout + got.stderr
    assert not list(src.rglob("*.so")) and not (target / "awaremw").exists()
