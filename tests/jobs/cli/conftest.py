"""Fixtures of the CLI tests."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from jobs.cli.client import Client
from tests.jobs.cli.runner import PROGRAM


@pytest.fixture
def program(tmp_path: Path) -> Path:
    """A small program file to send, `P.nc`, holding PROGRAM."""
    path = tmp_path / "P.nc"
    path.write_text(PROGRAM)
    return path


@pytest.fixture
def ctrl_c_before_the_answer(monkeypatch: pytest.MonkeyPatch) -> Callable[..., None]:
    """Factory: the next request (a POST unless `method` says) whose path ends with the given
    one reaches dncq, which acts on it, and the user presses Ctrl-C before the CLI reads the
    answer (once; later calls are left alone)."""
    call = Client.call

    def interrupt(ending: str, method: str = "POST") -> None:
        pending = [(method, ending)]

        def interrupted(self: Client, method: str, path: str, **kwargs: Any) -> Any:
            answer = call(self, method, path, **kwargs)
            if pending and method == pending[0][0] and path.endswith(pending[0][1]):
                pending.clear()
                raise KeyboardInterrupt
            return answer

        monkeypatch.setattr(Client, "call", interrupted)

    return interrupt
