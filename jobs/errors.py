"""The API's error codes: the contract's own and dncq's, one table, stable; and the HTTP
status a refusal of dncq's own resources is answered with, by the API and in the audit
trail of the dashboard alike.

docs/errors.md is this table in prose; a test keeps the two in step.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Sequence
from enum import IntEnum
from typing import Any

from worker.transports import base as t


class ErrorCode(IntEnum):
    """`errorCode` values. Never renumber: clients match on them."""

    SUCCESS = 0
    PATH_EXISTS = 142  # contract: a file of that name is already there
    PATH_NOT_FOUND = 158  # contract: no such file or folder (or, 2.6.4, nothing running)
    MACHINE_NOT_FOUND = 10003  # contract: unknown machineID
    BAD_PARAMETER = 20001  # missing, malformed or unsafe parameter
    PATH_OUTSIDE_ROOT = 20002  # a path that leaves the machine's allowed roots
    UNSUPPORTED = 20003  # this controller model or transport cannot do that
    MACHINE_OFFLINE = 20004
    MACHINE_TIMEOUT = 20005
    CONNECTION_FAILED = 20006  # refused, unreachable or dropped
    MACHINE_BUSY = 20007  # the machine's concurrency limit was not freed in time
    PROGRAM_RUNNING = 20008  # deleting or replacing the running program without force
    DIR_NOT_EMPTY = 20009
    PERMISSION_DENIED = 20010
    MACHINE_DISABLED = 20011
    FILE_TOO_LARGE = 20012  # receiveFile (JSON) is for files up to 10 MB; replace keeps 32 MB
    BODY_TOO_LARGE = 20013  # request body over the configured limit (HTTP 413)
    STILL_RUNNING = 20014  # batch answer came before this target finished
    CANCELLED = 20015  # target cancelled before it started
    VERIFY_MISMATCH = 20016  # bytes read back differ from those sent
    INTERNAL_ERROR = 20017
    AUTH_MISSING = 20401  # HTTP 401
    AUTH_INVALID = 20403  # HTTP 403; 401 for a revoked named key
    ROLE_REFUSED = 20406  # HTTP 403: the key or user is known; its role or machines do not allow it
    DECIDED_ALREADY = 20409  # HTTP 409: a library version or inbox item decided by another first
    KEYS_LOCKED_OUT = 20429  # HTTP 429: too many wrong keys came from the client's address


MESSAGES: dict[ErrorCode, str] = {
    ErrorCode.SUCCESS: "Success",
    ErrorCode.PATH_EXISTS: "Path exists.",
    ErrorCode.PATH_NOT_FOUND: "Path is not found.",
    ErrorCode.MACHINE_NOT_FOUND: "Machine ID does not exist.",
    ErrorCode.BAD_PARAMETER: "Bad parameter.",
    ErrorCode.PATH_OUTSIDE_ROOT: "Path is outside the machine's root.",
    ErrorCode.UNSUPPORTED: "Not supported by this machine.",
    ErrorCode.MACHINE_OFFLINE: "Machine is offline.",
    ErrorCode.MACHINE_TIMEOUT: "Machine did not answer in time.",
    ErrorCode.CONNECTION_FAILED: "Connection to the machine failed.",
    ErrorCode.MACHINE_BUSY: "Machine is busy.",
    ErrorCode.PROGRAM_RUNNING: "Program is running on the machine.",
    ErrorCode.DIR_NOT_EMPTY: "Directory is not empty.",
    ErrorCode.PERMISSION_DENIED: "Permission denied by the machine.",
    ErrorCode.MACHINE_DISABLED: "Machine is disabled.",
    ErrorCode.FILE_TOO_LARGE: "File is too large for this endpoint.",
    ErrorCode.BODY_TOO_LARGE: "Request body is too large.",
    ErrorCode.STILL_RUNNING: "Still running.",
    ErrorCode.CANCELLED: "Cancelled.",
    ErrorCode.VERIFY_MISMATCH: "File read back differs from the file sent.",
    ErrorCode.INTERNAL_ERROR: "Internal error.",
    ErrorCode.AUTH_MISSING: "API key is missing.",
    ErrorCode.AUTH_INVALID: "API key is not valid.",
    ErrorCode.ROLE_REFUSED: "Not allowed for this role.",
    ErrorCode.DECIDED_ALREADY: "Already decided.",
    ErrorCode.KEYS_LOCKED_OUT: "Too many wrong API keys.",
}

TRANSIENT_CODES = frozenset(
    {
        ErrorCode.MACHINE_OFFLINE,
        ErrorCode.MACHINE_TIMEOUT,
        ErrorCode.CONNECTION_FAILED,
        ErrorCode.MACHINE_BUSY,
    }
)
"""Codes worth retrying; every other failure is permanent."""


class ContractError(Exception):
    """A failure answered with the contract's `errorCode`/`errorMsg`/`statusMsg`."""

    def __init__(self, code: ErrorCode, status_msg: str | None = None, *,
                 transient: bool | None = None) -> None:
        """`transient`: worth another attempt; by default, whether `code` is one of
        TRANSIENT_CODES (an internal error can be transient: the database was lost)."""
        if status_msg:  # text that is not Unicode (a lone surrogate) escaped: storable, sayable
            status_msg = status_msg.encode("utf-8", "backslashreplace").decode("utf-8")
        super().__init__(f"{int(code)} {MESSAGES[code]} {status_msg or ''}".strip())
        self.code = code
        self.status_msg = status_msg
        self.transient = code in TRANSIENT_CODES if transient is None else transient

    def body(self) -> dict[str, Any]:
        """The JSON body the contract gives for this error."""
        return result(self.code, self.status_msg)


