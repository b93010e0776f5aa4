"""Fixtures every test package may use (helpers that are plain functions live in factories.py)."""

from __future__ import annotations

from collections.abc import Iterator

import pgcluster
import pytest
from factories import MeasurementFactory, measurement


@pytest.fixture
def make_measurement() -> MeasurementFactory:
    """Factory: a measurement of a box seen from a camera, with optional position noise
    (:func:`factories.measurement`)."""
    return measurement


@pytest.fixture(scope="session")
def pg_cluster() -> Iterator[pgcluster.Cluster]:
    """One real PostgreSQL 15 cluster for the whole session (tests/pgcluster.py), started on first
    use; skipped with the reason where the server binaries are absent."""
    why = pgcluster.missing()
    if why is not None:
        pytest.skip(why)
    with pgcluster.start_cluster() as cluster:
        yield cluster
