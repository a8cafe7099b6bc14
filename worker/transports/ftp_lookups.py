"""What is at a name on an FTP server: its folders' listings (MLSD, LIST, NLST), a file's or
folder's facts (MLST, SIZE, MDTM, CWD), and links read as what they lead to."""

from __future__ import annotations

import contextlib
import ftplib
import posixpath
from collections.abc import Callable

from worker.transports.base import (
    CHUNK_BYTES,
    Deadline,
    Entry,
    NotFound,
    Permanent,
    Unsupported,
    byte_count,
)
from worker.transports.ftp_errors import translated
from worker.transports.ftp_link import FtpOptions, finish
from worker.transports.ftp_listing import (
    may_name_a_link,
    mdtm_seconds,
    names_a_link,
    parse_list_line,
    parse_mlsx,
)


class FtpLookups:
    """The ftp transport's lookups on a logged-in connection, learning on first use which
    of MLSD and MLST the server has."""

    options: FtpOptions
    _has_mlsd: bool | None  # the transport's, None until the server has been asked
    _has_mlst: bool | None

    def _list(self, ftp: ftplib.FTP, full: str, path: str) -> list[Entry]:
        """A folder's entries as the server lists them, temporary files too; MLSD or LIST."""
        if self._has_mlsd is not False:
            try:
                lines = self._lines(ftp, f"MLSD {full}", "list_dir", path)
                self._has_mlsd = True
                return self._followed(ftp, full, [(line, parse_mlsx(line)) for line in lines])
            except Unsupported:
                self._has_mlsd = False
        return self._list_legacy(ftp, full, path)

    def _holds_anything(self, ftp: ftplib.FTP, full: str, path: str) -> bool:
        """Whether a folder lists any entry, dot files too where the server shows them."""
        if self._list(ftp, full, path):
            return True
        with contextlib.suppress(Permanent):
            return bool(self._list_dot_files(ftp, full, path))
        return False

    def _list_all(self, ftp: ftplib.FTP, full: str, path: str) -> list[Entry]:
        """A folder's entries, dot files too where the server shows them: MLSD does, and
        vsftpd's and ProFTPD's LIST with `-a` (without, theirs leave them out)."""
        if self._has_mlsd is not False:
            entries = self._list(ftp, full, path)
            if self._has_mlsd:
                return entries
        try:
            return self._list_dot_files(ftp, full, path)
        except Permanent:
            return self._list(ftp, full, path)

    def _list_dot_files(self, ftp: ftplib.FTP, full: str, path: str) -> list[Entry]:
        """`LIST -a`: `-a` is vsftpd's and ProFTPD's, not everyone's (Permanent then)."""
        lines = self._lines(ftp, f"LIST -a {full}", "list_dir", path)
        return [e for e in map(parse_list_line, lines)
                if e is not None and e.name not in (".", "..")]

    def _lines(self, ftp: ftplib.FTP, command: str, op: str, path: str) -> list[str]:
        """A listing command's data, as lines in the server's encoding."""
        deadline = Deadline(self.options.transfer_timeout_s)
        with translated(op, path):
            conn = ftp.transfercmd(command)
            with conn:
                data = bytearray()
                while block := conn.recv(CHUNK_BYTES):
                    deadline.check(f"{op} {path!r}")
                    data += block
                finish(ftp, conn)
        # surrogateescape: a name the encoding cannot take still lists, and gives BadPath later
        text = bytes(data).decode(self.options.encoding, "surrogateescape")
        return [line for line in text.splitlines() if line.strip()]

    def _list_legacy(self, ftp: ftplib.FTP, full: str, path: str) -> list[Entry]:
        """LIST parsed (Unix or DOS style); NLST and CWD probes if the format is unknown."""
        self._require_dir(ftp, full, path)  # LIST of a missing folder may just be empty
        lines = self._lines(ftp, f"LIST {full}", "list_dir", path)
        parsed = [(line, parse_list_line(line)) for line in lines
                  if not line.startswith("total ")]
        if all(e is not None for _, e in parsed):
            return [e for e in self._followed(ftp, full, parsed) if e.name not in (".", "..")]
        names = {posixpath.basename(n) for n in self._lines(ftp, f"NLST {full}", "list_dir", path)}
        return [Entry(n, self._is_dir(ftp, posixpath.join(full, n))) for n in sorted(names)
                if n not in (".", "..")]

    def _stat(self, ftp: ftplib.FTP, full: str, path: str) -> Entry:
        name = posixpath.basename(full)
        if self._has_mlst is not False:
            try:
                with translated("stat", path):
                    reply = ftp.sendcmd(f"MLST {full}")
                self._has_mlst = True
                facts = reply.splitlines()[1].strip() if "\n" in reply else ""
                line = f"{facts.partition(' ')[0]} {name}"
                entry = parse_mlsx(line)
                if entry is None:
                    raise NotFound(path)
                if entry.is_dir or not may_name_a_link(line):
                    return entry
            except Unsupported:
                self._has_mlst = False
        return self._stat_followed(ftp, full, path)  # no MLST, or a link's own facts in it

    def _stat_followed(self, ftp: ftplib.FTP, full: str, path: str) -> Entry:
        """SIZE, MDTM or CWD's answer: about what a link leads to, not the link."""
        name = posixpath.basename(full)
        try:
            with translated("stat", path):
                size = size_of(ftp.size, full)
        except NotFound:
            if self._is_dir(ftp, full):
                return Entry(name, True)
            raise
        mtime = None
        with contextlib.suppress(Permanent), translated("stat", path):
            mtime = mdtm_seconds(ftp.sendcmd(f"MDTM {full}")[4:].strip())
        return Entry(name, False, size, mtime)

    def _followed(self, ftp: ftplib.FTP, full: str,
                  parsed: list[tuple[str, Entry | None]]) -> list[Entry]:
        """The entries a folder's listing lines give, a link's as what it leads to; a link
        that leads nowhere is left out, since there is nothing there to read."""
        entries = []
        for line, entry in parsed:
            if entry is not None and names_a_link(line):
                target = posixpath.join(full, entry.name)
                try:
                    entry = self._stat_followed(ftp, target, target)
                except NotFound:
                    continue
            if entry is not None:
                entries.append(entry)
        return entries

    def _exists(self, ftp: ftplib.FTP, full: str, path: str) -> bool:
        try:
            self._stat(ftp, full, path)
        except NotFound:
            return False
        return True

    def _is_dir(self, ftp: ftplib.FTP, full: str) -> bool:
        try:
            with translated("stat", full):
                ftp.cwd(full)
        except NotFound:
            return False
        return True

    def _require_dir(self, ftp: ftplib.FTP, full: str, path: str) -> None:
        if not self._is_dir(ftp, full):
            raise NotFound(path)


def size_of(size: Callable[[str], int | None], full: str) -> int | None:
    """SIZE's answer, or None when the server's answer is not a count of bytes."""
    try:
        return byte_count(size(full))
    except ValueError:  # "213 abc"
        return None
