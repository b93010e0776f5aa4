"""The wardmap exception family.

Every error a user can cause derives from :class:`WardmapError`. Each boundary
translates it once: the CLI prints one line and exits 1, HTTP maps it to a status,
ingest counts it as a rejection.
"""

from __future__ import annotations


class WardmapError(Exception):
    """Base of all errors wardmap raises on bad input or bad state."""


class ConfigError(WardmapError):
    """A configuration file or value is missing, malformed or out of range."""


class DatasetError(WardmapError):
    """A data-set folder is missing files or holds malformed ones."""


class WireError(WardmapError):
    """A message on the wire cannot be decoded or fails validation.

    Attributes:
        field: dotted name of the offending field (``""`` for the whole message).
    """

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        super().__init__(f"{field}: {message}" if field else message)


class GeometryError(WardmapError):
    """An array has the wrong shape, is not finite, or is not a valid transform."""


class SimulationError(WardmapError):
    """A simulator request cannot be served (unknown scenario, bad parameters)."""


class KnowledgeGraphError(WardmapError):
    """The knowledge-graph file is malformed or a class is unknown."""
