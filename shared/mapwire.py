"""The object map's Zenoh messages: key expressions, schemas and the decoder robots use.

The map server (``server/mapserve.py``) answers queries on :data:`OBJECTS_KEY` and publishes
changes on :data:`UPDATES_KEY`; a robot (``edge/``) or any other client decodes both with
:func:`decode_map_message`. Both sides import this module, so the format has one definition
(edge and server never import each other).

Payloads are msgpack maps with ``schema`` and ``version``:

- ``wardmap.map.objects``: ``objects`` (list of object maps), ``next_offset`` (int or nil);
- ``wardmap.map.update``: ``kind`` (``created``, ``updated``, ``merged`` ...), ``object``,
  optional ``merged_into``;
- ``wardmap.map.error``: ``detail``.

An object map has ``object_id``, ``category``, ``confidence``, ``T_world_object``
(``{"t": [x, y, z], "q_xyzw": [...]}``, metres, the wire convention of ``shared/wire.py``),
``yaw`` (rad), ``size``, ``bounds_min``, ``bounds_max`` (metres), ``n_observations``,
``first_seen_s``, ``last_seen_s``, ``robots``, ``confirmed`` (bool), and optionally ``color_rgb`` and
``distance_m``. docs/map_api.md has the full field list.
"""

from __future__ import annotations

from typing import Any, Final

import msgpack

from wardmap.shared.errors import WireError
from wardmap.shared.zenoh_config import KEY_PREFIX

__all__ = [
    "ENCODING",
    "MAX_MESSAGE_BYTES",
    "OBJECTS_KEY",
    "SCHEMA_ERROR",
    "SCHEMA_OBJECTS",
    "SCHEMA_UPDATE",
    "UPDATES_KEY",
    "VERSION",
    "decode_map_message",
    "pack_map_message",
]

OBJECTS_KEY: Final = f"{KEY_PREFIX}/map/objects"
UPDATES_KEY: Final = f"{KEY_PREFIX}/map/updates"
SCHEMA_OBJECTS: Final = "wardmap.map.objects"
SCHEMA_UPDATE: Final = "wardmap.map.update"
SCHEMA_ERROR: Final = "wardmap.map.error"
SCHEMAS: Final = (SCHEMA_OBJECTS, SCHEMA_UPDATE, SCHEMA_ERROR)
VERSION: Final = 1
ENCODING: Final = "application/msgpack"
MAX_MESSAGE_BYTES: Final = 16 * 2**20


def pack_map_message(schema: str, fields: dict[str, Any]) -> bytes:
    """msgpack bytes of ``{schema, version, **fields}``.

    Raises:
        ValueError: ``schema`` is not one of the map schemas.
    """
    if schema not in SCHEMAS:
        raise ValueError(f"unknown map schema {schema!r}")
    payload: bytes = msgpack.packb({"schema": schema, "version": VERSION, **fields}, use_bin_type=True)
    return payload


def decode_map_message(payload: bytes, *, max_bytes: int = MAX_MESSAGE_BYTES) -> dict[str, Any]:
    """Unpack a map message (objects reply, update or error) and check ``schema`` and ``version``.

    Returns the message as a dict (fields in the module docstring).

    Raises:
        WireError: oversize, not msgpack, not a map, unknown schema or version.
    """
    if len(payload) > max_bytes:
        raise WireError("", f"map message of {len(payload)} bytes exceeds {max_bytes}")
    try:
        message = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=True)
    except (ValueError, msgpack.UnpackException) as exc:
        raise WireError("", f"not a msgpack map message: {exc}") from exc
    if not isinstance(message, dict):
        raise WireError("", f"expected a map, got {type(message).__name__}")
    schema = message.get("schema")
    if schema not in SCHEMAS:
        raise WireError("schema", f"unknown map schema {str(schema)[:60]!r}")
    if message.get("version") != VERSION:
        raise WireError("version", f"unsupported version {message.get('version')!r:.20} of {schema}")
    return message
