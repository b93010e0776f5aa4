"""``wardmap.shared.logsetup``: the text and JSON log formats of the CLI."""

from __future__ import annotations

import io
import json
import logging
from collections.abc import Iterator

import pytest

from wardmap.shared.logsetup import configure_logging


@pytest.fixture(autouse=True)
def _restore_root() -> Iterator[None]:
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    for h in list(root.handlers):
        root.removeHandler(h)
    for h in handlers:
        root.addHandler(h)
    root.setLevel(level)


def test_json_logs_are_one_object_per_line() -> None:
    """A multi-line message and an exception's traceback stay on one line each record; every line
    parses as a JSON object with time (UTC, ``Z``), level, logger and message."""
    out = io.StringIO()
    configure_logging(1, stream=out, log_format="json")
    log = logging.getLogger("wardmap.test")
    log.info("two\nlines %d", 2)
    try:
        raise RuntimeError("boom")
    except RuntimeError:
        log.exception("failed")
    log.debug("not at -v")
    lines = out.getvalue().splitlines()
    assert len(lines) == 2
    first, second = (json.loads(line) for line in lines)
    assert first["message"] == "two\nlines 2"
    assert (first["level"], first["logger"]) == ("INFO", "wardmap.test")
    assert first["ts"].endswith("Z") and "T" in first["ts"]
    assert "exc" not in first
    assert second["level"] == "ERROR" and "RuntimeError: boom" in second["exc"]


def test_text_logs_and_a_bad_format() -> None:
    """The text format is one human line; an unknown format is refused."""
    out = io.StringIO()
    configure_logging(0, stream=out)
    logging.getLogger("wardmap.test").warning("careful")
    assert out.getvalue().rstrip().endswith("WARNING wardmap.test: careful")
    with pytest.raises(ValueError, match="bad log format"):
        configure_logging(0, stream=out, log_format="xml")  # type: ignore[arg-type]
