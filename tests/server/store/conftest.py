"""Fixtures of the store tests: every backend behind one fixture, and small valid keyframes.

Protocol tests take ``backend`` (or ``store``) and run once per backend in :data:`BACKENDS`; a
new backend adds its name there and a branch in :class:`Backend`. Keyframes are real
``wardmap.shared.wire`` messages (a 64x48 JPEG, a 32x24 depth raster, a few keypoints)
encoded with :func:`wire.encode`.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import factories
import numpy as np
import pgcluster
import pytest

from wardmap.server.store import MapStore, open_store
from wardmap.shared import wire
from wardmap.shared.se3 import make_transform
from wardmap.shared.wire import KeyframeMsg

BACKENDS = ("sqlite", "postgres", "postgis")
"""Store backends the Protocol tests run against: "postgres" and "postgis" are a database of the
session's cluster (tests/pgcluster.py; skipped where PostgreSQL is not installed), with the GiST box
object index (``?postgis=off``) and with PostGIS's (skipped where PostGIS is not installed)."""
_TEMPLATES: dict[tuple[int, str], str] = {}
"""(cluster port, backend) -> a database holding the migrated, empty schema that tests copy."""

W, H = 64, 48
T0 = 1_714_557_600.0  # 2024-05-01 10:00 UTC


class Backend:
    """One store backend holding one empty database for a test.

    Attributes:
        name: the backend (an entry of :data:`BACKENDS`).
        url: the URL :func:`open_store` opens it with.
    """

    def __init__(self, name: str, tmp_path: Path, cluster: pgcluster.Cluster | None = None) -> None:
        self.name = name
        self.path = tmp_path / "map.db"
        self.cluster = cluster
        if name == "sqlite":
            self.url = f"sqlite:///{self.path}"
        elif name in ("postgres", "postgis") and cluster is not None:
            query = "?postgis=off" if name == "postgres" else ""
            template = _TEMPLATES.get((cluster.port, name))
            if template is None:  # migrate once per session; each test copies the result (fast)
                template = cluster.new_database()
                open_store(cluster.url(template) + query).close()
                _TEMPLATES[(cluster.port, name)] = template
            self.database = cluster.new_database(template)
            self.url = cluster.url(self.database) + query
        else:
            raise ValueError(f"unknown store backend {name!r}")

    def open(self) -> MapStore:
        """A new handle on the test's database (a reopened store sees what was committed)."""
        return open_store(self.url)

    def integrity_ok(self) -> bool:
        """Whether the backend's own consistency check passes (PostgreSQL: amcheck on every B-tree
        index of the store's tables)."""
        if self.cluster is not None:
            self.cluster.psql("CREATE EXTENSION IF NOT EXISTS amcheck", self.database)
            self.cluster.psql(
                "SELECT bt_index_check(c.oid) FROM pg_index i JOIN pg_class c ON c.oid = i.indexrelid "
                "JOIN pg_am a ON a.oid = c.relam WHERE a.amname = 'btree' AND c.relnamespace = "
                "'public'::regnamespace", self.database)
            return True  # bt_index_check raises (psql fails) on a damaged index
        with sqlite3.connect(self.path) as conn:
            return str(conn.execute("PRAGMA integrity_check").fetchone()[0]) == "ok"


@pytest.fixture(params=BACKENDS)
def backend(request: pytest.FixtureRequest, tmp_path: Path) -> Backend:
    if request.param in ("postgres", "postgis"):
        cluster: pgcluster.Cluster = request.getfixturevalue("pg_cluster")
        if request.param == "postgis" and not cluster.postgis:
            pytest.skip("PostGIS is not installed for PostgreSQL 15 (Debian: postgresql-15-postgis-3)")
        return Backend(request.param, tmp_path, cluster)
    return Backend(request.param, tmp_path)


@pytest.fixture
def store(backend: Backend) -> Iterator[MapStore]:
    with backend.open() as s:
        yield s


# --------------------------------------------------------------------------- keyframes


def _pose(stamp: float) -> np.ndarray:
    """A rigid pose that depends on ``stamp`` (yaw and translation), so values can be checked."""
    a = 0.1 * stamp
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return make_transform(R, [stamp % 7.0, -1.0, 0.5])


_BASE: KeyframeMsg | None = None


def base_keyframe() -> KeyframeMsg:
    """A valid tiny keyframe (built once; others are ``replace``d copies)."""
    global _BASE
    if _BASE is None:
        _BASE = factories.keyframe(np.random.default_rng(0), n_keypoints=5)
    return _BASE


def keyframe(
    robot: str = "r1",
    session: str = "s1",
    seq: int = 0,
    stamp: float | None = None,
    pose_source: wire.PoseSource = "rgb",
) -> tuple[KeyframeMsg, bytes]:
    """A keyframe with this key (stamp ``T0 + seq`` unless given) and its wire bytes."""
    t = T0 + seq if stamp is None else stamp
    msg = replace(
        base_keyframe(),
        robot_id=robot,
        session_id=session,
        seq=seq,
        stamp=t,
        T_odom_camera=_pose(t - T0),
        pose_source=pose_source,
    )
    return msg, wire.encode(msg)


def pose_at(stamp: float) -> np.ndarray:
    """The ``T_odom_camera`` of :func:`keyframe` at ``stamp``."""
    return _pose(stamp - T0)