NOT_FOUND_CODES = frozenset({ErrorCode.PATH_NOT_FOUND, ErrorCode.MACHINE_NOT_FOUND})

_LIBRARY_STATUS = {ErrorCode.PATH_NOT_FOUND: 404, ErrorCode.MACHINE_NOT_FOUND: 404,
                   ErrorCode.BAD_PARAMETER: 400, ErrorCode.FILE_TOO_LARGE: 413}


def resource_status(refusal: ContractError) -> int:
    """The HTTP status of a refusal of dncq's own resources (machines, jobs, backups,
    schedules, users): 404 for one that does not exist, 409 for a request it cannot take."""
    return 404 if refusal.code in NOT_FOUND_CODES else 409


def library_status(refusal: ContractError) -> int:
    """The HTTP status of a refusal of the program library (and of a file sent to a
    machine): 404 for a missing program, version or machine, 400 for a bad name or
    reference, 413 for content too large for the operation, 409 for anything else."""
    return _LIBRARY_STATUS.get(refusal.code, 409)


def unknown_machine(machine_id: str, known: Iterable[str] = ()) -> ContractError:
    """The contract's 10003 for a machine id nobody registered (or that was removed),
    naming the one of the `known` ids it was likely typed for."""
    return ContractError(ErrorCode.MACHINE_NOT_FOUND,
                         f"Invalid MachineID ({machine_id}){hint(machine_id, known)}")


def hint(name: str, known: Iterable[str]) -> str:
    """` (did you mean 1001?)`, naming the known name `name` was likely typed for; empty
    when none is."""
    return f" (did you mean {close}?)" if (close := meant(name, list(known))) else ""


def meant(name: str, known: list[str]) -> str | None:
    """The known name `name` was likely typed for, or None: one that reads the same but for
    look-alikes and case first (1O1O for 1010), then one a character off (1x01 for 1001),
    then the closest difflib finds (difflib rates 1016 as close as 1001 for 1O01 and, on a
    tie, names the greater)."""
    folded = _folded(name)
    if same := [k for k in known if k != name and _folded(k) == folded]:
        return same[0]
    close = difflib.get_close_matches(name, known, n=max(len(known), 1), cutoff=0.6)
    one_off = [c for c in close if len(c) == len(name)
               and sum(a != b for a, b in zip(c, name, strict=True)) == 1]
    return (one_off or close)[0] if close else None


