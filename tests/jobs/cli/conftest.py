"""Fixtures of the CLI tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.jobs.cli.runner import PROGRAM


@pytest.fixture
def program(tmp_path: Path) -> Path:
    """A small program file to send, `P.nc`, holding PROGRAM."""
    path = tmp_path / "P.nc"
    path.write_text(PROGRAM)
    return path
