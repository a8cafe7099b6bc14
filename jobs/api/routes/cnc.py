"""The contract's single-machine file API, section 2.6: `/api/cnc/...`.

Routes parse the contract's parameters, open the machine through `jobs.fleet.registry`
and call one operation of `MachineFiles`; errors come back as the contract's JSON.
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import io
import tempfile
from collections.abc import Iterator
from typing import Annotated, Any

from fastapi import APIRouter, Body, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse
from pydantic import BaseModel, ConfigDict, Field, model_validator
from starlette.background import BackgroundTask

from jobs.api.deps import SessionDep, SettingsDep, requires
from jobs.api.errors import cut_short
from jobs.api.readahead import ReadAhead
from jobs.api.text import CheckedRoute
from jobs.auth.roles import Role
from jobs.errors import SUCCESS, ContractError, ErrorCode, result
from jobs.fleet import door, registry
from jobs.fleet.file_bytes import as_json_content
from jobs.fleet.paths import MissingParameter, bad
from jobs.fleet.rules import FANUC_HEAD_BYTES
from jobs.run.slot import machine_slot, opened
from jobs.service import own_spelling
from jobs.settings import Settings

router = APIRouter(prefix="/api/cnc", tags=["cnc (gateway contract 2.6)"],
                   route_class=CheckedRoute)

MachineID = Annotated[str, Query(alias="machineID", description="Target machine (required)")]
FileName = Annotated[str | None, Query(alias="fileName", description="File name, not a path")]
DirAtCNC = Annotated[
    str | None, Query(alias="dirAtCNC", description="Folder; default: the machine's root")
]
SubDir = Annotated[
    str | None, Query(alias="subDir", description="Folder below the root; ignored with dirAtCNC")
]
Force = Annotated[bool, Query(description="Go ahead even if the file is the running program")]

Result = dict[str, Any]
# The contract's GETs that change a machine: recorded in the audit trail as POSTs are.
CHANGING_GETS = frozenset(f"/api/cnc/{name}" for name in (
    "deleteFile", "lockFileByRange", "createDir", "deleteDir", "selectProgram"))
RESULT_EXAMPLE = {"errorCode": 0, "errorMsg": "Success"}
# Base64 broken into lines (MIME, the base64 tool, Python's encodebytes) is Base64 still.
_BASE64_SPACES = str.maketrans("", "", " \t\r\n")


class Listing(BaseModel):
    """2.6.1 / 2.6.16: one folder's programs and subfolders."""

    dirAtCNC: str
    programs: list[str]
    subDirs: list[str]


class FileContent(BaseModel):
    """2.6.3 / 2.6.6 body: text as `content`+`encoding`, binary as `base64`."""

    model_config = ConfigDict(extra="allow")

    content: str | None = None
    encoding: str | None = None
    base64: str | None = Field(default=None, description="Ignored when content is given")

    @model_validator(mode="before")
    @classmethod
    def _any_case(cls, data: Any) -> Any:
        """The fields in any case (`Content`, `Targets`), as a batch's targets take theirs."""
        return own_spelling(data, cls.model_fields) if isinstance(data, dict) else data


def content_bytes(body: FileContent, default_encoding: str) -> bytes:
    """The file a JSON body carries: `content` wins over `base64` (2.6.6)."""
    if body.content is not None:
        encoding = body.encoding or default_encoding
        try:
            return body.content.encode(encoding)
        except LookupError:
            raise bad(f"unknown encoding {encoding!r}") from None
        except UnicodeEncodeError:
            raise bad(f"content cannot be written in {encoding}") from None
        except ValueError as exc:  # a codec's own refusal (idna's labels), a NUL in the name
            raise bad(f"content cannot be written in {encoding!r}: {exc}") from None
    if body.base64 is not None:
        try:
            return base64.b64decode(body.base64.translate(_BASE64_SPACES), validate=True)
        except (binascii.Error, ValueError):
            raise bad("base64 is not valid Base64") from None
    raise MissingParameter("content (text) or base64 (binary)")


