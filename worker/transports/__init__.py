"""Transports by name: how a machine's files are reached.

Each transport is a module with one class and its options model; this registry
is the only place that knows them all.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import SecretStr

from worker.transports.base import Transport, TransportOptions
from worker.transports.dnc import DncOptions, DncTransport
from worker.transports.ftp import FtpOptions, FtpTransport
from worker.transports.gateway import GatewayOptions, GatewayTransport
from worker.transports.mock import MockOptions, MockTransport, machine_folder
from worker.transports.moonraker import MoonrakerOptions, MoonrakerTransport
from worker.transports.octoprint import OctoPrintOptions, OctoPrintTransport
from worker.transports.serial_line import SerialOptions, SerialTransport
from worker.transports.share import ShareTransport
from worker.transports.share_options import ShareOptions


@dataclass(frozen=True)
class TransportKind:
    """A registered transport: its class and its options model."""

    cls: Any  # a Transport class: Protocol classes do not type-check as type[Transport]
    options_model: type[TransportOptions]


REGISTRY: dict[str, TransportKind] = {
    "mock": TransportKind(MockTransport, MockOptions),
    "ftp": TransportKind(FtpTransport, FtpOptions),
    "gateway": TransportKind(GatewayTransport, GatewayOptions),
    "share": TransportKind(ShareTransport, ShareOptions),
    "octoprint": TransportKind(OctoPrintTransport, OctoPrintOptions),
    "moonraker": TransportKind(MoonrakerTransport, MoonrakerOptions),
    "serial": TransportKind(SerialTransport, SerialOptions),
    "dnc": TransportKind(DncTransport, DncOptions),
}

PLANNED: tuple[str, ...] = ()
"""Names reserved for transports not available in this version."""


class UnknownTransport(ValueError):
    """No transport of that name is available."""


def kind(name: str) -> TransportKind:
    """The registered transport called `name`."""
    try:
        return REGISTRY[name]
    except KeyError:
        hint = " (not available in this version)" if name in PLANNED else ""
        raise UnknownTransport(
            f"unknown transport {name!r}{hint}; available: {', '.join(REGISTRY)}"
        ) from None


def validate_options(name: str, options: dict[str, Any]) -> TransportOptions:
    """Check a machine's transport options against the transport's model."""
    return kind(name).options_model.model_validate(options)


def secret_fields(name: str) -> set[str]:
    """Option names that hold secrets for this transport."""
    model = kind(name).options_model
    return {f for f, info in model.model_fields.items() if info.annotation in _SECRET_TYPES}


_SECRET_TYPES = (SecretStr, SecretStr | None)


def open_transport(
    name: str,
    options: dict[str, Any],
    *,
    machine_id: str,
    data_dir: Path,
    storage_roots: tuple[str, ...] = (),
) -> Transport:
    """A transport for one machine; a mock and a DNC link also get the storage roots its
    model has, a serial line its state folder."""
    validated = validate_options(name, options)
    if isinstance(validated, MockOptions):
        folder = machine_folder(data_dir / "mock", validated.folder or machine_id)
        return MockTransport(validated, folder=folder, roots=storage_roots)
    if isinstance(validated, DncOptions):
        return DncTransport(validated, roots=storage_roots)
    if isinstance(validated, SerialOptions):  # what dncq holds for the machine lives here
        return SerialTransport(validated, folder=machine_folder(data_dir / "serial", machine_id),
                               roots=storage_roots)
    return kind(name).cls(validated)  # type: ignore[no-any-return]