def _folded(name: str) -> str:
    """`name` with the characters typed for one another made one (O and 0; I, l and 1)."""
    return name.upper().translate(_LOOK_ALIKE)


_LOOK_ALIKE = str.maketrans("OIL", "011")


def disabled_machine(machine_id: str) -> ContractError:
    """20011 for a machine switched off in the registry."""
    return ContractError(ErrorCode.MACHINE_DISABLED, f"machine {machine_id} is disabled")


def first_named(names: Sequence[str], limit: int) -> str:
    """`a, b, c and 7 more`: the first `limit` names, and how many more there are."""
    more = len(names) - limit
    return ", ".join(names[:limit]) + (f" and {more} more" if more > 0 else "")


def validation_summary(errors: Sequence[Any], *, under: str = "", whole: str = "body") -> str:
    """pydantic's errors as one line, `where: what; ...` (no links, no input echoed).

    `under` prefixes every location; `whole` names an error about the input as a whole.
    """
    def where(loc: Sequence[Any]) -> str:
        parts = [under] * bool(under) + [str(p) for p in loc if p not in ("query", "body")]
        return ".".join(parts) or whole

    def said(e: Any) -> str:
        if e.get("type") == "json_invalid":  # its location is where the JSON breaks off
            return f"{whole}: {e['msg']} at character {e['loc'][-1]}"
        # a validator's own words, without pydantic's "Value error, " before them
        return f"{where(e['loc'])}: {e['msg'].removeprefix('Value error, ')}"

    return "; ".join(said(e) for e in errors)


def result(code: ErrorCode, status_msg: str | None = None) -> dict[str, Any]:
    """`{"errorCode", "errorMsg"[, "statusMsg"]}` for `code`."""
    body: dict[str, Any] = {"errorCode": int(code), "errorMsg": MESSAGES[code]}
    if status_msg:
        body["statusMsg"] = status_msg
    return body


SUCCESS = result(ErrorCode.SUCCESS)

_BY_TRANSPORT_ERROR: tuple[tuple[type[t.TransportError], ErrorCode], ...] = (
    (t.NotFound, ErrorCode.PATH_NOT_FOUND),
    (t.Exists, ErrorCode.PATH_EXISTS),
    (t.NotEmpty, ErrorCode.DIR_NOT_EMPTY),
    (t.Unsupported, ErrorCode.UNSUPPORTED),
    (t.PermissionDenied, ErrorCode.PERMISSION_DENIED),
    (t.BadPath, ErrorCode.BAD_PARAMETER),
    (t.Offline, ErrorCode.MACHINE_OFFLINE),
    (t.TimedOut, ErrorCode.MACHINE_TIMEOUT),
    (t.PunchedInstead, ErrorCode.MACHINE_TIMEOUT),  # it did not switch to receive
    (t.Busy, ErrorCode.MACHINE_BUSY),
    (t.ConnectFailed, ErrorCode.CONNECTION_FAILED),
    (t.Dropped, ErrorCode.CONNECTION_FAILED),
)


def from_transport(exc: t.TransportError) -> ContractError:
    """The contract error for a transport failure; a Permanent one is never transient."""
    for cls, code in _BY_TRANSPORT_ERROR:
        if isinstance(exc, cls):
            return ContractError(code, str(exc) or None)
    # Any other failure of a transport is its machine's answer that made no sense: 20006,
    # tried again unless the transport knows the same request will fail again (a mock
    # machine's options.json that is not JSON, a URL with no gateway API behind it).
    return ContractError(ErrorCode.CONNECTION_FAILED, str(exc) or None,
                         transient=not isinstance(exc, t.Permanent))
