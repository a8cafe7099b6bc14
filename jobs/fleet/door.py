"""The one door to a machine's files: its model's path rules over its transport, opened with
its secrets unsealed and masked in every message, and what the machine can do through it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from jobs.errors import ContractError, ErrorCode, disabled_machine
from jobs.fleet import sealed
from jobs.fleet.failures import mapped
from jobs.fleet.paths import MachinePaths
from jobs.fleet.redact import Redacting, Redactor
from jobs.fleet.registry import MachineSpec, governing_row, secret_options
from jobs.fleet.rules import MachineFiles
from worker import transports


def paths_of(spec: MachineSpec) -> MachinePaths:
    """The machine's path rules: its model's roots, or only its root behind a file server."""
    confine = not transports.kind(spec.transport).cls.own_storage
    return MachinePaths(governing_row(spec), spec.root, confine=confine)


def open_files(spec: MachineSpec, *, data_dir: Path) -> MachineFiles:
    """The machine's files behind its model's rules: the one door every caller uses."""
    if not spec.enabled:
        raise disabled_machine(spec.id)
    paths = paths_of(spec)
    options, secrets = _unsealed(spec, data_dir)
    redactor = Redactor(secrets)
    with mapped():  # a transport may refuse already when it is made
        transport = redactor.call(
            transports.open_transport, spec.transport, options, machine_id=spec.id,
            data_dir=data_dir, storage_roots=tuple(r.storage for r in paths.roots),
        )
    return MachineFiles(Redacting(transport, redactor), paths, encoding=spec.encoding)


def secrets_of(spec: MachineSpec, data_dir: Path) -> list[str]:
    """The values of the machine's secrets, unsealed: what its messages must not show."""
    return _unsealed(spec, data_dir)[1]


def _unsealed(spec: MachineSpec, data_dir: Path) -> tuple[dict[str, Any], list[str]]:
    """The machine's options with its secrets unsealed, and those secrets' values."""
    options, secrets = dict(spec.options), []
    try:
        for key in secret_options(spec.transport, options):
            if sealed.is_sealed(options[key]):
                options[key] = sealed.keyring(data_dir, create=False).unseal(options[key])
            if isinstance(options[key], str):
                secrets.append(options[key])
    except sealed.SecretsKeyError as exc:
        raise ContractError(ErrorCode.INTERNAL_ERROR,
                            f"the secrets of machine {spec.id} cannot be read: {exc}") from None
    return options, secrets


def abilities(spec: MachineSpec) -> list[str]:
    """What the machine can do beyond files: its governing model's rules and its transport's
    reach together (a Fanuc behind FTP cannot lock ranges)."""
    row = governing_row(spec)
    caps = transports.kind(spec.transport).cls.capabilities
    return [what for what, able in (
        ("subfolders", row.list_subdirs and caps.folders),
        ("folders", (row.make_dirs or bool(row.make_dirs_roots)) and caps.make_dirs),
        ("select", row.select_program), ("lock", row.lock_range and caps.lock_range),
        ("current program", caps.current_program), ("drip-feed", caps.drip_feed)) if able]


def reads_held_copies(spec: MachineSpec) -> bool:
    """Whether listing and reading the machine's files read what dncq holds for it on this
    host (an RS-232 line's programs), not the machine: no operation on the machine."""
    return transports.kind(spec.transport).cls.capabilities.held_copies
