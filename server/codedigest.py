"""Digests of the code (and the knowledge graph) that made some derived data, so caches and
checkpoints made by other code are not reused."""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from importlib import resources
from pathlib import Path

from wardmap.shared.knowledge import PACKAGED_FILE

__all__ = ["code_digest"]


def code_digest(paths: Iterable[Path]) -> str:
    """16 hex digits of sha256 over each file's name and bytes, in the order given, then the
    packaged knowledge graph (``wardmap.shared.data``)."""
    h = hashlib.sha256()
    for path in paths:
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    h.update(resources.files("wardmap.shared.data").joinpath(PACKAGED_FILE).read_bytes())
    return h.hexdigest()[:16]
