"""The mapping stage: stored keyframes -> perception -> association -> the object map.

``stage.py`` runs it (thread, cursor, retries, replay, idle sessions, checkpoints);
``perceive.py`` takes one keyframe through perception; ``workers.py`` runs perception worker
processes on every server, which claim stored keyframes and store their results for the stage;
``writer.py`` is the map writer (association, colours, object-map writes); ``checkpoint.py``
says what a saved association state is valid for and how it is encoded.
"""

from __future__ import annotations

from wardmap.server.mapping.stage import MapPipeline, PipelineConfig, PipelineCounters, PipelineFactory
from wardmap.server.mapping.writer import MappedKeyframe, MapWriter, WriterState, for_association

__all__ = [
    "MapPipeline",
    "MapWriter",
    "MappedKeyframe",
    "PipelineConfig",
    "PipelineCounters",
    "PipelineFactory",
    "WriterState",
    "for_association",
]
