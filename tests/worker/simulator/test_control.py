"""The simulated control on its own: a run that starved before its end of data still ends,
and the feed holds it records."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.jobs.helpers import wait_until
from worker.simulator.control import Control, IoChannel, RunState
from worker.simulator.programs import ProgramStore


@pytest.fixture
def control(tmp_path: Path) -> Iterator[Control]:
    made = Control(ProgramStore(tmp_path / "root"), block_rate=20_000)
    yield made
    made.close()


def test_a_run_starved_when_its_end_of_data_comes_is_done(control: Control) -> None:
    control.start_dnc("P1", channel=IoChannel.NETWORK)
    control.load(1, [b"G1 X%d" % n for n in range(1, 201)])
    wait_until(lambda: control.state is RunState.STARVED)  # every line executed, more due

    control.end_of_data()

    wait_until(lambda: control.state is RunState.DONE)
    assert control.last_run is not None and control.last_run.last_line == 200
    assert control.last_run.ended == "done" and control.last_run.starved_count == 1


def test_lines_after_a_starvation_end_it_and_its_length_is_recorded(control: Control) -> None:
    control.start_dnc("P1", channel=IoChannel.NETWORK)
    control.load(1, [b"G1 X1"] * 100)
    wait_until(lambda: control.state is RunState.STARVED)

    control.load(101, [b"G1 X2"] * 100)
    control.end_of_data()

    wait_until(lambda: control.state is RunState.DONE)
    assert control.last_run is not None and control.last_run.starved_count == 1
    assert control.last_run.longest_starved_ms > 0 and control.longest_starved_s > 0
