"""Fixtures every test package may use (helpers that are plain functions live in factories.py)."""

from __future__ import annotations

import pytest
from factories import MeasurementFactory, measurement


@pytest.fixture
def make_measurement() -> MeasurementFactory:
    """Factory: a measurement of a box seen from a camera, with optional position noise
    (:func:`factories.measurement`)."""
    return measurement
