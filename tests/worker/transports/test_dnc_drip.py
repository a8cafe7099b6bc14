"""Drip-feed runs of the `dnc` transport against the simulator: line sync, window, stop,
link drops shorter and longer than the grace period, and a control not in DNC mode."""

from __future__ import annotations

import threading
import tracemalloc
from collections.abc import Callable, Iterator

import pytest

from tests.jobs.helpers import wait_until
from tests.worker.simulator.sim_process import Sim, SimFactory, start_sim  # noqa: F401
from tests.worker.transports.tcp_proxy import CuttableProxy, make_proxy  # noqa: F401
from worker.transports import dnc_wire as wire
from worker.transports.base import Busy
from worker.transports.dnc import DncTransport
from worker.transports.dnc_drip import NotInDncMode
from worker.transports.drip import LinkLost

ProxyFactory = Callable[[int], CuttableProxy]
# The simulator's own link supervision, short so that a paused link is noticed in tests.
FAST_HEARTBEAT = ("--heartbeat-s", "0.2", "--ping-checks", "3")


def program(count: int) -> Iterator[bytes]:
    """A program of `count` distinct lines, made as it is read."""
    for number in range(1, count + 1):
        yield b"N%d G01 X%d.%03d" % (number, number % 500, number % 1000)


def expected(count: int) -> list[str]:
    return [line.decode() for line in program(count)]


class Watch:
    """on_line and should_stop for a run: records line sync, acts at a running line."""

    def __init__(self, at_line: int = 0, action: Callable[[], None] | None = None) -> None:
        self.seen: list[tuple[int, int]] = []
        self.at_line = at_line
        self.action = action
        self.stop = False

    def on_line(self, running: int, sent: int) -> None:
        self.seen.append((running, sent))
        if self.action is not None and running >= self.at_line:
            action, self.action = self.action, None
            threading.Thread(target=action, daemon=True).start()  # off the feeding thread

    def should_stop(self) -> bool:
        return self.stop


def run(dnc: DncTransport, count: int, watch: Watch) -> object:
    return dnc.drip_feed("BIG.NC", program(count), total_lines=count, on_line=watch.on_line,
                         should_stop=watch.should_stop)


@pytest.mark.timeout(120)
def test_a_200000_line_program_runs_through_a_window_never_above_1000_lines(
        start_sim: SimFactory) -> None:  # noqa: F811
    sim = start_sim("--block-rate", "40000")
    dnc = sim.transport()
    watch = Watch()

    result = run(dnc, 200_000, watch)
    dnc.close()

    assert result.last_line == 200_000 and result.lines_sent == 200_000  # type: ignore[attr-defined]
    wait_until(lambda: sim.runs(), timeout_s=30)  # the control writes its record once done
    (record,) = sim.runs()
    assert record["ended"] == "done" and 100 <= record["peak_window_lines"] <= 1000
    assert sim.executed() == expected(200_000)
    running = [line for line, _ in watch.seen]
    assert running == sorted(running)
    assert any(0 < line < 200_000 for line in running)  # line sync while it ran


# A list of the 200,000 lines alone takes 12 MB; the feed itself peaks near 0.2 MB.
FLAT_PEAK_BYTES = 5 * 1024 * 1024


@pytest.mark.timeout(180)
def test_a_200000_line_drip_feed_keeps_the_client_memory_flat(
        start_sim: SimFactory) -> None:  # noqa: F811
    sim = start_sim("--block-rate", "40000")
    dnc = sim.transport()
    last = [0, 0]  # the latest line sync only: recording each would grow with the program

    def on_line(running: int, sent: int) -> None:
        last[:] = running, sent

    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        before, _ = tracemalloc.get_traced_memory()
        result = dnc.drip_feed("BIG.NC", program(200_000), total_lines=200_000,
                               on_line=on_line, should_stop=lambda: False)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
        dnc.close()

    assert result.last_line == 200_000 and last == [200_000, 200_000]
    assert peak - before < FLAT_PEAK_BYTES, f"peak {(peak - before) / 1e6:.1f} MB above the start"


def test_stop_resets_the_control_and_ends_the_run(start_sim: SimFactory) -> None:  # noqa: F811
    sim = start_sim("--block-rate", "500")
    dnc = sim.transport()
    watch = Watch(at_line=100)
    watch.action = lambda: setattr(watch, "stop", True)

    result = run(dnc, 100_000, watch)
    dnc.close()

    assert result.stopped and 100 <= result.last_line < 100_000  # type: ignore[attr-defined]
    wait_until(lambda: sim.runs(), timeout_s=30)
    (record,) = sim.runs()
    assert record["ended"] == "reset" and record["last_line"] == result.last_line  # type: ignore[attr-defined]
    assert sim.executed() == expected(result.last_line)  # type: ignore[attr-defined]


def test_a_stop_asked_after_the_control_ran_the_last_line_ends_the_run_done(
        start_sim: SimFactory) -> None:  # noqa: F811
    # Every line was sent and END_FILE_DNC with them; the stop comes once the control has
    # run them all. Its answer says done: nothing was stopped.
    sim = start_sim("--block-rate", "100")
    dnc = sim.transport()
    watch = Watch()
    asked: list[bool] = []

    def should_stop() -> bool:
        if watch.seen and watch.seen[-1][1] == 200:  # all held, END_FILE_DNC sent with them
            wait_until(lambda: sim.runs(), timeout_s=30)  # the control says done from here
            asked.append(True)
            return True
        return False

    result = dnc.drip_feed("BIG.NC", program(200), total_lines=200, on_line=watch.on_line,
                           should_stop=should_stop)
    dnc.close()

    assert asked  # the stop was asked before the client heard the run was done
    assert (result.last_line, result.stopped) == (200, False)
    assert [r["ended"] for r in sim.runs()] == ["done"]


