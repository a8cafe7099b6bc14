"""The demo fleet's machines that have only a controller link: simulated controls in-process.

`dncq serve` starts one simulated control per machine tagged `simulated-link` and points the
machine at it (a free loopback port each start): the seed's TCP protocol for a `dnc`
machine, an RS-232 line behind a raw TCP serial device server for a `serial` one. So the
demo shows drip-feed runs and file work over both links with nothing else installed.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from jobs.models import Machine
from worker.simulator.control import Control, IoChannel
from worker.simulator.panel import Panel
from worker.simulator.programs import ProgramStore
from worker.simulator.serial_machine import SerialMachine, TcpRawEnd
from worker.simulator.tcp_server import DncServer

SIMULATED_LINK_TAG = "simulated-link"
DEMO_BLOCK_RATE = 500.0  # blocks/s: a 212,000-line program runs in about 7 minutes

SAMPLE = ("%\nO{num}\n(DEMO DRIP-FEED PROGRAM)\nG21 G90 G40 G80\nT01 M06\nG54 G0 X0 Y0 S3000 M03\n"
          "G43 Z5. H01 M08\n{moves}G0 Z50. M09\nM05\nM30\n%\n")


def sample_program(num: str, moves: int) -> str:
    """A real-looking Fanuc milling program with `moves` feed moves."""
    body = "".join(f"N{10 * (i + 1)} G1 X{i % 80}.{i % 10} Y{(i * 7) % 60}.0 F800\n"
                   for i in range(moves))
    return SAMPLE.format(num=num, moves=body)


def panel_dir(data_dir: Path, machine_id: str) -> Path:
    """The folder of a simulated control's operator panel: write `type`, `read`, ... there."""
    return data_dir / "sim" / f"{machine_id}-panel"


class DemoLinks:
    """The simulated controls of one `dncq serve`, closed with it."""

    def __init__(self) -> None:
        self._stack = contextlib.ExitStack()

    def start(self, *, session: Session, data_dir: Path) -> int:
        """Start a control for every machine tagged `simulated-link`; returns how many."""
        started = 0
        for machine in session.scalars(select(Machine).where(
                Machine.transport.in_(("dnc", "serial")))):
            if SIMULATED_LINK_TAG not in (machine.tags or []):
                continue
            store = ProgramStore(data_dir / "sim" / machine.id, model=machine.model)
            serial = machine.transport == "serial"
            control = Control(store, block_rate=DEMO_BLOCK_RATE,
                              io_channel=IoChannel.RS232 if serial else IoChannel.NETWORK)
            self._stack.callback(control.close)
            line: SerialMachine | None = None
            server: DncServer | None = None
            if serial:  # the control's RS-232 port behind a simulated serial device server
                end = TcpRawEnd("127.0.0.1", 0)
                line = SerialMachine(control, end)
                line.start()
                self._stack.callback(line.close)
                options = {**machine.options, "url": f"socket://127.0.0.1:{end.port}"}
            else:
                server = DncServer(control, host="127.0.0.1", port=0)
                server.start()
                self._stack.callback(server.close)
                options = {**machine.options, "host": "127.0.0.1", "port": server.port}
            # Its operator's keys: files in data/sim/<id>-panel (worker.simulator.panel).
            panel = Panel(panel_dir(data_dir, machine.id), control, serial=line, tcp=server)
            panel.start()
            self._stack.callback(panel.close)
            session.execute(update(Machine).where(Machine.id == machine.id)
                            .values(options=options))
            started += 1
        return started

    def close(self) -> None:
        self._stack.close()
