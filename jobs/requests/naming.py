"""A command's body as a file name or a folder: the seed's prefix, suffix and extension,
padding and ignored characters, and the checks that keep the result one safe name."""

from __future__ import annotations

import re

from jobs.fleet.request_settings import NamingRules, check_file_name, check_relative_folder

_DRIVE = re.compile(r"[A-Za-z]:")


def file_name(body: str, naming: NamingRules) -> str:
    """The file a body names: `10` is `0010` with four-digit padding.

    In order: the ignored characters are dropped; a `number_letter` before a number is
    dropped (`O10` is `10`); a number shorter than `pad_to` is padded on its left; then
    `prefix + name + suffix`, and the extension by `extension_mode` (replace: the body's
    extension becomes `extension`; add: `extension` always added; remove: the body's
    dropped; keep: the body's kept, `extension` added only when it has none).

    Raises:
        ValueError: nothing is left, or the result is not one safe file name (a `/`,
            `\\`, `..`, control characters).
    """
    text = "".join(char for char in body if char not in naming.ignore_chars).strip()
    if not text:
        raise ValueError("no file name given")
    if naming.extension_mode == "add":
        stem, extension = text, naming.extension
    else:
        stem, extension = _split_extension(text)
        if naming.extension_mode == "replace":
            extension = naming.extension
        elif naming.extension_mode == "remove":
            extension = ""
        elif not extension:
            extension = naming.extension
    letter = naming.number_letter
    if letter and stem[:1].upper() == letter.upper() and stem[1:].isdigit():
        stem = stem[1:]
    if naming.pad_to and stem.isdigit():
        stem = stem.rjust(naming.pad_to, naming.pad_char)
    name = f"{naming.prefix}{stem}{naming.suffix}" + (f".{extension}" if extension else "")
    if not name.strip("."):  # `...`: dots only, which some storage reads as a path step
        raise ValueError(f"file name {name!r} is not a name")
    return check_file_name(name)


def _split_extension(text: str) -> tuple[str, str]:
    stem, dot, extension = text.rpartition(".")
    if dot and stem and extension and not stem.endswith(".") and " " not in extension:
        return stem, extension
    return text, ""


def relative_folder(body: str) -> str:
    """The folder a set-path body names, relative to the sources: `/VIPROS` is `VIPROS`,
    `VIPROS\\OLD` is `VIPROS/OLD`, "" or `/` the top.

    Raises:
        ValueError: it leaves the sources (`..`, a drive, a UNC path) or has an unsafe step.
    """
    text = body.strip().replace("\\", "/")
    if _DRIVE.match(text) or text.startswith("//"):
        raise ValueError(f"folder {body!r} is absolute; give a folder below the sources")
    steps = [step for step in text.strip("/").split("/") if step != "."]
    if ".." in steps:
        raise ValueError(f"folder {body!r} leaves the sources ('..')")
    return check_relative_folder("/".join(steps), what="folder")


def path_of(folder: str, name: str | None) -> str:
    """`VIPROS/0010`: a folder and a name as one path for messages ("" folder: the top)."""
    if name is None:
        return folder or "/"
    return f"{folder}/{name}" if folder else name
