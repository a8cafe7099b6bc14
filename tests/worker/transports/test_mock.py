"""The mock transport passes the conformance suite (its storage is a local folder)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.worker.transports.contract import *  # noqa: F403
from worker.transports.mock import MockOptions, MockTransport


@pytest.fixture
def transport(tmp_path: Path) -> Iterator[MockTransport]:
    mock = MockTransport(MockOptions(), folder=tmp_path / "machine")
    yield mock
    mock.close()
