"""Logging set-up for the command line. Library modules only call ``getLogger``."""

from __future__ import annotations

import logging
import sys


def configure_logging(verbosity: int = 0, *, stream: object = None) -> None:
    """Send log records to stderr: WARNING by default, INFO with -v, DEBUG with -vv.

    Only the CLI calls this; calling it again replaces the handler.
    """
    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    handler = logging.StreamHandler(stream if stream is not None else sys.stderr)  # type: ignore[arg-type]
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)-7s %(name)s: %(message)s", "%H:%M:%S"))
    root.addHandler(handler)
    root.setLevel(level)
    logging.getLogger("numba").setLevel(logging.WARNING)
