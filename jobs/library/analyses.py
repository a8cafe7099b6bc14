"""Each stored program analysed once per content: the analysis kept beside its blob.

`blobs/ab/<sha256>.analysis.json` holds the analysis of `blobs/ab/<sha256>`; it is made again
only when the analyser's version or its settings change. Shared between hosts with the
blobs themselves.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from jobs.library import blobs
from jobs.library.analysis import ANALYSER_VERSION, Analysis, AnalysisSettings, analyse
from jobs.library.line_ends import split_lines
from jobs.settings import Settings


def _cache(settings: Settings, sha256: str) -> Path:
    blob = blobs.path(settings, sha256)
    return blob.with_name(f"{blob.name}.analysis.json")


def of_blob(settings: Settings, sha256: str,
            analysis_settings: AnalysisSettings | None = None) -> Analysis:
    """The analysis of the stored program `sha256` (158 when it is not stored)."""
    wanted = analysis_settings or AnalysisSettings()
    cache = _cache(settings, sha256)
    try:
        kept = Analysis.from_json(cache.read_text())
        if kept.analyser_version == ANALYSER_VERSION and \
                kept.settings_digest == wanted.digest():
            return kept
    except (OSError, ValueError):
        pass  # none yet, or of another analyser: made again
    made = analyse(_text_lines(settings, sha256), settings=wanted)
    # a temporary name of its own (0600): two first reads at once each write theirs
    handle, temp = tempfile.mkstemp(dir=cache.parent, prefix=f".{cache.name}.")
    try:
        with open(handle, "w") as out:
            out.write(made.to_json())
        os.replace(temp, cache)
    except BaseException:
        Path(temp).unlink(missing_ok=True)
        raise
    return made


def _text_lines(settings: Settings, sha256: str) -> Iterator[str]:
    """The program's lines as text (Latin-1: every byte is a character), read as they come,
    numbered as a drip-feed run numbers them (jobs.library.line_ends)."""
    for line in split_lines(blobs.read(settings, sha256)):
        yield line.decode("latin-1") + "\n"


def seed_view(analysis: Analysis) -> dict[str, str]:
    """The seed's `gcodeAnalysis`: `estimatedPrintTime` "HH:mm:ss" and `filament` "0.79m"
    (`n/a` for a machine tool's program, which uses none)."""
    return {"estimatedPrintTime": analysis.estimated_print_time,
            "filament": analysis.filament or "n/a"}


def view(analysis: Analysis) -> dict[str, object]:
    """The analysis as the library API shows it."""
    return {"cycleTimeS": round(analysis.cycle_time_s, 1),
            "estimatedTime": analysis.estimated_print_time,
            "tools": [{"tool": t.number, "firstLine": t.first_line, "lastLine": t.last_line}
                      for t in analysis.tools],
            "programNumber": analysis.program_number, "firstComment": analysis.first_comment,
            "filament": analysis.filament, "notes": list(analysis.notes)}
