"""The demo fleet: simulated machines of several controller models with sample programs."""

from __future__ import annotations

import contextlib
import io
from collections.abc import Iterator
from pathlib import Path

from sqlalchemy.orm import Session

from jobs.errors import ContractError, ErrorCode
from jobs.fleet import demo_links, door, fleet_file, registry
from jobs.folders import private_dir

FANUC_SAMPLE = "%\nO{num}\nG21 G90 G40\nT01 M06\nG90 G0 G54 X12.64 Y88.0 S2546\nM30\n%\n"
GCODE = "G21 G90 G40\nT01 M06\nG0 X0 Y0 Z5.\nG1 Z-1. F200\nM30\n"

DEMO_FLEET: list[dict[str, object]] = [
    {"id": "1010", "name": "Lathe-A", "model": "Fanuc 0i-F", "tags": ["lathes", "hall-1"],
     "options": {"current_program": "O1234"}},
    {"id": "1011", "name": "Mill-B", "model": "Siemens 840D", "tags": ["mills", "hall-1"]},
    {"id": "1012", "name": "Mill-C", "model": "Heidenhain TNC640", "tags": ["mills", "hall-2"]},
    {"id": "1013", "name": "Lathe-D", "model": "Mitsubishi M800", "tags": ["lathes", "hall-2"]},
    {"id": "1014", "name": "Tapper-E", "model": "Brother S", "tags": ["hall-2"]},
    {"id": "1015", "name": "Lathe-F", "model": "Fanuc 18i", "tags": ["lathes", "hall-1"]},
    # Its control drops request programs into /requests (answers are written there too).
    {"id": "1016", "name": "Sim-G", "model": "Mock", "tags": ["sim"],
     "requests": {"enabled": True, "drop_folder": "/requests"}},
    # A control reached only over its DNC link (the seed's TCP protocol), simulated by
    # `dncq serve` itself (jobs.fleet.demo_links); its port is set at each start.
    {"id": "2001", "name": "DNC-H", "model": "Fanuc 0i-F", "transport": "dnc",
     "tags": ["dnc", "hall-3", demo_links.SIMULATED_LINK_TAG],
     "options": {"host": "127.0.0.1", "port": 1}, "requests": {"enabled": True}},
    # An older control on RS-232, behind a serial device server (simulated as well).
    {"id": "2002", "name": "RS232-J", "model": "Fanuc 0i-F", "transport": "serial",
     "tags": ["rs232", "hall-3", demo_links.SIMULATED_LINK_TAG],
     "options": {"url": "socket://127.0.0.1:1", "baud": 115200}, "requests": {"enabled": True}},
]
DRIP_SAMPLE_LINES = 20_000  # data/samples/BIGPART.NC: a drip-feed run of about 40 s

# (machine id, folder as dirAtCNC or None for the root, file name, content)
SAMPLES: list[tuple[str, str | None, str, str]] = [
    ("1010", None, "", FANUC_SAMPLE.format(num="1234")),
    ("1010", None, "", FANUC_SAMPLE.format(num="8000")),
    ("1010", None, "", FANUC_SAMPLE.format(num="0010")),
    ("1010", "//CNC_MEM/USER", "", FANUC_SAMPLE.format(num="2000")),
    ("1011", None, "PART1.MPF", GCODE),
    ("1011", "dir1", "sample.NC", GCODE),
    ("1012", None, "PLATE.h", "0 BEGIN PGM PLATE MM\n1 L Z+100 R0 FMAX\n2 END PGM PLATE MM\n"),
    ("1012", "demo", "FLANGE.h", "0 BEGIN PGM FLANGE MM\n1 END PGM FLANGE MM\n"),
    ("1013", None, "100", GCODE),
    ("1013", "IC1", "200", GCODE),
    ("1014", None, "O1000.NC", GCODE),
    ("1015", None, "", FANUC_SAMPLE.format(num="0001")),
    ("1016", None, "SAMPLE", GCODE),
    ("1016", "1", "sample1.nc", GCODE),
    ("1016", "1/1", "sample2.nc", GCODE),
]

DEMO_FOLDERS: list[tuple[str, str, str]] = [  # (machine id, parent dirAtCNC, new folder)
    ("1010", "//CNC_MEM/", "USER"),
    ("1011", "mpf.dir", "dir1"),
    ("1012", "TNC:\\nc_prog", "demo"),
    ("1016", "/", "1"),
    ("1016", "/1", "1"),
    ("1016", "/", "requests"),
]


def create(*, session: Session, data_dir: Path) -> int:
    """Register the demo fleet and put sample programs on it; returns the machine count."""
    fleet_file.import_fleet(
        session=session, machines=[registry.MachineIn.model_validate(m) for m in DEMO_FLEET],
        data_dir=data_dir)
    session.flush()
    for machine_id, parent, new_folder in DEMO_FOLDERS:
        with door.open_files(registry.get(session=session, machine_id=machine_id),
                                 data_dir=data_dir) as files, _unless_exists():
            files.make_dir(new_folder, parent, None)
    _link_samples(data_dir)
    for machine_id, folder, name, content in SAMPLES:
        data = content.encode()
        with door.open_files(registry.get(session=session, machine_id=machine_id),
                                 data_dir=data_dir) as files, _unless_exists():
            files.send(files.send_ref(name, folder, None, data), io.BytesIO(data))
    return len(DEMO_FLEET)


def _link_samples(data_dir: Path) -> None:
    """The DNC machine's own program (in its simulated control's store) and a program
    larger than a control's memory to drip-feed, in data/samples/."""
    store = private_dir(data_dir / "sim" / "2001")
    own = store / "O0100"
    if not own.exists():
        own.write_text(demo_links.sample_program("0100", 20))
    samples = private_dir(data_dir / "samples")
    big = samples / "BIGPART.NC"
    if not big.exists():
        big.write_text(demo_links.sample_program("0200", DRIP_SAMPLE_LINES))


@contextlib.contextmanager
def _unless_exists() -> Iterator[None]:
    """Starting the demo twice finds its samples there: that is fine."""
    try:
        yield
    except ContractError as exc:
        if exc.code is not ErrorCode.PATH_EXISTS:
            raise
