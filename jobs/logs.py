"""How dncq's processes log: lines of text, or one JSON object per line (`DNCQ_LOG_FORMAT=json`).

A JSON line holds `time` (ISO 8601, UTC), `level`, `logger`, `message`, the traceback as
`exc_info`, and the fields a call gives with `extra=` (`job_id`, `machine_id`). Records are
formatted after the loggers' filters ran, so what those mask (the API key in the access
log) is masked in either format.
"""

from __future__ import annotations

import logging
from typing import Any, Literal

from pythonjsonlogger.core import RESERVED_ATTRS
from pythonjsonlogger.json import JsonFormatter

LogFormat = Literal["text", "json"]

TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
# Record attributes that are not for the reader: uvicorn's coloured copy of the message,
# asyncio's task name (None outside a task).
_LEFT_OUT = (*RESERVED_ATTRS, "color_message", "taskName")


class JsonLines(JsonFormatter):
    """One JSON object per record: time, level, logger, message, and the extra fields."""

    def __init__(self) -> None:
        super().__init__("%(levelname)s %(name)s %(message)s",
                         rename_fields={"levelname": "level", "name": "logger"},
                         reserved_attrs=_LEFT_OUT, timestamp="time")


def configure(log_format: LogFormat, *, level: int = logging.INFO) -> None:
    """The root logger writes to stderr in `log_format`."""
    if log_format == "json":
        handler = logging.StreamHandler()
        handler.setFormatter(JsonLines())
        root = logging.getLogger()
        root.handlers[:] = [handler]
        root.setLevel(level)
        logging.captureWarnings(True)  # Python's warnings as records too, not loose text
    else:
        logging.basicConfig(level=level, format=TEXT_FORMAT)


def as_json(logger: logging.Logger) -> None:
    """Every handler of `logger` writes JSON lines (Celery's own handlers, once it made them)."""
    for handler in logger.handlers:
        handler.setFormatter(JsonLines())


def uvicorn_options(log_format: LogFormat) -> dict[str, Any]:
    """Options for uvicorn's Config: in JSON, no logging setup of its own, so that its
    loggers reach the root's handler; in text, uvicorn's as before."""
    return {"log_config": None} if log_format == "json" else {}
