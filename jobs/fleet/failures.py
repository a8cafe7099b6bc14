"""Transport failures as the contract's errors, mapped once, at the fleet's door: `mapped`.

Used by every operation of `MachineFiles` (jobs.fleet.rules) and by the registry's own
calls to a machine (jobs.fleet.registry).
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

from jobs.errors import ContractError, ErrorCode, from_transport
from worker.transports.base import TransportError

log = logging.getLogger(__name__)


@contextlib.contextmanager
def mapped(shown: tuple[str, str] | None = None) -> Iterator[None]:
    """Turn transport failures into the contract's errors, once, here.

    `shown` is (storage path, the same path in the controller's notation): the message names
    the path as the user writes it (`TNC:\\nc_prog\\part.nc`, not `TNC/nc_prog/part.nc`).

    A transport that trips over its machine's answer (JSON of the wrong shape, a number out
    of range) raises what Python raises; that is the machine's fault, not dncq's: 20006,
    with the traceback in the log.
    """
    try:
        yield
    except TransportError as exc:
        error = from_transport(exc)
        if shown and shown[1]:
            said = error.code in _ABOUT_THE_PATH
            error = ContractError(error.code, _naming(error.status_msg, *shown, say=said),
                                  transient=error.transient)
        raise error from exc
    except _UNREADABLE_ANSWER as exc:
        log.warning("a machine's answer could not be read", exc_info=True)
        raise ContractError(ErrorCode.CONNECTION_FAILED,
                            f"the machine's answer could not be read ({type(exc).__name__})"
                            ) from exc


# The failures that are about the path itself: their message names it if the transport's did not.
_ABOUT_THE_PATH = frozenset({ErrorCode.PATH_NOT_FOUND, ErrorCode.PATH_EXISTS,
                             ErrorCode.DIR_NOT_EMPTY, ErrorCode.PERMISSION_DENIED})


def _naming(message: str | None, storage: str, written: str, *, say: bool) -> str | None:
    """A transport's message with the path as the controller writes it; with `say`, the
    path added if the message did not name it (`No such file or directory (TNC:\\...)`)."""
    if message and storage and storage in message:
        return message.replace(storage, written)
    if not say or (message and written in message):
        return message
    return f"{message} ({written})" if message else written


_UNREADABLE_ANSWER = (ValueError, TypeError, KeyError, IndexError, AttributeError,
                      OverflowError)
