"""The simulated control's settings that `dncq sim-cnc` takes as options: its operating mode
and where its DNC data comes from. Apart from `control`, which loads the transports, so that
every other `dncq` command builds its options without them.
"""

from __future__ import annotations

from enum import StrEnum


class Mode(StrEnum):
    """The control's operating mode."""

    EDIT = "edit"  # programs are edited: nothing runs
    MEM = "mem"  # programs run from memory: no DNC
    DNC = "dnc"  # programs run from the link


class IoChannel(StrEnum):
    """Where the control takes DNC data from."""

    NETWORK = "network"  # the seed's TCP protocol
    RS232 = "rs232"  # a serial line
