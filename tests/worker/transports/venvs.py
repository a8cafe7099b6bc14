"""Servers the tests install from PyPI into virtual environments of their own, kept between runs."""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import sys
from pathlib import Path

from tests.servers import unavailable

INSTALL_TIMEOUT_S = 900


def cache_dir() -> Path:
    """Where the environments live (`DNCQ_TEST_CACHE`, default `~/.cache/dncq-tests`)."""
    folder = Path(os.environ.get("DNCQ_TEST_CACHE", "~/.cache/dncq-tests")).expanduser()
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def venv_with(name: str, requirement: str) -> Path:
    """The python of `<cache>/<name>-venv` holding `requirement`, installed on first use.

    A marker file written after a successful install makes the environment reusable;
    without it (an install that was interrupted) the folder is made again.
    """
    venv = cache_dir() / f"{name}-venv"
    marker = venv / ".dncq-ready"
    python = venv / "bin" / "python"
    with open(cache_dir() / f"{name}-venv.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one installer at a time (pytest-xdist workers)
        if marker.exists() and marker.read_text().strip() == requirement and python.exists():
            return python
        shutil.rmtree(venv, ignore_errors=True)
        try:
            subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True,
                           capture_output=True, timeout=120)
            subprocess.run([str(python), "-m", "pip", "install", "-q", requirement], check=True,
                           capture_output=True, timeout=INSTALL_TIMEOUT_S)
        except (OSError, subprocess.SubprocessError) as exc:
            tail = getattr(exc, "stderr", b"") or b""
            unavailable(f"cannot install {requirement} into {venv}: {exc} "
                        f"{tail.decode(errors='replace')[-500:]}")
        marker.write_text(requirement + "\n")
    return python
