"""Where a long name may wrap on a page: after its separators first, inside a word last.

A browser breaks lines at spaces and hardly anywhere else: `CAM/FIXTURE_PLATE_SECOND_OP/
O1234_ROUGHING.nc` is one word to it. Table cells keep words whole (`overflow-wrap:
break-word`, so a column is never narrower than its longest word), and this filter gives a
name its own break points: `<wbr>` after `/`, `\\`, `_` and `-`, before `.`, so the file's
extension stays with it. A word longer than `LONG_WORD_CHARS` with no separator in it is
marked `long-word`, which may be cut anywhere: it would otherwise push its table past a
tablet's screen.
"""

from __future__ import annotations

import re

from markupsafe import Markup, escape

LONG_WORD_CHARS = 24  # a longer word may be cut inside: kept whole, it widens its table
# A break point: after a run of separators, or before a run of dots, never at either end.
_BREAK = re.compile(r"(?<=[/\\_-])(?![/\\_-])(?=.)|(?<=[^.])(?=\.+[^.])")
_LONG_WORD = re.compile(rf"[^\s/\\_.-]{{{LONG_WORD_CHARS + 1},}}")


def breakable(value: object) -> Markup:
    """`value` as HTML that wraps at its separators before it wraps inside a word."""
    if value is None:
        return Markup("")
    parts = (_marked(part) for part in _BREAK.split(str(value)))
    return Markup("<wbr>").join(parts)


def _marked(text: str) -> Markup:
    """`text` escaped, each word too long to keep whole marked `long-word`."""
    out, done = Markup(), 0
    for word in _LONG_WORD.finditer(text):
        out += escape(text[done:word.start()])
        out += Markup('<span class="long-word">%s</span>') % word.group(0)
        done = word.end()
    return out + escape(text[done:])
