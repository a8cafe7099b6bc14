"""The demo's library programs that its machines' operators can ask for from the control."""

from __future__ import annotations

from sqlalchemy.orm import Session

from jobs.library import blobs
from jobs.library import service as library
from jobs.settings import Settings

# (folder, name, program): what `(DIR=/VIPROS)(PRG=0010)` asks for in the demo
PROGRAMS: list[tuple[str, str, str]] = [
    ("VIPROS", "0010", "%\nO0010 (VIPROS BRACKET)\nG21 G90 G40 G80\nT01 M06\n"
                       "G54 G0 X0 Y0 S2500 M03\nG43 Z5. H01\nN100 G1 Z-2. F200\n"
                       "N110 X40. F600\nN120 Y30.\nN130 X0\nN140 Y0\nG0 Z50.\nM30\n%\n"),
    ("VIPROS", "0020", "%\nO0020 (VIPROS FLANGE)\nG21 G90\nT02 M06\nG0 X0 Y0\nM30\n%\n"),
]


def seed(*, session: Session, settings: Settings) -> int:
    """Add the demo's approved programs the library does not hold yet; returns how many."""
    added = 0
    for folder, name, text in PROGRAMS:
        if library.holds(session=session, folder=folder, name=name):
            continue
        blob = blobs.put(settings, [text.encode()])
        library.add(session=session, folder=folder, name=name, blob=blob,
                    note="demo program", created_by="demo", approve=True)
        added += 1
    return added
