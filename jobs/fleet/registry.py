"""The machine registry: machines as given and as kept, and lookups (the one door to a
machine's files is jobs.fleet.door, a fleet file is read in jobs.fleet.fleet_file, a machine
checked in jobs.fleet.checks)."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, Field, field_validator
from sqlalchemy import delete as sa_delete
from sqlalchemy import select, text
from sqlalchemy.orm import InstrumentedAttribute, Session

from jobs.db import in_chunks, write_first
from jobs.errors import (
    ContractError,
    hint,
    unknown_machine,
)
from jobs.fleet import catalogue, request_settings, sealed
from jobs.fleet.paths import MachinePaths
from jobs.models import TAKES_REQUESTS, Machine
from worker import transports

T = TypeVar("T")

log = logging.getLogger(__name__)

SECRET_MASK = "**********"


class MachineIn(BaseModel):
    """A machine as a fleet file or the admin API gives it."""

    model_config = ConfigDict(extra="forbid")

    # Starts with a letter or digit: archive names beginning with "_" stay dncq's own.
    id: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
    name: str = Field(min_length=1, max_length=200)
    model: str
    transport: str = "mock"
    root: str | None = None
    encoding: str = "utf-8"
    max_concurrent: int = Field(default=1, ge=1, le=64)
    enabled: bool = True
    tags: list[str] = Field(default_factory=list)
    options: dict[str, Any] = Field(default_factory=dict)
    requests: dict[str, Any] | None = None
    """What the operator may ask from the control (`jobs.fleet.request_settings`), as given:
    the preset of the machine's controller fills in the rest."""
    governing_model: str | None = Field(default=None, exclude=True)
    """Shown by GET, ignored here: a machine read from the API can be put back as it is."""
    roots: list[str] | None = Field(default=None, exclude=True)  # shown by GET; ignored
    can: list[str] | None = Field(default=None, exclude=True)  # shown by GET; ignored

    @field_validator("id", mode="before")
    @classmethod
    def _id_as_text(cls, value: Any) -> Any:
        # YAML reads `id: 1010` as a number; machine IDs are strings.
        return str(value) if isinstance(value, int) else value

    @field_validator("model")
    @classmethod
    def _known_model(cls, value: str) -> str:
        catalogue.lookup(value)
        return value

    @field_validator("encoding")
    @classmethod
    def _known_encoding(cls, value: str) -> str:
        try:
            "".encode(value)
        except LookupError:
            raise ValueError(f"unknown encoding {value!r} (e.g. utf-8, cp1252)") from None
        return value

    def check(self) -> None:
        """Cross-field checks: options fit the transport and can work on this host, the root
        fits the model."""
        missing = transports.validate_options(self.transport, self.options).missing_package()
        if missing:
            raise ValueError(f"options: {missing}")
        if self.root:
            MachinePaths(governing_row(self), None, confine=False).parse(self.root)
        if self.requests is not None:
            request_settings.resolve(self.model, self.requests)


@dataclass(frozen=True)
class MachineSpec:
    """A machine as the data plane needs it: plain data, safe to hand to a task."""

    id: str
    name: str
    model: str
    transport: str
    root: str | None = None
    encoding: str = "utf-8"
    max_concurrent: int = 1
    enabled: bool = True
    tags: list[str] = field(default_factory=list)
    options: dict[str, Any] = field(default_factory=dict, repr=False)  # may hold secrets
    requests: dict[str, Any] | None = None  # as given; `request_settings()` fills it in

    @classmethod
    def of(cls, machine: Machine) -> MachineSpec:
        """The spec of a registry row."""
        return cls(
            id=machine.id, name=machine.name, model=machine.model, transport=machine.transport,
            root=machine.root, encoding=machine.encoding, max_concurrent=machine.max_concurrent,
            enabled=machine.enabled, tags=list(machine.tags), options=dict(machine.options),
            requests=dict(machine.requests) if machine.requests is not None else None,
        )

    def request_settings(self) -> request_settings.RequestSettings:
        """What the machine's operator may ask: its controller's preset with the machine's
        own settings over it (off unless they turn it on)."""
        return request_settings.resolve(self.model, self.requests)

    def public(self) -> dict[str, Any]:
        """The machine as the API and CLI show it: secrets masked."""
        known = self.transport in transports.REGISTRY
        secrets = transports.secret_fields(self.transport) if known else set()
        options = {k: (SECRET_MASK if k in secrets or _looks_secret(k) else v)
                   for k, v in self.options.items()}
        row = governing_row(self)
        return {
            "id": self.id, "name": self.name, "model": self.model, "transport": self.transport,
            "root": self.root or row.default_root, "encoding": self.encoding,
            "max_concurrent": self.max_concurrent, "enabled": self.enabled, "tags": self.tags,
            "options": options, "governing_model": row.name, "requests": self.requests,
        }


def _looks_secret(key: str) -> bool:
    return any(word in key.lower() for word in ("password", "secret", "token", "api_key", "apikey"))


