"""Tests of the Kobuki wheel-odometry model (:mod:`wardmap.sim.odometry`).

Ground truth is built here from piecewise-constant (forward speed, yaw rate) segments,
integrated exactly (constant curvature per step) at the Kobuki's 50 Hz and turned into
poses with :func:`wardmap.shared.se3.yaw_transform`.
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from wardmap.shared.errors import SimulationError
from wardmap.shared.se3 import inverse, yaw_transform
from wardmap.sim.odometry import (
    KOBUKI_ODOMETRY_RATE_HZ,
    BaseGeometry,
    OdometryNoise,
    integrate_odometry,
    odometry_error_bound,
    simulate_odometry,
)

F64 = NDArray[np.float64]
RATE_HZ = KOBUKI_ODOMETRY_RATE_HZ

# (forward speed m/s, yaw rate rad/s, duration s) segments.
Segments = list[tuple[float, float, float]]
PATHS: dict[str, Segments] = {
    "straight": [(0.5, 0.0, 4.0)],
    "circle_arc": [(0.4, 0.8, 6.0)],  # radius 0.5 m, 4.8 rad of turning
    "s_curve": [(0.5, 0.0, 1.0), (0.5, 0.6, 3.0), (0.5, -0.6, 3.0), (0.5, 0.0, 1.0)],
    "spin_in_place": [(0.0, 0.5, 4.0), (0.0, -0.5, 2.0)],
}
# 20 m at 0.5 m/s: 8 m straight, left 90° turn (r = 1 m), 6 m, right 90° turn, rest straight.
TWENTY_M: Segments = [
    (0.5, 0.0, 16.0),
    (0.5, 0.5, np.pi),
    (0.5, 0.0, 12.0),
    (0.5, -0.5, np.pi),
    (0.5, 0.0, (20.0 - 14.0 - np.pi) / 0.5),
]


def make_ground_truth(
    segments: Segments, start: tuple[float, float, float] = (3.0, -2.0, 1.0), t0: float = 100.0
) -> tuple[F64, F64, float]:
    """Stamps (N,) s, ``T_world_base`` (N, 4, 4) and path length (m) of ``segments``."""
    dt = 1.0 / RATE_HZ
    x, y, yaw = start
    poses = [yaw_transform(x, y, yaw)]
    length_m = 0.0
    for v, w, duration in segments:
        for _ in range(round(duration * RATE_HZ)):
            chord = v * dt * np.sinc(w * dt / (2.0 * np.pi))
            x += chord * np.cos(yaw + 0.5 * w * dt)
            y += chord * np.sin(yaw + 0.5 * w * dt)
            yaw += w * dt
            length_m += abs(v) * dt
            poses.append(yaw_transform(x, y, yaw))
    stamps = t0 + np.arange(len(poses)) / RATE_HZ
    return stamps, np.array(poses), length_m


def relative_to_first(T_world_base: F64) -> F64:
    """Ground truth of ``T_odom_base`` (N, 4, 4): the odom frame is the first base pose."""
    return np.einsum("ij,njk->nik", inverse(T_world_base[0]), T_world_base)


def yaw_of(T: F64) -> F64:
    """Yaw (rad) of (..., 4, 4) planar transforms."""
    return np.arctan2(T[..., 1, 0], T[..., 0, 0])


def wrap(angle: F64) -> F64:
    return np.angle(np.exp(1j * angle))


@pytest.mark.parametrize("use_gyro", [True, False], ids=["gyro", "wheels"])
@pytest.mark.parametrize("name", list(PATHS))
def test_noiseless_round_trip_reproduces_ground_truth(name: str, use_gyro: bool) -> None:
    """Zero noise, straight line / circle arc / S curve / spin in place, starting away from
    the world origin: integrating the simulated encoders (heading from the gyro or from
    the wheels) gives the ground truth relative to the first pose, within the tick
    quantisation term of the error bound, and the identity at index 0."""
    geometry, noise = BaseGeometry(), OdometryNoise.noiseless()
    stamps, T_world_base, length_m = make_ground_truth(PATHS[name])
    stream = simulate_odometry(stamps, T_world_base, geometry, noise, np.random.default_rng(0))
    out_stamps, T_odom_base = integrate_odometry(stream.encoders, geometry, use_gyro=use_gyro)

    pos_tol, yaw_tol = odometry_error_bound(
        length_m, stamps[-1] - stamps[0], noise, geometry, use_gyro=use_gyro
    )
    truth = relative_to_first(T_world_base)
    np.testing.assert_array_equal(out_stamps, stamps)
    np.testing.assert_allclose(T_odom_base[0], np.eye(4), atol=1e-12)
    pos_err = np.linalg.norm(T_odom_base[:, :2, 3] - truth[:, :2, 3], axis=1)
    yaw_err = np.abs(wrap(yaw_of(T_odom_base) - yaw_of(truth)))
    assert pos_err.max() <= pos_tol
    assert yaw_err.max() <= yaw_tol + 1e-9
    np.testing.assert_allclose(T_odom_base[:, 2, :], [[0.0, 0.0, 1.0, 0.0]] * len(stamps))
    if use_gyro:
        np.testing.assert_allclose(stream.T_odom_base, T_odom_base)


@pytest.mark.parametrize("use_gyro", [True, False], ids=["gyro", "wheels"])
def test_default_noise_drift_within_bound_and_bound_not_vacuous(use_gyro: bool) -> None:
    """Default noise, 200 seeded runs of a 20 m path (straight, left and right 90° turns,
    0.5 m/s, 50 Hz): the final position and yaw errors stay within the 3-sigma
    odometry_error_bound in at least 97% of runs, and the errors' RMS is at least 20% of
    the 1-sigma bound, so the bound is not absurdly loose."""
    geometry, noise = BaseGeometry(), OdometryNoise()
    stamps, T_world_base, length_m = make_ground_truth(TWENTY_M)
    assert length_m == pytest.approx(20.0, abs=0.02)
    truth_final = relative_to_first(T_world_base)[-1]
    duration_s = stamps[-1] - stamps[0]

    rng = np.random.default_rng(2024)
    pos_err, yaw_err = np.empty(200), np.empty(200)
    for k in range(200):
        stream = simulate_odometry(stamps, T_world_base, geometry, noise, rng)
        _, T_odom_base = integrate_odometry(stream.encoders, geometry, use_gyro=use_gyro)
        pos_err[k] = np.linalg.norm(T_odom_base[-1, :2, 3] - truth_final[:2, 3])
        yaw_err[k] = abs(wrap(yaw_of(T_odom_base[-1]) - yaw_of(truth_final)))

    pos_3s, yaw_3s = odometry_error_bound(length_m, duration_s, noise, geometry, use_gyro=use_gyro)
    pos_1s, yaw_1s = odometry_error_bound(
        length_m, duration_s, noise, geometry, sigmas=1.0, use_gyro=use_gyro
    )
    assert np.mean(pos_err <= pos_3s) >= 0.97
    assert np.mean(yaw_err <= yaw_3s) >= 0.97
    assert np.sqrt(np.mean(pos_err**2)) >= 0.2 * pos_1s
    assert np.sqrt(np.mean(yaw_err**2)) >= 0.2 * yaw_1s


def test_one_metre_straight_gives_about_11700_ticks_per_wheel() -> None:
    """A 1 m straight move at 0.5 m/s: each wheel counts 11.7 ticks/mm * 1000 mm = 11700
    ticks (within one tick without noise; within the wheel scale error with default
    noise), counters start at 0 and hold whole counts."""
    geometry = BaseGeometry()
    stamps, T_world_base, _ = make_ground_truth([(0.5, 0.0, 2.0)])
    for noise, rel_tol in ((OdometryNoise.noiseless(), 1.0 / 11700.0), (OdometryNoise(), 0.02)):
        stream = simulate_odometry(stamps, T_world_base, geometry, noise, np.random.default_rng(7))
        ticks = stream.encoders[:, 1:3]
        np.testing.assert_array_equal(ticks[0], [0.0, 0.0])
        np.testing.assert_array_equal(ticks, np.round(ticks))
        np.testing.assert_allclose(ticks[-1], [11700.0, 11700.0], rtol=rel_tol)
    assert geometry.ticks_per_rev == pytest.approx(2573.0, abs=1.0)


def test_standing_still_counts_no_ticks_and_gyro_bias_drifts_heading() -> None:
    """Base at rest for 10 s with only a constant gyro bias: no wheel travel so no ticks
    (slip is relative to travel); the gyro reads a constant rate and the integrated yaw
    drifts by exactly rate * duration."""
    geometry = BaseGeometry()
    noise = OdometryNoise(**{**vars(OdometryNoise.noiseless()), "gyro_bias_std_rad_s": 0.01})
    stamps, T_world_base, _ = make_ground_truth([(0.0, 0.0, 10.0)])
    stream = simulate_odometry(stamps, T_world_base, geometry, noise, np.random.default_rng(3))
    np.testing.assert_array_equal(stream.encoders[:, 1:3], 0.0)
    gyro = stream.encoders[:, 3]
    np.testing.assert_allclose(gyro, gyro[0], rtol=0, atol=1e-15)
    assert gyro[0] != 0.0
    assert yaw_of(stream.T_odom_base[-1]) == pytest.approx(gyro[0] * 10.0, rel=1e-9)
    np.testing.assert_allclose(stream.T_odom_base[:, :2, 3], 0.0, atol=1e-15)


def test_same_seed_gives_identical_streams() -> None:
    """Default noise with slip events on the S curve: two runs with the same seed give
    bit-identical arrays, a different seed gives different ticks and gyro."""
    geometry = BaseGeometry()
    noise = OdometryNoise(slip_events_per_m=0.5)
    stamps, T_world_base, _ = make_ground_truth(PATHS["s_curve"])
    a = simulate_odometry(stamps, T_world_base, geometry, noise, np.random.default_rng(11))
    b = simulate_odometry(stamps, T_world_base, geometry, noise, np.random.default_rng(11))
    c = simulate_odometry(stamps, T_world_base, geometry, noise, np.random.default_rng(12))
    np.testing.assert_array_equal(a.stamps, b.stamps)
    np.testing.assert_array_equal(a.encoders, b.encoders)
    np.testing.assert_array_equal(a.T_odom_base, b.T_odom_base)
    assert not np.array_equal(a.encoders[:, 1:], c.encoders[:, 1:])


def _bad_inputs() -> list[tuple[str, F64, F64]]:
    stamps, T, _ = make_ground_truth(PATHS["straight"])
    swapped = stamps.copy()
    swapped[[5, 6]] = swapped[[6, 5]]
    repeated = stamps.copy()
    repeated[6] = repeated[5]
    nan_T = T.copy()
    nan_T[3, 0, 3] = np.nan
    return [
        ("non_monotonic_stamps", swapped, T),
        ("repeated_stamp", repeated, T),
        ("stamps_2d", stamps[:, None], T),
        ("length_mismatch", stamps[:-1], T),
        ("poses_3x3", stamps, T[:, :3, :3]),
        ("nan_pose", stamps, nan_T),
        ("empty", stamps[:0], T[:0]),
    ]


@pytest.mark.parametrize(("stamps", "T_world_base"), [c[1:] for c in _bad_inputs()],
                         ids=[c[0] for c in _bad_inputs()])
def test_simulate_rejects_bad_input(stamps: F64, T_world_base: F64) -> None:
    """Malformed ground truth (unordered or repeated stamps, wrong shapes, NaN, empty)
    raises SimulationError."""
    with pytest.raises(SimulationError):
        simulate_odometry(stamps, T_world_base, BaseGeometry(), OdometryNoise(),
                          np.random.default_rng(0))


def test_integrate_and_parameters_reject_bad_input() -> None:
    """Encoders of the wrong shape, with NaN or with non-monotonic stamps, negative noise
    or geometry parameters, and a negative distance for the bound raise SimulationError."""
    stamps, T, _ = make_ground_truth(PATHS["straight"])
    enc = simulate_odometry(stamps, T, BaseGeometry(), OdometryNoise(), np.random.default_rng(0))
    good = enc.encoders
    unordered = good.copy()
    unordered[[3, 4], 0] = unordered[[4, 3], 0]
    with_nan = good.copy()
    with_nan[2, 3] = np.nan
    for bad in (good[:, :3], good[0], unordered, with_nan):
        with pytest.raises(SimulationError):
            integrate_odometry(bad, BaseGeometry())
    with pytest.raises(SimulationError):
        OdometryNoise(wheel_slip_std=-0.1)
    with pytest.raises(SimulationError):
        BaseGeometry(wheel_base_m=0.0)
    with pytest.raises(SimulationError):
        odometry_error_bound(-1.0, 10.0, OdometryNoise(), BaseGeometry())
