"""``--log-format``, the option of the long-running commands (router, server, edge)."""

from __future__ import annotations

import argparse

from wardmap.shared.logsetup import LOG_FORMATS


def add_log_format(parser: argparse.ArgumentParser) -> None:
    """Add ``--log-format {text,json}`` to ``parser`` (``cli/main.py`` reads ``args.log_format``)."""
    parser.add_argument(
        "--log-format", choices=LOG_FORMATS, default="text",
        help="log lines on stderr as text (default) or one JSON object per line (log collectors)",
    )
