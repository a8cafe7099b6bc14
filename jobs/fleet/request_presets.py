"""The request settings each controller family starts from, as plain data.

`RequestSettings()` without a preset is the Fanuc one, so the seed's example works on any
ISO control out of the box. Choices per family:

- fanuc: programs `O1234` between `%` lines, comments in parentheses, the request program
  `O8888`. A body `0010` (or `10`, or `O10`) names the library file `0010`, padded to four
  digits: the library keeps Fanuc programs under their number without the `O` (`VIPROS/0010`
  holds `O0010`), and the control gets `O0010` because the program says so. Answers are
  `O8889` (a listing) and `O8890` (an error or status report), ending `M30`.
- haas: as Fanuc, with five-digit numbers as the current (NGC) control writes them: the
  request program `O08888`, files `00010`, answers `O08889` and `O08890`. For a classic
  control's four digits give `naming: {pad_to: 4}`.
- heidenhain_iso: programs `%1234 G71 *` ... `N99999999 %1234 G71 *`, every block numbered
  and ended by `*`; comments start with `;` (the TNC's comment character in ISO and
  conversational programs alike; parentheses are not comments there). Files are the ISO
  `.I` files: `1234` names `1234.I`. The request program `9999`, answers `9998` and `9997`.
- siemens_iso: programs `%_N_NAME_MPF`, comments `;`; `PART1` names `PART1.MPF`. The
  request program `DNCREQ`, answers `DNCLIST.MPF` and `DNCERR.MPF`, ending `M30`.

Every family: body commands as comments (`(PRG=0010)`, `;PRG=0010` where `;` comments) or
slash words (`/REQ 0010`), with the command names of `COMMANDS`.
"""

from __future__ import annotations

from typing import Any

COMMANDS: dict[str, str] = {
    "PRG": "send",  # (PRG=0010): send VIPROS/0010
    "REQ": "send",  # /REQ 0010
    "LST": "list",  # (LST=): the current folder's listing
    "DIR": "set_path",  # (DIR=/VIPROS)
    "FIL": "set_file",  # (FIL=0010): for a rename; as the last command, send it
    "NAME": "received_name",  # (NAME=O0010) in the header: the program's name
    "DEL": "delete",  # (DEL=0010)
    "REN": "rename",  # (FIL=0010)(REN=0020)
    "MSG": "skip",  # (MSG=...): an operator's note, logged
    "TOOLBREAK": "toolbreak",  # (TOOLBREAK=N100)(PRG=0010): restart 0010 from N100
    "CMP": "compare",  # (CMP=0010): the next program received is compared with 0010
    "RCVDIR": "directory",  # (RCVDIR=JOB42): received programs go to JOB42 for a while
}

PRESETS: dict[str, dict[str, Any]] = {
    "fanuc": {
        "dialect": "fanuc",
        "request_program": "O8888",
        "naming": {"pad_to": 4, "pad_char": "0", "number_letter": "O"},
        "listing": {"program_name": "O8889", "comment_open": "(", "comment_close": ")"},
        "error_program": {"program_name": "O8890"},
    },
    "haas": {
        "dialect": "fanuc",
        "request_program": "O08888",
        "naming": {"pad_to": 5, "pad_char": "0", "number_letter": "O"},
        "listing": {"program_name": "O08889", "comment_open": "(", "comment_close": ")"},
        "error_program": {"program_name": "O08890"},
    },
    "heidenhain_iso": {
        "dialect": "heidenhain_iso",
        "request_program": "9999",
        "naming": {"pad_to": 0, "number_letter": "", "extension": "I",
                   "extension_mode": "keep"},
        "listing": {"program_name": "9998", "comment_open": ";", "comment_close": " *",
                    "block_numbers": True, "end_block": ""},
        "error_program": {"program_name": "9997"},
    },
    "siemens_iso": {
        "dialect": "siemens_iso",
        "request_program": "DNCREQ",
        "naming": {"pad_to": 0, "number_letter": "", "extension": "MPF",
                   "extension_mode": "keep"},
        "listing": {"program_name": "DNCLIST.MPF", "comment_open": ";", "comment_close": ""},
        "error_program": {"program_name": "DNCERR.MPF"},
    },
}
