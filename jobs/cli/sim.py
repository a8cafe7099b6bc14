"""`dncq sim-cnc`: a simulated CNC control serving a folder over its controller links.

One control (program store, modes, DNC window) behind each link it is given: the seed's
TCP protocol on `--port`, an RS-232 line on `--serial` (a pty it creates, or a device) or
on `--tcp-raw` (a raw TCP port, as a serial device server offers); DNC over RS-232 wants
`--io-channel rs232`. Every link server is started the same way (`_links`), so a further
link is one more option and one more server on the same control. `--panel` is the
operator's keys (worker.simulator.panel).
"""

from __future__ import annotations

import signal
import time
from pathlib import Path
from typing import Annotated, Protocol

import typer

from jobs.cli.common import err
from worker.simulator.modes import IoChannel, Mode

STOP_CHECK_S = 0.2  # how soon a stop signal that reached another thread is acted on


class _LinkServer(Protocol):
    def start(self) -> None: ...

    def close(self) -> None: ...


def sim_cnc(
    port: Annotated[int, typer.Option(help="TCP port of the seed protocol (0: any free one)")],
    root: Annotated[Path, typer.Option(help="Folder that holds the control's programs")],
    model: Annotated[str, typer.Option(help="Controller model: sets the program naming "
                                       "(Fanuc: O-numbers)")] = "Generic",
    host: Annotated[str, typer.Option(help="Listen address")] = "127.0.0.1",
    block_rate: Annotated[float, typer.Option(help="Blocks executed per second in DNC",
                                              min=0.001)] = 1000.0,
    mode: Annotated[Mode, typer.Option(help="Operating mode at start")] = Mode.DNC,
    io_channel: Annotated[IoChannel, typer.Option(help="Where DNC data may come from")
                          ] = IoChannel.NETWORK,
    heartbeat_s: Annotated[float, typer.Option(help="Silence before a ping check, in s",
                                               min=0.01)] = 2.0,
    ping_checks: Annotated[int, typer.Option(help="Unanswered ping checks before the link "
                                             "is down", min=1)] = 3,
    grace_s: Annotated[float, typer.Option(help="How long a DNC run waits for its client to "
                                           "come back, in s", min=0)] = 30.0,
    log_dir: Annotated[Path | None, typer.Option(help="Write executed.log (every executed "
                                                 "line) and runs.jsonl here")] = None,
    serial: Annotated[Path | None, typer.Option(help="RS-232 on this path: a device to open, "
                                                "or where to link a new pty's other end")
                      ] = None,
    tcp_raw: Annotated[int | None, typer.Option(help="RS-232 as a raw TCP port, as a serial "
                                                "device server (0: any free one)")] = None,
    buffer_bytes: Annotated[int, typer.Option(help="RS-232 receive buffer in DNC, in bytes "
                                              "(DC3 at half, DC1 at an eighth)", min=16)
                            ] = 1024,
    baud: Annotated[int, typer.Option(help="RS-232 line speed the control is set to: bounds "
                                      "what it takes in while it looks away (a busy host)",
                                      min=300)] = 115_200,
    panel: Annotated[Path | None, typer.Option(
        help="Operator panel folder; a file written there presses a key: mode (edit, mem, "
             "dnc), reset, read (READ: read in the next program sent, replacing its "
             "namesake; holds the seconds it waits, 180 if empty), punch (a stored "
             "program's name), type (a program's text, punched as typed). Punches go to "
             "the first RS-232 side (--serial if given), else into the TCP side's outbox "
             "(QUERY_PUNCH). status.json there shows the state, ready_to_read and the "
             "outbox length")] = None,
) -> None:
    """Run a simulated CNC control until interrupted (Ctrl-C or SIGTERM)."""
    from worker.simulator.control import Control
    from worker.simulator.panel import Panel
    from worker.simulator.programs import ProgramStore
    from worker.simulator.serial_machine import PtyEnd, SerialMachine, TcpRawEnd
    from worker.simulator.tcp_server import DncServer

    control = Control(ProgramStore(root, model=model), mode=mode, io_channel=io_channel,
                      block_rate=block_rate, log_dir=log_dir)
    tcp = DncServer(control, host=host, port=port, heartbeat_s=heartbeat_s,
                    ping_checks=ping_checks, grace_s=grace_s)
    links: list[_LinkServer] = [tcp]
    ends: list[PtyEnd | TcpRawEnd] = []
    if serial is not None:
        ends.append(PtyEnd(serial))
    if tcp_raw is not None:
        ends.append(TcpRawEnd(host, tcp_raw))
    serials = [SerialMachine(control, end, buffer_bytes=buffer_bytes, baud=baud)
               for end in ends]
    links += serials
    if panel is not None:  # one panel, one PUNCH key: it punches on the first RS-232 side
        links.append(Panel(panel, control, serial=serials[0] if serials else None, tcp=tcp))
    # The handler takes no lock: it runs on the main thread between two of its steps, and an
    # Event's set() would wait for ever on the lock the main thread holds inside Event.wait.
    stopping: list[int] = []
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda signum, _frame: stopping.append(signum))
    for link in links:
        link.start()
    # The port on a line of its own: a caller that asked for port 0 reads it from here.
    print(f"listening tcp {host} {tcp.port}", flush=True)
    for end in ends:  # "serial /dev/pts/N" or "tcp-raw HOST PORT"
        print(f"listening tcp-raw {host} {end.port}" if isinstance(end, TcpRawEnd)
              else f"listening serial {end.device}", flush=True)
    err.print(f"Simulated {model} control ({mode.value.upper()} mode) serving {root}",
              highlight=False)
    # The kernel hands a process's signal to any of its threads, and Python runs the handler
    # on the main thread only once that thread runs again: a wait without a timeout would
    # sleep through a SIGTERM that reached a link's thread.
    while not stopping:
        time.sleep(STOP_CHECK_S)
    for link in links:
        link.close()
    control.close()


def register(app: typer.Typer) -> None:
    """Add `sim-cnc` to the `dncq` app."""
    app.command("sim-cnc")(sim_cnc)