@pytest.mark.parametrize("drop", ["pause", "cut"])
def test_a_short_link_drop_resumes_without_a_lost_or_repeated_line(
        start_sim: SimFactory, make_proxy: ProxyFactory, drop: str) -> None:  # noqa: F811
    """A pause holds the bytes 3 s (the client's ping checks, 3 x 0.2 s, give up first and
    it connects again); a cut closes the connection. Either way the control resumes."""
    sim = start_sim("--block-rate", "3000", *FAST_HEARTBEAT)
    proxy = make_proxy(sim.port)
    dnc = sim.transport(proxy.port, heartbeat_interval_s=0.2, grace_s=20.0)

    def drop_link() -> None:
        if drop == "cut":
            proxy.cut()
        else:
            proxy.pause()
            threading.Event().wait(3.0)
            proxy.resume()

    result = run(dnc, 8000, Watch(at_line=1000, action=drop_link))
    dnc.close()

    assert result.last_line == 8000  # type: ignore[attr-defined]
    assert proxy.connections >= 2  # the link did drop, and the client connected again
    wait_until(lambda: sim.runs(), timeout_s=30)  # its log is whole once its record is written
    assert sim.executed() == expected(8000)
    assert sim.runs()[-1]["ended"] == "done"


def test_a_drop_that_loses_the_answer_to_end_file_dnc_still_ends_the_run_done(
        start_sim: SimFactory, make_proxy: ProxyFactory) -> None:  # noqa: F811
    """END_FILE_DNC arrives, its answer is lost with the link, and the control finishes
    the program before the client is back: the resumed run is the control's done one."""
    sim = start_sim("--block-rate", "3000", *FAST_HEARTBEAT)
    proxy = make_proxy(sim.port)
    dnc = sim.transport(proxy.port, grace_s=20.0)
    end_file_dnc = wire.MAGIC + bytes([wire.VERSION, wire.Command.END_FILE_DNC])
    proxy.cut_after(end_file_dnc, lambda: wait_until(lambda: sim.runs(), timeout_s=30))

    result = run(dnc, 1500, Watch())
    dnc.close()

    assert (result.last_line, result.stopped) == (1500, False)  # type: ignore[attr-defined]
    assert proxy.connections >= 2  # the link did drop after END_FILE_DNC
    assert sim.executed() == expected(1500)
    assert [r["ended"] for r in sim.runs()] == ["done"]


def test_a_drop_longer_than_the_grace_period_is_link_lost_with_the_last_line(
        start_sim: SimFactory, make_proxy: ProxyFactory) -> None:  # noqa: F811
    """grace_s is 1 s here (a real one is tens of seconds); the link stays down."""
    sim = start_sim("--block-rate", "2000", *FAST_HEARTBEAT)
    proxy = make_proxy(sim.port)
    dnc = sim.transport(proxy.port, heartbeat_interval_s=0.2, grace_s=1.0)

    with pytest.raises(LinkLost) as lost:
        run(dnc, 50_000, Watch(at_line=500, action=proxy.down))
    dnc.close()

    assert 500 <= lost.value.last_line <= lost.value.lines_sent < 50_000
    assert len(sim.executed()) >= lost.value.last_line


def test_a_control_switched_out_of_dnc_mode_mid_run_is_waited_for_and_the_run_goes_on(
        start_sim: SimFactory, tmp_path) -> None:  # noqa: F811
    # The seed (S63): the client keeps querying until the control's conditions are met
    # again. The operator switches to MEM for a moment, then back to DNC.
    panel = tmp_path / "panel"
    sim = start_sim("--block-rate", "2000", "--panel", str(panel))
    dnc = sim.transport(max_poll_interval_s=0.05)

    def switch_away_and_back() -> None:
        (panel / "mode").write_text("mem")
        wait_until(lambda: not (panel / "mode").exists(), timeout_s=10)  # the key was taken
        threading.Event().wait(1.5)
        (panel / "mode").write_text("dnc")

    result = run(dnc, 6000, Watch(at_line=500, action=switch_away_and_back))
    dnc.close()

    assert result.last_line == 6000 and not result.stopped  # type: ignore[attr-defined]
    wait_until(lambda: sim.runs(), timeout_s=30)
    assert sim.executed() == expected(6000)  # none lost or repeated across the switch
    assert sim.runs()[-1]["ended"] == "done"


def test_a_reset_at_the_machine_mid_run_ends_it_as_lost_with_where_to_restart(
        start_sim: SimFactory, tmp_path) -> None:  # noqa: F811
    panel = tmp_path / "panel"
    sim = start_sim("--block-rate", "2000", "--panel", str(panel))
    dnc = sim.transport()

    with pytest.raises(LinkLost) as lost:
        run(dnc, 50_000, Watch(at_line=500, action=lambda: (panel / "reset").write_text("")))
    dnc.close()

    assert "the control no longer holds the run (reset at the machine)" in str(lost.value)
    wait_until(lambda: sim.runs(), timeout_s=30)
    executed = len(sim.executed())
    assert 500 <= lost.value.last_line <= executed <= lost.value.lines_sent < 50_000


@pytest.mark.parametrize(("args", "said"), [(("--mode", "mem"), "MEM mode"),
                                            (("--io-channel", "rs232"), "IO channel")])
def test_a_control_that_cannot_take_dnc_refuses_with_its_hint(
        start_sim: SimFactory, args: tuple[str, ...], said: str) -> None:  # noqa: F811
    sim: Sim = start_sim(*args)
    dnc = sim.transport()

    with pytest.raises(NotInDncMode, match=said) as refused:
        run(dnc, 10, Watch())
    dnc.close()

    assert isinstance(refused.value, Busy)
    assert sim.runs() == []