def governing_row(spec: MachineSpec | MachineIn) -> catalogue.ModelRow:
    """The catalogue row whose rules apply: the controller's, or the file server's in front."""
    cls = transports.kind(spec.transport).cls
    if cls.own_storage or not cls.server_row:
        return catalogue.lookup(spec.model)
    return catalogue.lookup(cls.server_row)


def secret_options(transport: str, options: dict[str, Any]) -> list[str]:
    """The options that hold secrets: the transport's `SecretStr` fields that are set."""
    known = transports.secret_fields(transport) if transport in transports.REGISTRY else set()
    return [k for k in options if k in known or _looks_secret(k)]


# -- registry service ------------------------------------------------------


def get(*, session: Session, machine_id: str) -> MachineSpec:
    """The machine `machine_id`, or the contract's 10003."""
    machine = session.get(Machine, machine_id)
    if machine is None:
        raise _unknown(session, machine_id)
    return MachineSpec.of(machine)


def check_machine_filter(*, session: Session, machine_id: str | None,
                         held_by: InstrumentedAttribute[str], found: Sequence[Any]) -> None:
    """10003 for a list filtered by a machine (None: not filtered) that `found` nothing, a
    machine nobody registered that no row holds in `held_by` (a machine id column): a
    mistyped id (1O10), named with the id it was likely typed for. A machine removed since
    is known by its rows (its targets, runs, backups)."""
    if machine_id is None or found:
        return
    if session.scalar(select(held_by).where(held_by == machine_id).limit(1)) is None:
        get(session=session, machine_id=machine_id)


def _unknown(session: Session, machine_id: str) -> ContractError:
    """10003 for `machine_id`, naming a registered id it was likely typed for (1001 for 1O01)."""
    return unknown_machine(machine_id, hinted_ids(session=session))


def hints(*, session: Session, names: Sequence[str]) -> dict[str, str]:
    """" (did you mean 1010?)" for each of the first HINTED_NAMES `names` no machine has,
    empty where no registered id is close."""
    ids = hinted_ids(session=session) if names else []
    return {name: hint(name, ids) for name in names[:HINTED_NAMES]}


def hinted_ids(*, session: Session) -> list[str]:
    """The registered ids an unknown one is compared with to hint at the one it was typed
    for (`errors.meant`); none in a fleet over HINTED_FLEET (at 100,000 machines, looking
    cost up to 0.4 s a miss)."""
    known = session.scalars(select(Machine.id).limit(HINTED_FLEET + 1)).all()
    return list(known) if len(known) <= HINTED_FLEET else []


HINTED_FLEET = 10_000  # machines: a miss reads their ids and compares each (about 25 ms)
HINTED_NAMES = 20  # unknown ids hinted at in one request: each hint costs that much


def list_all(*, session: Session, tag: str | None = None) -> list[MachineSpec]:
    """Every machine, ordered by id; only those tagged `tag` when given."""
    rows = session.scalars(select(Machine).order_by(Machine.id)).all()
    specs = [MachineSpec.of(m) for m in rows]
    return [s for s in specs if tag is None or tag in s.tags]


def of_ids(*, session: Session, machine_ids: Iterable[str]) -> dict[str, MachineSpec]:
    """The registered machines among `machine_ids`, by id: what a request naming a few
    machines reads, however large the fleet (the whole of 100,000 took 3.3 s)."""
    found: dict[str, MachineSpec] = {}
    for chunk in in_chunks(sorted(set(machine_ids))):
        found.update((m.id, MachineSpec.of(m)) for m in session.scalars(
            select(Machine).where(Machine.id.in_(chunk))))
    return found


def column_of(*, session: Session, column: InstrumentedAttribute[T],
              machine_ids: Iterable[str]) -> dict[str, T]:
    """One column (`Machine.name`, `Machine.encoding`) of the registered machines among
    `machine_ids`, by id: less to read than whole machines, when that is all it takes."""
    found: dict[str, T] = {}
    for chunk in in_chunks(sorted(set(machine_ids))):
        found.update(session.execute(
            select(Machine.id, column).where(Machine.id.in_(chunk))).all())
    return found


def taking_requests(*, session: Session,
                    kinds: Iterable[str] | None = None) -> list[MachineSpec]:
    """The enabled machines with request settings, by id; only of transports `kinds` if given.

    Asked by every worker every few seconds (listeners, drop folders): the database picks
    the few such machines, where reading a fleet of 100,000 took seconds each time.
    """
    # The condition as the partial index ix_machines_taking_requests has it, written into
    # the statement: a parameter in its place would keep the planner from the index. The
    # transports are picked here, not in SQL: with them in the statement, PostgreSQL took
    # the fleet's one transport for the more selective condition and read all 100,000.
    query = (select(Machine).where(Machine.enabled.is_(True), text(TAKES_REQUESTS))
             .order_by(Machine.id))
    wanted = None if kinds is None else set(kinds)
    return [MachineSpec.of(m) for m in session.scalars(query)
            if wanted is None or m.transport in wanted]


