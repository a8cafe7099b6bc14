"""Library folders and names: checked as machine file names are, and `folder/name` split."""

from __future__ import annotations

from jobs.fleet.paths import MAX_PATH_CHARS, bad, check_name

MAX_FOLDER_CHARS = 500  # library_programs.folder


def check_folder(folder: str) -> str:
    """A folder such as `VIPROS` or `VIPROS/OLD`; no `..`, no root, no empty step."""
    if not folder:
        raise bad("folder is required")
    if folder.startswith("/") or ":" in folder.split("/")[0]:
        raise bad(f"folder {folder!r} is absolute; give a library folder such as VIPROS")
    if len(folder) > MAX_FOLDER_CHARS:
        raise bad(f"folder is longer than {MAX_FOLDER_CHARS} characters")
    for part in folder.split("/"):
        if not part:
            raise bad(f"folder {folder!r} has an empty step")
        check_name(part, what="folder")
    return folder


def check_program_name(name: str) -> str:
    """A program's name in its folder: a plain file name."""
    if not name:
        raise bad("name is required")
    check_name(name, what="name")
    return name


def split(path: str) -> tuple[str, str]:
    """`VIPROS/OLD/0010` as its folder and name, both checked."""
    if len(path) > MAX_PATH_CHARS:
        raise bad(f"path is longer than {MAX_PATH_CHARS} characters")
    folder, slash, name = path.rpartition("/")
    if not slash:
        raise bad(f"{path!r} is not folder/name (such as VIPROS/0010)")
    return check_folder(folder), check_program_name(name)


def split_reference(reference: str) -> tuple[str, str, int | None]:
    """`VIPROS/0010@3` as folder, name and version number (None: the current approved one)."""
    path, at, number = reference.rpartition("@")
    if not at:
        return (*split(reference), None)
    if not number.isdecimal() or int(number) < 1:
        raise bad(f"version in {reference!r} is not a number from 1")
    return (*split(path), int(number))
