"""The raw deflate of a backup's files, at every level a shop may set."""

from __future__ import annotations

import random
import zlib

import pytest
from isal import isal_zlib

from jobs.backup import deflate
from jobs.settings import Settings


def milling(moves: int) -> bytes:
    """A milling program of `moves` cutting moves."""
    rng = random.Random(3)
    return "".join(f"N{n * 10} G1 X{rng.uniform(0, 400):.3f} Y{rng.uniform(0, 300):.3f} F1200\n"
                   for n in range(moves)).encode()


PROGRAM = milling(9000)  # about 300 KB: larger than a chunk, as a long program is
CHUNK = 64 * 1024


@pytest.mark.parametrize("level", range(10))
def test_every_level_deflates_a_program_that_any_unzip_reads_back(level):
    assert zlib.decompress(deflate.whole(PROGRAM, level), -zlib.MAX_WBITS) == PROGRAM


@pytest.mark.parametrize("level", range(10))
def test_every_level_deflates_a_program_read_in_chunks_into_one_member(level):
    stream = deflate.stream(level)
    packed = b"".join(stream.compress(PROGRAM[at:at + CHUNK])
                      for at in range(0, len(PROGRAM), CHUNK)) + stream.flush()
    assert zlib.decompress(packed, -zlib.MAX_WBITS) == PROGRAM


def test_the_default_level_deflates_with_isal():
    # ISA-L deflates G-code several times as fast as zlib-ng's level 3 into members within
    # a few percent of its size (docs/backups.md#zip-details): the default is one of its levels.
    level = Settings.model_fields["backup_zip_level"].default
    packed = deflate.whole(PROGRAM, level)
    assert packed == isal_zlib.compress(PROGRAM, level, -isal_zlib.MAX_WBITS)
    assert len(packed) < len(PROGRAM) / 2


def test_level_zero_stores_the_bytes_as_they_are():
    # ISA-L's own level 0 still compresses; a shop that sets 0 asks for no deflate at all.
    assert len(deflate.whole(PROGRAM, 0)) < len(PROGRAM) * 1.01
    assert PROGRAM[:1000] in deflate.whole(PROGRAM, 0)
