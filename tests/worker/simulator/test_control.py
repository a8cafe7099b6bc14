"""The simulated control on its own: a run that starved before its end of data still ends,
and the feed holds it records."""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.jobs.helpers import wait_until
from worker.simulator.control import Control, IoChannel, NotReadyToRead, RunState
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


def test_a_program_read_in_after_read_replaces_its_namesake_and_ends_the_read(
        control: Control) -> None:
    (control.store.root / "P1").write_bytes(b"old")
    control.press_read()

    with control.read_in("P1") as out:
        out.write(b"new")

    assert (control.store.root / "P1").read_bytes() == b"new"
    assert not control.ready_to_read


def test_a_read_in_without_read_pressed_is_refused(control: Control) -> None:
    with pytest.raises(NotReadyToRead), control.read_in("P1"):
        pass


def test_a_read_in_that_fails_stores_nothing_and_the_control_stays_ready(
        control: Control) -> None:
    control.press_read()

    with pytest.raises(ConnectionError), control.read_in("P1") as out:
        out.write(b"half")
        raise ConnectionError("the link went")

    assert list(control.store.root.iterdir()) == [] and control.ready_to_read


def test_read_holds_only_for_its_window(control: Control) -> None:
    control.press_read(window_s=0.05)

    wait_until(lambda: not control.ready_to_read)


def test_punched_programs_leave_the_outbox_oldest_first_once_sent(control: Control) -> None:
    control.punch("O0001", b"first")
    control.punch("O0002", b"second")

    first = control.first_punch()
    assert first is not None and control.first_punch() == first == ("O0001", b"first")
    control.punch_sent(first)

    assert control.first_punch() == ("O0002", b"second") and control.outbox_length == 1


def test_next_line_read_while_the_control_frees_executed_lines_is_the_true_one(
        control: Control) -> None:
    """The RS-232 side reads `next_line` without the lock and loads its line there; had it
    read a number too small halfway through a freeing, the line was refused as one already
    held, and lost. Each step of the freeing reads it here, as another thread may."""
    seen: list[int] = []

    class Window(deque[bytes]):
        def popleft(self) -> bytes:
            seen.append(control.next_line)
            return super().popleft()

    control.start_dnc("P1", channel=IoChannel.NETWORK)
    control._window = Window()
    control.load(1, [b"G1 X1"] * 250)
    control.end_of_data()

    wait_until(lambda: control.state is RunState.DONE)
    assert len(seen) == 200 and set(seen) == {251}
    assert control.last_run is not None and control.last_run.lines_loaded == 250