@router.get("/readProgramList", response_model=Listing, summary="2.6.1 List one folder",
            dependencies=[requires(Role.VIEWER)])
def read_program_list(session: SessionDep, settings: SettingsDep, machine_id: MachineID,
                      dir_at_cnc: DirAtCNC = None, sub_dir: SubDir = None) -> Result:
    with opened(session, settings, machine_id, reading=True) as files:
        return files.list_program_dir(dir_at_cnc, sub_dir)


@router.get(
    "/receiveFileStream",
    summary="2.6.2 Read a file as a stream (any size)",
    response_class=StreamingResponse,
    responses={200: {"content": {"application/octet-stream": {}}}},
    dependencies=[requires(Role.VIEWER)],
)
def receive_file_stream(session: SessionDep, settings: SettingsDep, machine_id: MachineID,
                        file_name: FileName = None, dir_at_cnc: DirAtCNC = None,
                        sub_dir: SubDir = None) -> StreamingResponse:
    spec = registry.get(session=session, machine_id=machine_id)
    session.commit()
    held = contextlib.ExitStack()  # closed when the machine's last byte is read, or on error
    try:
        held.enter_context(machine_slot(settings, spec, reading=True))
        files = held.enter_context(door.open_files(spec, data_dir=settings.data_dir))
        ref = files.ref(file_name, dir_at_cnc, sub_dir)
        entry = files.stat(ref)
        chunks = files.open(ref)
        ahead = ReadAhead(settings.data_dir / "spool")
    except BaseException:
        held.close()
        raise
    ahead.start(chunks, release=held.close)  # the slot goes back at the machine's pace
    headers = {"Content-Disposition": f"attachment; filename*=UTF-8''{_quote(ref.name)}"}
    body = ahead.stream()
    if entry.size is not None:  # a byte count (worker.transports.base.Entry keeps no other)
        headers["Content-Length"] = str(entry.size)
        body = _exactly(body, entry.size, ref.name)
    body = cut_short(body, f"download of {ref.name} from machine {machine_id}")
    return StreamingResponse(body, media_type="application/octet-stream",
                             headers=headers, background=BackgroundTask(ahead.stop))


def _exactly(chunks: Iterator[bytes], size: int, name: str) -> Iterator[bytes]:
    """The chunks, as long as they add up to the `size` the machine gave for the file.

    The last byte goes out only once the file ended right there: a file longer than its
    size (it grew, or the server's size was wrong) is cut off one byte short, so that the
    client sees an incomplete download rather than a whole-looking wrong file.
    """
    sent, last = 0, b""
    for chunk in chunks:
        data = last + chunk
        if sent + len(data) > size:
            raise ContractError(ErrorCode.CONNECTION_FAILED,
                                f"{name} is longer than the {size} bytes its machine gave")
        cut = len(data) - (1 if data and sent + len(data) == size else 0)
        if cut:
            yield data[:cut]
        sent, last = sent + cut, data[cut:]
    if sent + len(last) < size:
        raise ContractError(ErrorCode.CONNECTION_FAILED,
                            f"{name} ended after {sent + len(last)} of {size} bytes")
    if last:
        yield last


def _quote(name: str) -> str:
    from urllib.parse import quote

    return quote(name, safe="")


@router.get("/receiveFile", summary="2.6.3 Read a file as JSON (up to 10 MB)",
            dependencies=[requires(Role.VIEWER)])
def receive_file(session: SessionDep, settings: SettingsDep, machine_id: MachineID,
                 file_name: FileName = None, dir_at_cnc: DirAtCNC = None,
                 sub_dir: SubDir = None) -> Result:
    with opened(session, settings, machine_id, reading=True) as files:
        ref = files.ref(file_name, dir_at_cnc, sub_dir)
        data = files.read_bytes(ref, max_bytes=settings.max_receive_file_bytes)
        return as_json_content(data, encoding=files.encoding)