def upsert(*, session: Session, machine_in: MachineIn,
           data_dir: Path) -> tuple[MachineSpec, bool]:
    """Create or update a machine; returns it and whether it was created.

    Its secrets are stored sealed (`jobs.fleet.sealed`) with the keys of `data_dir`. A secret
    given as `SECRET_MASK` (as the API shows it) keeps the stored one, and a root
    equal to the default (as the API shows an unset one) is stored unset, so that it follows
    a later change of model: a machine read from the API, edited and put back stays the same.
    """
    machine_in.check()
    _refuse_sealed(machine_in)
    # Held, and read as another save left it: every column is written against what is
    # stored, so of two saves at once the later replaces the machine whole (the ORM writes
    # only what differs from what it read, and a mix of the two was kept).
    write_first(session)
    machine = session.get(Machine, machine_in.id, with_for_update=True, populate_existing=True)
    machine_in = _as_stored(machine_in, stored=MachineSpec.of(machine) if machine else None)
    machine_in = _sealed(machine_in, data_dir)
    created = machine is None
    if machine is None:
        machine = Machine(id=machine_in.id)
        session.add(machine)
    for key, value in machine_in.model_dump().items():
        setattr(machine, key, value)
    session.flush()
    log.info("machine %s %s (%s, %s)", machine.id, "added" if created else "updated",
             machine.model, machine.transport)
    return MachineSpec.of(machine), created


def _refuse_sealed(machine_in: MachineIn) -> None:
    """Refuse a secret given already sealed: dncq never shows one, so it can only come from
    a copy of a database, and taking it would send that database's secret to whatever host
    this machine names (or fail only when used, sealed with another key)."""
    for key in secret_options(machine_in.transport, machine_in.options):
        if sealed.is_sealed(machine_in.options[key]):
            raise ValueError(f"options.{key}: {sealed.PREFIX}… is how dncq stores a secret, "
                             "not one it takes: give the secret itself")


def _as_stored(machine_in: MachineIn, *, stored: MachineSpec | None) -> MachineIn:
    """`machine_in` with masked secrets replaced by the stored ones and a default root unset."""
    options = dict(machine_in.options)
    for key, value in machine_in.options.items():
        if value == SECRET_MASK:
            if stored is None or key not in stored.options:
                raise ValueError(f"options.{key}: {SECRET_MASK} is how a secret is shown; "
                                 "give the secret itself")
            if _moved(machine_in, stored):  # else a changed host could collect the secret
                raise ValueError(f"options.{key}: the machine's address or TLS settings "
                                 "change, so give the secret itself")
            options[key] = stored.options[key]
    # The default shown by GET was the stored model's; an edit may also change the model.
    defaults = {governing_row(machine_in).default_root}
    if stored is not None and stored.root is None:
        defaults.add(governing_row(stored).default_root)
    root = None if machine_in.root in defaults else machine_in.root
    return machine_in.model_copy(update={"options": options, "root": root})


def _sealed(machine_in: MachineIn, data_dir: Path) -> MachineIn:
    """`machine_in` with every secret sealed; one stored sealed is kept as it is."""
    options = dict(machine_in.options)
    for key in secret_options(machine_in.transport, options):
        value = options[key]
        if isinstance(value, str) and not sealed.is_sealed(value):
            options[key] = sealed.keyring(data_dir).seal(value)
    return machine_in.model_copy(update={"options": options})


def reseal(*, session: Session, data_dir: Path) -> int:
    """Seal every machine's secrets again with the first key; returns how many machines.

    After a new key is put first: secrets sealed with an older key, or stored before
    secrets were sealed, are then sealed with the new one, and the old key can go.
    """
    keys = sealed.keyring(data_dir)
    count = 0
    for machine in session.scalars(select(Machine).order_by(Machine.id)):
        options = dict(machine.options)
        secret_keys = [k for k in secret_options(machine.transport, options)
                       if isinstance(options[k], str)]
        for key in secret_keys:
            options[key] = keys.rotated(options[key])
        if secret_keys:
            machine.options = options
            count += 1
    session.flush()
    return count


# Options that say where a secret is sent and how it is protected on the way.
_ADDRESS_OPTIONS = ("host", "port", "url", "server", "share", "tls", "tls_verify",
                    "tls_ca_file", "verify_tls")


def _moved(machine_in: MachineIn, stored: MachineSpec) -> bool:
    """Whether `machine_in` sends the machine's secrets elsewhere, or less protected."""
    return machine_in.transport != stored.transport or any(
        machine_in.options.get(key) != stored.options.get(key) for key in _ADDRESS_OPTIONS)


def set_requests(*, session: Session, machine_id: str,
                 requests: dict[str, Any] | None) -> MachineSpec:
    """Replace what the machine's operator may ask (checked over its controller's preset)."""
    machine = session.get(Machine, machine_id)
    if machine is None:
        raise _unknown(session, machine_id)
    if requests is not None:
        request_settings.resolve(machine.model, requests)
    machine.requests = requests
    session.flush()
    return MachineSpec.of(machine)


def delete(*, session: Session, machine_id: str) -> None:
    """Remove a machine from the registry, in one statement (a removal meanwhile: 10003)."""
    removed = session.execute(sa_delete(Machine).where(Machine.id == machine_id))
    if not removed.rowcount:  # type: ignore[attr-defined]
        raise _unknown(session, machine_id)
