"""How often a drip-feed run of the `dnc` transport asks the control: by how long the lines
it holds ahead of its running line last, within poll_interval_s and max_poll_interval_s."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.worker.transports.test_dnc_drip import expected, program
from worker.simulator.control import Control
from worker.simulator.programs import ProgramStore
from worker.simulator.tcp_server import DncServer
from worker.transports.dnc import DncOptions, DncTransport
from worker.transports.dnc_drip import Pace
from worker.transports.dnc_wire import Command

# A fixed 0.05 s poll (poll_interval_s's default) asks a 1,000 blocks/s control for room
# about 28 times per 1,000 lines; paced by the window, about 4 (a quarter of ~0.9 s apart).
MAX_QUERIES_PER_1000_LINES = 10


@pytest.fixture
def control(tmp_path: Path) -> Iterator[tuple[Control, DncServer]]:
    """A simulated control at 1,000 blocks/s and its server, in this process."""
    made = Control(ProgramStore(tmp_path / "root"), block_rate=1000, log_dir=tmp_path / "log")
    server = DncServer(made)
    server.start()
    yield made, server
    server.close()
    made.close()


@pytest.mark.timeout(60)
def test_a_control_with_plenty_in_hand_is_asked_for_room_seldom(
        control: tuple[Control, DncServer], tmp_path: Path) -> None:
    _, server = control
    dnc = DncTransport(DncOptions(host="127.0.0.1", port=server.port, poll_interval_s=0.05))

    result = dnc.drip_feed("PACE.NC", program(5000), total_lines=5000,
                           on_line=lambda running, sent: None, should_stop=lambda: False)
    dnc.close()

    assert result.last_line == 5000
    assert (tmp_path / "log" / "executed.log").read_text().splitlines() == expected(5000)
    queries = server.requests[Command.QUERY_FILE_DNC]
    assert queries < 5 * MAX_QUERIES_PER_1000_LINES, f"{queries} QUERY_FILE_DNC"


def paced(rate: float) -> Pace:
    """A Pace that has seen the control run at `rate` lines/s."""
    pace = Pace(0.05, 0.25)
    pace.rates.append(rate)
    return pace


def test_the_wait_is_a_quarter_of_the_time_the_lines_ahead_last() -> None:
    assert paced(1000).wait_s(ahead_lines=400, sent=True) == pytest.approx(0.1)


def test_the_wait_is_never_above_max_poll_interval_s() -> None:
    assert paced(1000).wait_s(ahead_lines=1000, sent=False) == 0.25
    assert paced(0.5).wait_s(ahead_lines=1000, sent=True) == 0.25


@pytest.mark.parametrize(("sent", "wait_s"), [(True, 0.0), (False, 0.05)])
def test_a_control_about_to_run_dry_is_polled_at_once_after_a_send(
        sent: bool, wait_s: float) -> None:
    """40,000 blocks/s and 1,000 lines ahead: 25 ms of lines, a quarter under 0.05 s."""
    assert paced(40_000).wait_s(ahead_lines=1000, sent=sent) == wait_s


def test_without_a_rate_the_poll_is_the_fixed_one() -> None:
    pace = Pace(0.05, 0.25)
    pace.saw(0)  # one sighting: no rate yet

    assert pace.wait_s(ahead_lines=1000, sent=True) == 0.0
    assert pace.wait_s(ahead_lines=1000, sent=False) == 0.05


def test_the_highest_recent_rate_paces_so_a_starved_stretch_does_not_lengthen_the_wait(
        ) -> None:
    pace = paced(1000)
    pace.rates.append(0.0)  # a round during which the control ran nothing

    assert pace.wait_s(ahead_lines=400, sent=True) == pytest.approx(0.1)