@router.get("/readCurrentProgram", summary="2.6.4 Read the running program",
            dependencies=[requires(Role.VIEWER)])
def read_current_program(session: SessionDep, settings: SettingsDep, machine_id: MachineID,
                         dir_at_cnc: DirAtCNC = None, sub_dir: SubDir = None) -> Result:
    with opened(session, settings, machine_id, reading=True) as files:
        # Checked as every endpoint checks them (a path out of the root is refused); the
        # answer is the running program, wherever it is: a control runs one at a time.
        files.paths.resolve(dir_at_cnc, sub_dir)
        ref = files.current_program()
        if ref is None:
            return result(ErrorCode.PATH_NOT_FOUND, "No content.")
        data = files.read_bytes(ref, max_bytes=settings.max_receive_file_bytes)
        return {
            "dirAtCNC": files.paths.display(ref.place),
            "fileName": files.paths.listed_name(ref.name),
            **as_json_content(data, encoding=files.encoding),
        }


@router.post(
    "/sendFileStream",
    summary="2.6.5 Send a file as the raw body (any size)",
    openapi_extra={"requestBody": {"content": {"application/octet-stream": {}},
                                   "required": True}},
    dependencies=[requires(Role.OPERATOR, scoped=True, action="cnc.sendFileStream")],
)
async def send_file_stream(request: Request, session: SessionDep, settings: SettingsDep,
                           machine_id: MachineID, file_name: FileName = None,
                           dir_at_cnc: DirAtCNC = None, sub_dir: SubDir = None) -> Result:
    spec = await run_in_threadpool(registry.get, session=session, machine_id=machine_id)
    spool = await _spool(request, settings)
    try:
        return await run_in_threadpool(_send_spooled, spec, settings, spool, file_name,
                                       dir_at_cnc, sub_dir)
    finally:
        spool.close()


async def _spool(request: Request, settings: Settings) -> Any:
    """The request body in a temporary file of the data folder: constant memory, any size."""
    spool_dir = settings.data_dir / "spool"
    spool_dir.mkdir(parents=True, exist_ok=True)
    spool = tempfile.TemporaryFile(dir=spool_dir)
    try:
        async for chunk in request.stream():
            spool.write(chunk)
    except BaseException:
        spool.close()
        raise
    spool.seek(0)
    return spool


def _send_spooled(spec: registry.MachineSpec, settings: Settings, spool: Any,
                  file_name: str | None, dir_at_cnc: str | None, sub_dir: str | None) -> Result:
    with machine_slot(settings, spec), door.open_files(
            spec, data_dir=settings.data_dir) as files:
        head = spool.read(FANUC_HEAD_BYTES)
        spool.seek(0)
        ref = files.send_ref(file_name, dir_at_cnc, sub_dir, head)
        files.send(ref, spool)
    return SUCCESS


@router.post("/sendFile", summary="2.6.6 Send a file as JSON (up to 10 MB)",
             dependencies=[requires(Role.OPERATOR, scoped=True, action="cnc.sendFile")])
def send_file(session: SessionDep, settings: SettingsDep, machine_id: MachineID,
              body: Annotated[FileContent, Body()], file_name: FileName = None,
              dir_at_cnc: DirAtCNC = None, sub_dir: SubDir = None) -> Result:
    with opened(session, settings, machine_id) as files:
        data = content_bytes(body, files.encoding)
        if len(data) > settings.max_send_file_bytes:  # 2.6.6: not for files over 10 MB
            raise ContractError(ErrorCode.FILE_TOO_LARGE, f"{len(data)} bytes; sendFile takes "
                                f"up to {settings.max_send_file_bytes}: use sendFileStream")
        ref = files.send_ref(file_name, dir_at_cnc, sub_dir, data[:FANUC_HEAD_BYTES])
        files.send(ref, io.BytesIO(data))
    return SUCCESS


