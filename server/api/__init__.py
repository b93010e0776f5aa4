"""The map server's REST API (FastAPI), laid out as in the FastAPI full-stack template.

| module | holds |
|---|---|
| ``main.py`` | :func:`create_app`: the routers, the WardmapError -> HTTP handler, the lifespan |
| ``deps.py`` | :class:`Services` (what the composition root hands the routes) and the ``*Dep`` aliases |
| ``schemas.py`` | response bodies (pydantic), separate from the store's dataclasses |
| ``prometheus.py`` | ``/metrics``: a ``prometheus_client`` collector over the parts' counters |
| ``routes/<resource>.py`` | one ``APIRouter`` per resource: health, robots, keyframes, objects, ... |

The composition root is :class:`wardmap.server.app.MapServer`: it builds the store, object
map, Zenoh session, ingest, map service and mapping stage, and this app; the app's lifespan
only starts and stops it.
"""

from wardmap.server.api.deps import ServerLifecycle, Services
from wardmap.server.api.main import create_app
from wardmap.server.api.routes.keyframes import decode_cursor, encode_cursor
from wardmap.server.api.schemas import (
    CategoryList,
    CategoryOut,
    ErrorOut,
    Health,
    InvalidOut,
    KeyframeList,
    KeyframeOut,
    KeyframeRefOut,
    ObjectDetailOut,
    ObjectList,
    ObjectOut,
    ObservationOut,
    PoseOut,
    RobotList,
    RobotOut,
    TrajectoryOut,
    TransformOut,
)

__all__ = [
    "CategoryList",
    "CategoryOut",
    "ErrorOut",
    "Health",
    "InvalidOut",
    "KeyframeList",
    "KeyframeOut",
    "KeyframeRefOut",
    "ObjectDetailOut",
    "ObjectList",
    "ObjectOut",
    "ObservationOut",
    "PoseOut",
    "RobotList",
    "RobotOut",
    "ServerLifecycle",
    "Services",
    "TrajectoryOut",
    "TransformOut",
    "create_app",
    "decode_cursor",
    "encode_cursor",
]
