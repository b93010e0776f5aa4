"""Logging set-up for the command line. Library modules only call ``getLogger``.

Two formats: ``text`` (a time, the level, the logger and the message on one line, for people)
and ``json`` (one JSON object per line, for log collectors: journald, Loki, Elasticsearch):
``{"ts": "2026-11-26T13:59:52.123Z", "level": "WARNING", "logger": "wardmap.server.app",
"message": "...", "process": 1234, "thread": "MainThread"}`` plus ``"exc"`` (the formatted
traceback) when the record carries an exception. Times are UTC.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from typing import Literal

__all__ = ["LOG_FORMATS", "JsonFormatter", "configure_logging"]

LOG_FORMATS = ("text", "json")
"""The values of ``--log-format``."""

TEXT_FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"


class JsonFormatter(logging.Formatter):
    """One JSON object per record, on one line (newlines inside the message are escaped)."""

    def format(self, record: logging.LogRecord) -> str:
        ms = int(record.msecs)
        out: dict[str, object] = {
            "ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{ms:03d}Z",
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
            "process": record.process,
            "thread": record.threadName,
        }
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, ensure_ascii=False, default=str)


def configure_logging(
    verbosity: int = 0, *, stream: object = None, log_format: Literal["text", "json"] = "text"
) -> None:
    """Send log records to stderr: WARNING by default, INFO with -v, DEBUG with -vv, in
    ``log_format`` (:data:`LOG_FORMATS`; the module docstring).

    Only the CLI calls this; calling it again replaces the handler.

    Raises:
        ValueError: an unknown ``log_format``.
    """
    if log_format not in LOG_FORMATS:
        raise ValueError(f"bad log format {log_format!r}: expected one of {', '.join(LOG_FORMATS)}")
    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    handler = logging.StreamHandler(stream if stream is not None else sys.stderr)  # type: ignore[arg-type]
    if log_format == "json":
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(logging.Formatter(TEXT_FORMAT, "%H:%M:%S"))
    root.addHandler(handler)
    root.setLevel(level)
    logging.getLogger("numba").setLevel(logging.WARNING)
