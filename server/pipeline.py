"""Former home of the mapping stage, now ``server/mapping/``; these names stay importable
from here for callers not yet moved."""

from __future__ import annotations

from wardmap.server.mapping import (
    MapPipeline,
    PipelineConfig,
    PipelineCounters,
    PipelineFactory,
    for_association,
)

__all__ = ["MapPipeline", "PipelineConfig", "PipelineCounters", "PipelineFactory", "for_association"]
