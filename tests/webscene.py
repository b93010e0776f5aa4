"""A small ward for the web page's tests, and the real server app on a loopback port.

:func:`fill_ward` writes, through the store and the object map, what a short run leaves:
robot r1 (session s1, anchored: it set the map) drove along y = 0 from x = 0 to 10 m, robot r2
(one session, not anchored yet); three doors on the wall y = 5, a bed and a wheelchair
(:data:`OBJECTS`; the bed turned by :data:`BED_YAW`); door 2 was observed in r1's keyframe 3,
which is stored (the thumbnail).

:func:`live_server` runs ``MapServer(url).app`` under uvicorn on a thread (the app ``wardmap
server`` serves, without Zenoh or mapping) and yields its base URL and the running root, whose
``services.objects`` a test writes to as the map writer would.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace

import factories
import numpy as np

from wardmap.server.app import MapServer
from wardmap.server.objectmap import ObjectMap, ObjectState, Observation
from wardmap.server.store import GraphChange, GraphNodeRow, SessionAnchor, open_store
from wardmap.shared import wire
from wardmap.shared.se3 import make_transform, yaw_transform

T0 = factories.T0
R1_KEYFRAMES = 6
R2_KEYFRAMES = 3
DOOR_SIZE = (0.9, 0.1, 2.0)
OBJECTS: tuple[tuple[int, str, float, float, float, tuple[float, float, float]], ...] = (
    # id, category, x, y, z (centre, m), size (m)
    (1, "door", 0.0, 5.0, 1.0, DOOR_SIZE),
    (2, "door", 6.0, 5.0, 1.0, DOOR_SIZE),
    (3, "door", 12.0, 5.0, 1.0, DOOR_SIZE),
    (4, "bed", 5.0, 2.0, 0.3, (2.0, 1.0, 0.6)),
    (5, "wheelchair", 8.0, 1.5, 0.45, (0.7, 0.7, 0.9)),
)
BED_YAW = 0.5
"""The bed (object 4) is turned by this about z (rad); the others are not."""
THUMB_BOX = (10.0, 8.0, 40.0, 30.0)
"""Door 2's box (x1, y1, x2, y2) in the pixels of r1's keyframe 3."""

# The camera looks along the map's +x (its z axis), x to the map's -y, y down (map -z).
R_MAP_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_at(x: float, y: float) -> np.ndarray:
    """T_map_camera (4, 4) of a camera 1.2 m above (x, y) looking along +x."""
    return make_transform(R_MAP_CAMERA, [x, y, 1.2])


def read_token(url: str) -> str:
    """A new ``read`` token of the store at ``url`` (what a member of staff would be given)."""
    from wardmap.server.tokens import create_token

    with open_store(url) as store:
        return create_token(store, "read", "browser test").text


def fill_ward(url: str) -> None:
    """Write the ward of the module docstring into the store at ``url``."""
    base = factories.keyframe(np.random.default_rng(0))
    with open_store(url) as store:
        nodes = []
        for k in range(R1_KEYFRAMES):
            T = camera_at(2.0 * k, 0.0)
            msg = replace(base, robot_id="r1", session_id="s1", seq=k, stamp=T0 + k, T_odom_camera=T)
            assert store.insert(msg, wire.encode(msg), T0 + 100 + k) == "stored"
            nodes.append(GraphNodeRow(("r1", "s1", k), T0 + k, T, "rgb", T, None, b""))
        for k in range(R2_KEYFRAMES):
            T = camera_at(1.0 * k, 3.0)
            msg = replace(base, robot_id="r2", session_id="s1", seq=k, stamp=T0 + k, T_odom_camera=T)
            assert store.insert(msg, wire.encode(msg), T0 + 200 + k) == "stored"
            nodes.append(GraphNodeRow(("r2", "s1", k), T0 + k, T, "rgb", None, None, b""))
        store.commit_graph("backend", R1_KEYFRAMES + R2_KEYFRAMES, GraphChange(nodes, sessions=[
            SessionAnchor("r1", "s1", np.eye(4), T0 + 150, "r1/s1", 1),
            SessionAnchor("r2", "s1", None, None, "", 0)]))
        states = [ObjectState(oid, cat, 0.9, yaw_transform(x, y, BED_YAW if oid == 4 else 0.0, z),
                              np.array(size)) for oid, cat, x, y, z, size in OBJECTS]
        seen = [Observation(2, "r1", "s1", 3, T0 + 3, "door", 0.8, np.array(THUMB_BOX),
                            yaw_transform(6.0, 5.0, 0.0, 1.0), np.array(DOOR_SIZE))]
        ObjectMap(store).upsert(states, seen)


@contextmanager
def live_server(url: str) -> Iterator[tuple[str, MapServer]]:
    """``MapServer(url).app`` under uvicorn on a free 127.0.0.1 port, stopped at exit."""
    import uvicorn

    root = MapServer(url)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    sock.listen(64)
    port = sock.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(root.app, log_config=None, access_log=False, lifespan="on",
                                           timeout_graceful_shutdown=1))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, name="test-http", daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 30
        while not server.started:
            if not thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError("the test HTTP server did not start")
            time.sleep(0.02)  # uvicorn offers no start event
        yield f"http://127.0.0.1:{port}", root
    finally:
        server.should_exit = True
        thread.join(15)
        sock.close()
