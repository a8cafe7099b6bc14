"""Fleet files: the machines of a YAML `machines:` list, each checked before any is kept,
then added to the registry or updated there in one transaction."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError
from sqlalchemy.orm import Session

from jobs.errors import ContractError, validation_summary
from jobs.fleet.registry import MachineIn, upsert


class FleetFileError(ValueError):
    """A fleet file that cannot be imported; lists every bad entry."""


class _FleetLoader(yaml.SafeLoader):
    """YAML with a machine's `id` read as written (YAML 1.1 makes `0010` 8 and `12:30` 750),
    and no key given twice in one mapping: PyYAML keeps the last, so a second `options:`
    would drop the first's `tls` or password without a word."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        given: set[str] = set()
        for key, value in node.value:
            if isinstance(key, yaml.ScalarNode):
                if key.value in given:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"found {key.value!r} twice in one mapping",
                        key.start_mark)
                given.add(key.value)
            if (isinstance(key, yaml.ScalarNode) and key.value == "id"
                    and isinstance(value, yaml.ScalarNode) and value.tag in _NUMBER_TAGS):
                value.tag = "tag:yaml.org,2002:str"
        return super().construct_mapping(node, deep=deep)


_NUMBER_TAGS = ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float")


def parse_fleet(text: str) -> list[MachineIn]:
    """The machines of a fleet file (YAML `machines:` list), all checked before any is kept."""
    try:
        data = yaml.load(text, Loader=_FleetLoader) or {}  # noqa: S506 - a SafeLoader
    except yaml.YAMLError as exc:
        raise FleetFileError(f"a fleet file is YAML, and this is not: {_where_wrong(exc)}"
                             ) from None
    entries = data.get("machines") if isinstance(data, dict) else None
    if not isinstance(entries, list):
        raise FleetFileError("a fleet file holds a list under 'machines:'")
    machines, problems, seen = [], [], set()
    for n, entry in enumerate(entries, 1):
        label = f"entry {n}" + (f" (id {entry.get('id')})" if isinstance(entry, dict) else "")
        try:
            machine = MachineIn.model_validate(entry)
            machine.check()
        except (ValidationError, ValueError, ContractError) as exc:
            problems.append(f"{label}: {_short(exc)}")
            continue
        if machine.id in seen:
            problems.append(f"{label}: id {machine.id} appears twice")
        seen.add(machine.id)
        machines.append(machine)
    if problems:
        raise FleetFileError("fleet file not imported:\n  " + "\n  ".join(problems))
    return machines


def import_fleet(*, session: Session, machines: Iterable[MachineIn],
                 data_dir: Path) -> tuple[int, int]:
    """Add or update every machine; returns (added, updated). Importing twice never duplicates.

    Raises:
        FleetFileError: an entry the registry refuses; the caller's transaction is then
            rolled back whole.
    """
    added = updated = 0
    for index, machine_in in enumerate(machines, start=1):
        try:
            _, created = upsert(session=session, machine_in=machine_in, data_dir=data_dir)
        except ValueError as exc:  # what only the registry can tell (a masked secret)
            raise FleetFileError(f"entry {index} (id {machine_in.id}): {exc}") from None
        added += created
        updated += not created
    return added, updated


def _where_wrong(exc: yaml.YAMLError) -> str:
    """What is wrong with the YAML, and at which line and column; not the line itself, as
    PyYAML quotes it, since a fleet file's lines hold machines' passwords."""
    if not isinstance(exc, yaml.MarkedYAMLError) or exc.problem_mark is None:
        return type(exc).__name__
    mark = exc.problem_mark
    context = f" ({exc.context})" if exc.context else ""
    return f"line {mark.line + 1}, column {mark.column + 1}: {exc.problem}{context}"


def _short(exc: Exception) -> str:
    if isinstance(exc, ValidationError):
        return validation_summary(exc.errors(), whole="entry")
    return str(exc)
