"""What a received text would trigger, as rows (`dncq requests test MACHINE FILE`): one per
command found, with where it was found, its action and what would be done."""

from __future__ import annotations

from typing import Any

from jobs.fleet.request_settings import RequestSettings
from jobs.requests.naming import path_of
from jobs.requests.plan import planned
from jobs.requests.recognise import recognise


def explain(text: bytes, settings: RequestSettings) -> list[dict[str, Any]]:
    """The rows of what `text` would trigger, in the order of the text.

    Each row: `line`, `where` (header, body, pattern), `command`, `body`, `action` (None
    for a name the settings do not know), `folder` and `file` resolved (None when the
    command names none) and `result` in words. A text that is refused or is not a request
    gives one more row (`command` None) saying so; a request that is refused as a whole
    ends with a row giving the reason.
    """
    recognised = recognise(text, settings)
    plan, outcomes = planned(recognised, settings)
    rows: list[dict[str, Any]] = [
        {"line": o.command.line, "where": o.command.where, "command": o.command.name,
         "body": o.command.body,
         "action": None if o.command.action is None else o.command.action.value,
         "folder": o.folder, "file": o.name, "result": o.result}
        for o in outcomes]
    summary: str | None = None
    if plan.refused and not plan.is_request:
        summary = f"refused: {plan.refused}"
    elif plan.refused:
        summary = f"the request is refused: {plan.refused}"
    elif not plan.is_request:
        stored = (path_of(settings.receive_folder, plan.received_name) if plan.received_name
                  else "a failed transfer (the program gives no usable name)")
        summary = f"not a request: received and kept as {stored}"
    if summary:
        rows.append({"line": None, "where": None, "command": None, "body": None,
                     "action": None, "folder": None, "file": plan.received_name,
                     "result": summary})
    return rows
