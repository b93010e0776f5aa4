"""Scenes for the REST API tests: a keyframe store and an object map, each in a temporary
SQLite file, and a TestClient over the API-only server (:class:`MapServer` without Zenoh or
mapping) whose lifespan opens the same file. The clients send a real ``read`` token created
in that file (``api/auth.py`` checks it on every data route)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import factories
import numpy as np
import pytest
from fastapi.testclient import TestClient

from wardmap.server.app import MapServer
from wardmap.server.objectmap import ObjectMap, ObjectState, Observation
from wardmap.server.store import GraphChange, GraphNodeRow, SessionAnchor, open_store
from wardmap.server.tokens import create_token
from wardmap.shared import wire
from wardmap.shared.se3 import make_transform, yaw_transform
from wardmap.shared.wire import KeyframeMsg

W, H = 64, 48
T0 = 1_714_557_600.0


@dataclass(frozen=True)
class KeyframeScene:
    """Robot r1 (``n_r1`` keyframes, sessions s1 and s2) and r2 (``n_r2``, one session), received
    at ``t0 + 100 + k`` (r1) and ``t0 + 200 + k`` (r2); rejections ``wire: payload`` x2 and
    ``odd "reason"`` x1."""

    url: str
    t0: float = T0
    n_r1: int = 7
    n_r2: int = 3

    T_map_odom_s2: np.ndarray = field(default_factory=lambda: make_transform(np.eye(3), [3.0, 4.0, 0.0]))
    """Where the back-end put r1's second session (the first, s1, set the map: identity)."""

    @staticmethod
    def pose(k: int) -> np.ndarray:
        """T_odom_camera of keyframe ``k`` of either robot."""
        a = 0.1 * k
        R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        return make_transform(R, [k * 0.5, -1.0, 0.25])


def _keyframe() -> KeyframeMsg:
    return factories.keyframe(np.random.default_rng(0))


@pytest.fixture
def keyframe_scene(tmp_path: Path) -> KeyframeScene:
    """Real wire keyframes (a 64x48 JPEG, a 32x24 depth raster) stored through ``store.insert``."""
    scene = KeyframeScene(f"sqlite:///{tmp_path / 'map.db'}")
    base = _keyframe()
    with open_store(scene.url) as store:
        for k in range(scene.n_r1):
            msg = replace(base, robot_id="r1", session_id="s1" if k < 5 else "s2", seq=k,
                          stamp=T0 + k, T_odom_camera=scene.pose(k))
            assert store.insert(msg, wire.encode(msg), T0 + 100 + k) == "stored"
        for k in range(scene.n_r2):
            msg = replace(base, robot_id="r2", seq=k, stamp=T0 + k, T_odom_camera=scene.pose(k))
            assert store.insert(msg, wire.encode(msg), T0 + 200 + k) == "stored"
        store.count_rejection("wire: payload")
        store.count_rejection("wire: payload")
        store.count_rejection('odd "reason"')
        # The back-end's graph: r1/s1 set the map, r1/s2 was anchored through it, r2 floats.
        nodes = [GraphNodeRow(("r1", "s1" if k < 5 else "s2", k), T0 + k, scene.pose(k), "rgb",
                              (np.eye(4) if k < 5 else scene.T_map_odom_s2) @ scene.pose(k), None, b"")
                 for k in range(scene.n_r1)]
        nodes += [GraphNodeRow(("r2", base.session_id, k), T0 + k, scene.pose(k), "rgb", None, None, b"")
                  for k in range(scene.n_r2)]
        store.commit_graph("backend", scene.n_r1 + scene.n_r2, GraphChange(nodes, sessions=[
            SessionAnchor("r1", "s1", np.eye(4), T0 + 150, "r1/s1", 1),
            SessionAnchor("r1", "s2", scene.T_map_odom_s2, T0 + 160, "r1/s1", 2),
            SessionAnchor("r2", base.session_id, None, None, "", 0)]))
    return scene


def _token_headers(url: str, scope: str = "read") -> dict[str, str]:
    """The Authorization header of a new ``scope`` token in the store at ``url``."""
    with open_store(url) as store:
        return {"Authorization": f"Bearer {create_token(store, scope, 'tests').text}"}


@pytest.fixture
def token_headers() -> Callable[..., dict[str, str]]:
    """``token_headers(url, scope="read")``: the Authorization header of a new token in the
    store at ``url`` (test modules cannot import this conftest)."""
    return _token_headers


@pytest.fixture
def keyframe_client(keyframe_scene: KeyframeScene) -> Iterator[TestClient]:
    with TestClient(MapServer(keyframe_scene.url).app, headers=_token_headers(keyframe_scene.url)) as c:
        yield c


@dataclass(frozen=True)
class ObjectScene:
    """Objects ``id: (category, x, confidence, robots)``: object k stands at ``(x, 0, 0.5)``
    with yaw ``0.25 k``, size 1 x 0.5 x 2 m; each of its robots observed it once (seq
    ``10 k + i``, stamp ``t0 + k``) at ``(x, 0.1, 0.5)``, unrotated."""

    url: str
    t0: float = T0
    objects: tuple[tuple[int, str, float, float, tuple[str, ...]], ...] = (
        (1, "door", 0.0, 0.9, ("r1",)),
        (2, "door", 4.0, 0.6, ("r2",)),
        (3, "bed", 1.0, 0.95, ("r1", "r2")),
        (4, "wheelchair", 2.5, 0.4, ()),
        (5, "door", 10.0, 0.8, ("r1",)),
    )


@pytest.fixture
def object_scene(tmp_path: Path) -> ObjectScene:
    """The scene written through :class:`ObjectMap`."""
    scene = ObjectScene(f"sqlite:///{tmp_path / 'map.db'}")
    with open_store(scene.url) as store:
        objs, obs = [], []
        for oid, cat, x, conf, robots in scene.objects:
            objs.append(
                ObjectState(oid, cat, conf, yaw_transform(x, 0.0, 0.25 * oid, 0.5), np.array([1.0, 0.5, 2.0]))
            )
            for k, robot in enumerate(robots):
                obs.append(Observation(
                    oid, robot, "s1", 10 * oid + k, T0 + oid, cat, 0.7, np.array([0.0, 0.0, 8.0, 9.0]),
                    yaw_transform(x, 0.1, 0.0, 0.5), np.array([1.0, 0.5, 2.0]),
                ))
        ObjectMap(store).upsert(objs, obs)
    return scene


@pytest.fixture
def object_client(object_scene: ObjectScene) -> Iterator[TestClient]:
    with TestClient(MapServer(object_scene.url).app, headers=_token_headers(object_scene.url)) as c:
        yield c
