"""Pinhole camera with distortion: projection round trips and validation."""

from __future__ import annotations

import numpy as np
import pytest

from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import GeometryError

FR1 = PinholeCamera(640, 480, 517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633))


@pytest.mark.parametrize("cam", [FR1, PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)])
def test_project_unproject_round_trip(cam: PinholeCamera) -> None:
    """Random points in view project to pixels and back-project to the same 3D points."""
    rng = np.random.default_rng(0)
    uv = np.column_stack([rng.uniform(20, 620, 500), rng.uniform(20, 460, 500)])
    depth = rng.uniform(0.5, 6.0, 500)
    pts = cam.unproject(uv, depth)
    uv2, valid = cam.project(pts)
    assert valid.all()
    assert np.allclose(uv2, uv, atol=1e-6)
    assert np.allclose(pts[:, 2], depth)


def test_distortion_matches_opencv() -> None:
    """Our distortion model agrees with cv2.projectPoints (OpenCV's k1 k2 p1 p2 k3)."""
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-1, 1, 50), rng.uniform(-0.8, 0.8, 50), rng.uniform(1.5, 4, 50)])
    ours, _ = FR1.project(pts)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), FR1.K, np.array(FR1.distortion))
    assert np.allclose(ours, ref.reshape(-1, 2), atol=1e-6)


def test_points_behind_the_camera_are_invalid() -> None:
    """z <= 0 gives valid=False and NaN pixels instead of mirrored projections."""
    uv, valid = FR1.project(np.array([[0.0, 0.0, -1.0], [0.1, 0.1, 2.0]]))
    assert list(valid) == [False, True]
    assert np.isnan(uv[0]).all()


def test_fov_constructor_matches_thermal_spec() -> None:
    """The paper 003 thermal camera: 388x284 with 37.7 x 28.7 degrees."""
    cam = PinholeCamera.from_fov(388, 284, 37.7, 28.7)
    h, v = cam.fov_deg
    assert h == pytest.approx(37.7) and v == pytest.approx(28.7)


@pytest.mark.parametrize(
    "kwargs",
    [dict(width=0), dict(fx=-1.0), dict(cx=float("nan")), dict(distortion=(0.1, 0.2))],
)
def test_bad_intrinsics_are_rejected(kwargs: dict) -> None:
    """Zero size, negative focal length, NaN and a short distortion vector raise."""
    base = dict(width=640, height=480, fx=500.0, fy=500.0, cx=320.0, cy=240.0)
    base.update(kwargs)
    with pytest.raises(GeometryError):
        PinholeCamera(**base)  # type: ignore[arg-type]
