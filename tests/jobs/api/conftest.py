"""The API tests' session: what a module made at its import is removed at the end."""

from __future__ import annotations

import shutil
import sys

import pytest


def pytest_sessionfinish(session: pytest.Session) -> None:
    """The OpenAPI test's data folder, made when its module was collected (in every worker
    process of a parallel run, which ends without running atexit)."""
    fuzzed = sys.modules.get("tests.jobs.api.test_openapi")
    if fuzzed is not None:
        shutil.rmtree(fuzzed.FOLDER, ignore_errors=True)
