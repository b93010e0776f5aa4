"""The association checkpoint's contents: what it is valid for and how it is encoded.

The mapping stage saves its association state (the :class:`~wardmap.server.mapping.writer.WriterState`
and the idle closures at its cursor) so a restart replays only the keyframes after it. A
checkpoint is used only by the same association code and settings (:func:`checkpoint_key`).
The state is written in the association's versioned, data-only format
(:mod:`wardmap.server.association.state`: msgpack and a registry of the classes it may
rebuild; decoding never runs code), so a tampered database file can at worst lose the
checkpoint, which a full replay replaces.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Any, Final

from wardmap.server.association import state as association_state
from wardmap.server.association.associator import AssociationConfig
from wardmap.server.codedigest import code_digest
from wardmap.shared.config import to_mapping

CHECKPOINT_FORMAT: Final = 2
"""Bumped when the checkpoint's contents change shape (part of its key)."""


def encode_state(state: dict[str, Any]) -> bytes:
    """The checkpoint's state dict as bytes (:func:`wardmap.server.association.state.encode`)."""
    return association_state.encode(state)


def decode_state(blob: bytes) -> Any:
    """Inverse of :func:`encode_state`; raises :class:`~wardmap.server.association.state.CheckpointError`
    (or any exception) when the blob cannot be used."""
    return association_state.decode(blob)


def checkpoint_key(association: AssociationConfig, hist_bins: tuple[int, int, int]) -> str:
    """What a checkpoint is valid for: its format, the association code and settings."""
    return json.dumps({"format": CHECKPOINT_FORMAT, "code": association_code(),
                       "association": to_mapping(association),
                       "hist_bins": list(hist_bins)}, sort_keys=True)


@functools.cache
def association_code() -> str:
    """Digest of the code whose state a checkpoint holds (the association package, the mapping
    stage) and of the packaged knowledge graph: a checkpoint of other code is not used."""
    import wardmap.server.association as association

    return code_digest([*sorted(Path(association.__file__).resolve().parent.glob("*.py")),
                        *sorted(Path(__file__).resolve().parent.glob("*.py"))])
