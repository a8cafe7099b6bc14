"""Where dncq keeps stored backups under its data folder, and a backup job's work folder.

On the ground floor because the job, the runners, the reaper and the schedules all need
them, not only the backup package.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from collections.abc import Iterator
from pathlib import Path

from jobs.settings import Settings


def backup_dir(settings: Settings) -> Path:
    """Where stored backups live."""
    return settings.data_dir / "backups"


def work_dir(settings: Settings) -> Path:
    """Where backup jobs' work folders live, one per job named by its id."""
    return backup_dir(settings) / ".work"


def job_folder(settings: Settings, job_id: str) -> Path:
    """The job's work folder: made with the job, removed once its ZIP is registered.

    While it exists the job owes a ZIP; a job whose backup retention has since deleted
    has none, so the reaper does not assemble it again.
    """
    return work_dir(settings) / job_id


ASSEMBLING = ".assembling-"  # a ZIP being written: its process, then the archive's name


def being_assembled(settings: Settings, job_id: str, *, besides: str = "") -> bool:
    """Whether an assembly of the job writes its ZIP (other than the one whose part is named
    `besides`): its part's writer a live process of this host, or one of another host that
    wrote to it lately (worker.transports.parts). A folder that cannot be read shows none."""
    # Here, not at the top: every `dncq` command loads this module, and the transports'
    # package loads them all (commands that only ask the API start without them).
    from worker.transports import parts

    try:
        return parts.others_writing(backup_dir(settings), ASSEMBLING, f"-{job_id}-",
                                    besides=besides)
    except OSError:
        return False


@contextlib.contextmanager
def sending(folder: Path) -> Iterator[None]:
    """Mark a streamed backup job's work folder as read by its download while this lasts
    (`being_sent`): a lock, which goes with its process however that ends. A folder that
    could not be made holds nothing to keep."""
    try:
        lock = open(folder / SENDING, "a", opener=private_opener)
    except OSError:
        yield
        return
    with lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def being_sent(folder: Path) -> bool:
    """Whether a download still reads the work folder (`sending`), in any process of this
    host, or of another where the folder is shared and its file system passes locks on."""
    try:
        fd = os.open(folder / SENDING, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False


SENDING = ".sending"  # in a streamed backup job's work folder while its ZIP is sent


def private_dir(folder: Path) -> Path:
    """`folder` (and missing parents) made 0700; an existing one of ours tightened to 0700.

    The data folder holds the database, the API key, the secrets key and backups: nobody
    else on the host reads what is in it.
    """
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    status = folder.stat()
    if status.st_uid == os.getuid() and status.st_mode & 0o077:
        folder.chmod(0o700)
    return folder


def private_file(path: Path) -> Path:
    """`path` created empty and 0600 when missing (so what opens it later keeps that mode)."""
    with contextlib.suppress(FileExistsError):
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    return path


def private_opener(path: str, flags: int) -> int:
    """`open(..., opener=private_opener)`: a file it creates is 0600."""
    return os.open(path, flags, 0o600)