@router.get("/deleteFile", summary="2.6.8 Delete a file",
            dependencies=[requires(Role.OPERATOR, scoped=True, action="cnc.deleteFile")])
def delete_file(session: SessionDep, settings: SettingsDep, machine_id: MachineID,
                file_name: FileName = None, dir_at_cnc: DirAtCNC = None, sub_dir: SubDir = None,
                force: Force = False) -> Result:
    with opened(session, settings, machine_id) as files:
        files.delete(files.ref(file_name, dir_at_cnc, sub_dir), force=force)
    return SUCCESS


@router.get("/lockFileByRange", summary="2.6.10 Lock or unlock a program range",
            dependencies=[requires(Role.OPERATOR, scoped=True, action="cnc.lockFileByRange")])
def lock_file_by_range(
    session: SessionDep, settings: SettingsDep, machine_id: MachineID,
    is_lock: Annotated[bool, Query(alias="isLock")],
    lock_start: Annotated[int, Query(alias="lockStart")],
    lock_end: Annotated[int, Query(alias="lockEnd")],
) -> Result:
    with opened(session, settings, machine_id) as files:
        files.lock_range(is_lock=is_lock, start=lock_start, end=lock_end)
    return SUCCESS


DirName = Annotated[str | None, Query(alias="dirName", description="Folder to create or delete")]


@router.get("/createDir", summary="2.6.11 Create a folder",
            dependencies=[requires(Role.OPERATOR, scoped=True, action="cnc.createDir")])
def create_dir(session: SessionDep, settings: SettingsDep, machine_id: MachineID,
               dir_name: DirName = None, dir_at_cnc: DirAtCNC = None,
               sub_dir: SubDir = None) -> Result:
    with opened(session, settings, machine_id) as files:
        files.make_dir(dir_name, dir_at_cnc, sub_dir)
    return SUCCESS


@router.get("/deleteDir", summary="2.6.12 Delete an empty folder",
            dependencies=[requires(Role.OPERATOR, scoped=True, action="cnc.deleteDir")])
def delete_dir(session: SessionDep, settings: SettingsDep, machine_id: MachineID,
               dir_name: DirName = None, dir_at_cnc: DirAtCNC = None,
               sub_dir: SubDir = None) -> Result:
    with opened(session, settings, machine_id) as files:
        files.remove_dir(dir_name, dir_at_cnc, sub_dir)
    return SUCCESS


@router.get("/selectProgram", summary="2.6.14 Select the main program",
            dependencies=[requires(Role.OPERATOR, scoped=True, action="cnc.selectProgram")])
def select_program(session: SessionDep, settings: SettingsDep, machine_id: MachineID,
                   file_name: FileName = None, dir_at_cnc: DirAtCNC = None,
                   sub_dir: SubDir = None) -> Result:
    with opened(session, settings, machine_id) as files:
        files.select_program(files.ref(file_name, dir_at_cnc, sub_dir))
    return SUCCESS


@router.get("/readAllPrograms", summary="2.6.15 List every file below a folder",
            dependencies=[requires(Role.VIEWER)])
def read_all_programs(session: SessionDep, settings: SettingsDep, machine_id: MachineID,
                      dir_at_cnc: DirAtCNC = None, sub_dir: SubDir = None) -> Result:
    with opened(session, settings, machine_id, reading=True) as files:
        return files.read_all(dir_at_cnc, sub_dir)


@router.get("/searchFile", response_model=Listing, summary="2.6.16 Find a file below a folder",
            dependencies=[requires(Role.VIEWER)])
def search_file(session: SessionDep, settings: SettingsDep, machine_id: MachineID,
                file_name: FileName = None, dir_at_cnc: DirAtCNC = None,
                sub_dir: SubDir = None) -> Result:
    with opened(session, settings, machine_id, reading=True) as files:
        return files.search(file_name, dir_at_cnc, sub_dir)
