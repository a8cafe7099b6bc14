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
def ctrl_c_before_the_answer(monkeypatch: pytest.MonkeyPatch) -> Callable[[str], None]:
    """Factory: the next POST whose path ends with the given one reaches dncq, which acts on
    it, and the user presses Ctrl-C before the CLI reads the answer (once; later calls are
    left alone)."""
    call = Client.call

    def interrupt(ending: str) -> None:
        pending = [ending]

        def interrupted(self: Client, method: str, path: str, **kwargs: Any) -> Any:
            answer = call(self, method, path, **kwargs)
            if pending and method == "POST" and path.endswith(pending[0]):
                pending.clear()
                raise KeyboardInterrupt
            return answer

        monkeypatch.setattr(Client, "call", interrupted)

    return interrupt
