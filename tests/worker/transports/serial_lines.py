"""Serial lines for the tests: the simulated control on a pty pair, and ser2net in front of it.

`serial_machine(...)` starts a simulated control whose RS-232 side holds one end of a
pseudo-terminal pair (or, with `tcp_raw`, a raw TCP port); `line_to(url, ...)` opens
dncq's serial transport; `ser2net_url(machine)` puts ser2net (the Debian package, 4.x) on a
loopback port before the pty's other end, so dncq reaches the machine through
`socket://127.0.0.1:PORT` exactly as through a shop's serial device server.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.servers import free_port, unavailable, wait_for_port
from worker.simulator.control import Control, IoChannel, Mode
from worker.simulator.programs import ProgramStore
from worker.simulator.serial_machine import PtyEnd, SerialMachine, TcpRawEnd
from worker.transports.serial_line import SerialOptions, SerialTransport

MachineFactory = Callable[..., SerialMachine]


@pytest.fixture
def serial_machine(tmp_path: Path) -> Iterator[MachineFactory]:
    """Start simulated controls on pty pairs (`machine.end.link` is the path to open), or
    with `tcp_raw` on a loopback port (`machine.end.port`)."""
    started: list[SerialMachine] = []

    def start(*, mode: Mode = Mode.EDIT, block_rate: float = 1000.0, model: str = "Generic",
              tcp_raw: bool = False, **options: Any) -> SerialMachine:
        number = len(started)
        control = Control(ProgramStore(tmp_path / f"cnc{number}", model=model), mode=mode,
                          io_channel=IoChannel.RS232, block_rate=block_rate,
                          log_dir=tmp_path / f"log{number}")
        end = (TcpRawEnd("127.0.0.1", 0) if tcp_raw
               else PtyEnd(tmp_path / f"ttyCNC{number}"))
        machine = SerialMachine(control, end, **options)
        machine.start()
        started.append(machine)
        return machine

    yield start
    for machine in started:
        machine.close()
        machine.control.close()


def url_of(machine: SerialMachine) -> str:
    """The pyserial URL of a machine's line: its pty's path, or its raw TCP port."""
    end = machine.end
    return str(end.link) if isinstance(end, PtyEnd) else f"socket://127.0.0.1:{end.port}"


@pytest.fixture
def line_to(tmp_path: Path) -> Iterator[Callable[..., SerialTransport]]:
    """Open serial transports to a URL with options; each is closed after the test."""
    opened: list[SerialTransport] = []

    def open_line(url: str, **options: object) -> SerialTransport:
        line = SerialTransport(SerialOptions(url=url, **options),  # type: ignore[arg-type]
                               folder=tmp_path / f"state{len(opened)}")
        opened.append(line)
        return line

    yield open_line
    for line in opened:
        line.close()


def ser2net_config(port: int, device: str, *, rfc2217: bool = False) -> str:
    """ser2net 4.x YAML: a TCP accepter on loopback before `device`, bytes untouched (no
    XON/XOFF of its own, modem lines ignored: a pty has none); raw TCP, or telnet with
    RFC 2217 (the client sets the line's speed and framing over the connection)."""
    accepter = "telnet(rfc2217),tcp" if rfc2217 else "tcp"
    return (f"connection: &cnc\n"
            f"  accepter: {accepter},127.0.0.1,{port}\n"
            f"  enable: on\n"
            f"  options:\n"
            f"    kickolduser: true\n"
            f"  connector: serialdev,{device},115200n81,local\n")


@pytest.fixture
def ser2net_url(tmp_path: Path) -> Iterator[Callable[[SerialMachine], str]]:
    """Start ser2net before a machine's pty; gives the `socket://` (or, with `rfc2217`, the
    `rfc2217://`) URL to reach it."""
    program = shutil.which("ser2net") or shutil.which("ser2net", path="/usr/sbin")
    if program is None:
        unavailable("ser2net is not installed (apt-get install ser2net)")
    servers: list[subprocess.Popen[bytes]] = []

    def start(machine: SerialMachine, *, rfc2217: bool = False) -> str:
        port = free_port()
        config = tmp_path / f"ser2net{len(servers)}.yaml"
        config.write_text(ser2net_config(port, machine.end.device, rfc2217=rfc2217))
        servers.append(subprocess.Popen(
            [program, "-n", "-u", "-c", str(config), "-P", str(config.with_suffix(".pid"))],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE))
        try:
            wait_for_port(port, timeout_s=10)
        except TimeoutError:
            servers[-1].kill()
            _, err = servers[-1].communicate()
            raise RuntimeError(f"ser2net did not start: {err.decode(errors='replace')}") from None
        if rfc2217:  # a pty has no modem lines: ser2net never answers their settings
            return f"rfc2217://127.0.0.1:{port}?ign_set_control"
        return f"socket://127.0.0.1:{port}"

    yield start
    for server in servers:
        server.terminate()
        try:
            server.wait(5)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()
