"""Wheel odometry of a Kobuki-like differential-drive base: sensor model and dead reckoning.

Paper 003's platform is a Kobuki base: two driven wheels of radius 0.035 m on a track
(wheel base) of 0.230 m, encoders of ~11.7 ticks per mm of wheel travel, a single-axis
yaw gyro, odometry published at 50 Hz. :func:`simulate_odometry` turns a ground-truth
base trajectory into the raw sensor stream (encoder ticks + gyro rate) with a noise
model; :func:`integrate_odometry` is the robot's dead reckoning from that raw stream;
:func:`odometry_error_bound` is the noise model's n-sigma drift bound.

Frames (all right-handed, metres, radians):

- ``world``: the simulator's ground-truth frame, z up.
- ``base``: the robot base on the floor midway between the wheels; x forward, y left, z up.
- ``odom``: the base frame at the first stamp of a stream, so ``T_odom_base[0]`` is the
  identity. The ground truth of ``odom`` in the world is ``T_world_base[0]``.

The model is planar: only x, y and yaw of the ground truth matter; z, roll and pitch are
ignored and the odometry poses lie in the odom frame's z = 0 plane.

Encoder rows (``encoders`` (N, 4)) hold ``stamp_s, left_ticks, right_ticks,
gyro_z_rad_s``. The real Kobuki reports 16-bit wrapping counters; here the tick columns
are cumulative *unwrapped* integer counts stored as float64 (exact below 2**53), starting
at 0 at the first row, which is what a driver holds after unwrapping the 16-bit values.
``gyro_z_rad_s`` of row i is the mean yaw rate over the interval (stamp[i-1], stamp[i]];
row 0 carries the rate of the first interval and is never used by the integrator.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.shared.errors import SimulationError

F64 = NDArray[np.float64]

KOBUKI_ODOMETRY_RATE_HZ = 50.0
"""Rate at which the Kobuki base publishes encoder and gyro samples (Hz)."""

_FLOOR_EPS_TICKS = 1e-9
"""Guard so that an exact integer tick count accumulated in float rounds down to itself."""

_QUANT_TURN_ALLOWANCE_RAD = 8.0
"""Total absolute turning (rad) covered by the quantisation term of the error bound."""


@dataclass(frozen=True)
class OdometryNoise:
    """Noise of the wheel encoders and the yaw gyro; all zero gives perfect odometry."""

    wheel_slip_std: float = 0.01
    """Relative std (unitless) of each wheel's travelled distance in each step (slip)."""

    wheel_scale_error_std: float = 0.003
    """Relative std (unitless) of each wheel's radius error, drawn once per wheel and run."""

    gyro_noise_std_rad_s: float = 0.002
    """Std (rad/s) of the white noise added to each gyro rate sample."""

    gyro_bias_std_rad_s: float = 0.0005
    """Std (rad/s) of the constant gyro bias drawn once per run."""

    gyro_bias_walk_rad_s_sqrt_s: float = 0.0001
    """Random-walk density of the gyro bias (rad/s/sqrt(s)): bias std grows as sqrt(t)."""

    slip_events_per_m: float = 0.0
    """Rate (events per metre of each wheel's travel) of rare large slips; 0 disables them."""

    slip_event_std_m: float = 0.02
    """Std (m) of the extra distance a wheel's encoder reports in one slip event."""

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not np.isfinite(value) or value < 0.0:
                raise SimulationError(f"OdometryNoise.{f.name}: expected finite >= 0, got {value}")

    @classmethod
    def noiseless(cls) -> OdometryNoise:
        """All noise terms zero: odometry is exact up to tick quantisation."""
        return cls(**{f.name: 0.0 for f in fields(cls)})


@dataclass(frozen=True)
class BaseGeometry:
    """Kinematic geometry of the differential-drive base (Kobuki defaults)."""

    wheel_radius_m: float = 0.035
    """Nominal wheel radius (m); only informative (:attr:`ticks_per_rev`), since the
    encoder resolution is given per mm of travel."""

    wheel_base_m: float = 0.230
    """Track (m): distance between the two wheels' contact points."""

    ticks_per_mm: float = 11.7
    """Encoder ticks per mm of nominal wheel travel."""

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not np.isfinite(value) or value <= 0.0:
                raise SimulationError(f"BaseGeometry.{f.name}: expected finite > 0, got {value}")

    @property
    def ticks_per_m(self) -> float:
        """Encoder ticks per metre of nominal wheel travel."""
        return 1000.0 * self.ticks_per_mm

    @property
    def ticks_per_rev(self) -> float:
        """Encoder ticks per wheel revolution (about 2573 for the Kobuki)."""
        return 2.0 * np.pi * self.wheel_radius_m * self.ticks_per_m


@dataclass(frozen=True)
class OdometryStream:
    """What the simulated base reports, N samples.

    Attributes:
        stamps: (N,) sample times in seconds, strictly increasing.
        T_odom_base: (N, 4, 4) the robot's own dead-reckoned poses of base in odom
            (:func:`integrate_odometry` of ``encoders`` with the gyro); identity at index 0.
        encoders: (N, 4) raw rows ``stamp_s, left_ticks, right_ticks, gyro_z_rad_s``;
            ticks are cumulative unwrapped counts (see the module docstring).
    """

    stamps: F64
    T_odom_base: F64
    encoders: F64


def _check_stamps(stamps: ArrayLike, name: str) -> F64:
    t = np.asarray(stamps, dtype=np.float64)
    if t.ndim != 1 or t.shape[0] < 1:
        raise SimulationError(f"{name}: expected shape (N>=1,), got {t.shape}")
    if not np.all(np.isfinite(t)):
        raise SimulationError(f"{name}: contains non-finite values")
    if t.shape[0] > 1 and not np.all(np.diff(t) > 0.0):
        bad = int(np.argmin(np.diff(t))) + 1
        raise SimulationError(
            f"{name}: must be strictly increasing, "
            f"stamp[{bad}]={t[bad]} <= stamp[{bad - 1}]={t[bad - 1]}"
        )
    return t


def _yaw_transforms(x: F64, y: F64, yaw: F64) -> F64:
    """Batched :func:`wardmap.shared.se3.yaw_transform`: (N,) x, y (m), yaw (rad) -> (N, 4, 4)."""
    T = np.zeros((x.shape[0], 4, 4))
    c, s = np.cos(yaw), np.sin(yaw)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 2, 2] = T[:, 3, 3] = 1.0
    T[:, 0, 3], T[:, 1, 3] = x, y
    return T


def _sinc_half(dtheta: F64) -> F64:
    """``sin(dtheta / 2) / (dtheta / 2)``: chord over arc length of a constant-curvature step."""
    return np.sinc(dtheta / (2.0 * np.pi))


def simulate_odometry(
    stamps: ArrayLike,
    T_world_base: ArrayLike,
    geometry: BaseGeometry,
    noise: OdometryNoise,
    rng: np.random.Generator,
) -> OdometryStream:
    """Simulate the Kobuki's encoders and gyro along a ground-truth trajectory.

    Per step i (stamp[i-1] -> stamp[i]) the true planar motion is read from the ground
    truth: ``dtheta`` the yaw change and ``ds`` the arc length of a constant-curvature step
    whose chord is the displacement projected on the mid-step heading (the lateral part is
    not observable by wheels and is dropped). The wheels travel ``ds -/+ dtheta * b / 2``
    (left/right, ``b`` the wheel base). Each wheel's travel is scaled by its per-run scale
    error ``1 + e_w`` and by the step's slip ``1 + n``, plus rare slip events; the
    cumulative travel is floored to whole ticks, so the fractional remainder carries over
    and quantisation never accumulates. The gyro reads the step's mean yaw rate plus a bias
    (constant part drawn once, plus a random walk) plus white noise.

    Random numbers are drawn only from ``rng``, in a fixed order, so a seed fixes the
    output exactly.

    Args:
        stamps: (N,) sample times in seconds, strictly increasing.
        T_world_base: (N, 4, 4) ground-truth poses of the base in the world (z up).
        geometry: the base's geometry.
        noise: the noise model; :meth:`OdometryNoise.noiseless` for exact odometry.
        rng: source of all randomness.

    Returns:
        The raw stream and the robot's dead-reckoned poses (with the gyro) in odom.

    Raises:
        SimulationError: wrong shapes, non-finite values or stamps not strictly increasing.
    """
    t = _check_stamps(stamps, "stamps")
    n = t.shape[0]
    T = np.asarray(T_world_base, dtype=np.float64)
    if T.shape != (n, 4, 4):
        raise SimulationError(f"T_world_base: expected shape ({n}, 4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise SimulationError("T_world_base: contains non-finite values")

    # Ground-truth planar motion per step.
    yaw = np.unwrap(np.arctan2(T[:, 1, 0], T[:, 0, 0]))
    dtheta = np.diff(yaw)
    yaw_mid = yaw[:-1] + 0.5 * dtheta
    dxy = np.diff(T[:, :2, 3], axis=0)
    chord = dxy[:, 0] * np.cos(yaw_mid) + dxy[:, 1] * np.sin(yaw_mid)
    ds = chord / _sinc_half(dtheta)
    half_b = 0.5 * geometry.wheel_base_m
    travel_true_m = np.column_stack([ds - dtheta * half_b, ds + dtheta * half_b])  # (N-1, 2)
    dt = np.diff(t)

    # Noise, drawn in a fixed order.
    scale = 1.0 + noise.wheel_scale_error_std * rng.standard_normal(2)
    bias0 = noise.gyro_bias_std_rad_s * rng.standard_normal()
    slip = 1.0 + noise.wheel_slip_std * rng.standard_normal((n - 1, 2))
    n_events = rng.poisson(noise.slip_events_per_m * np.abs(travel_true_m))
    event_m = noise.slip_event_std_m * np.sqrt(n_events) * rng.standard_normal((n - 1, 2))
    walk = noise.gyro_bias_walk_rad_s_sqrt_s * np.sqrt(dt) * rng.standard_normal(n - 1)
    white = noise.gyro_noise_std_rad_s * rng.standard_normal(n)

    travel_meas_m = travel_true_m * scale * slip + event_m
    cum_ticks = np.cumsum(travel_meas_m * geometry.ticks_per_m, axis=0)
    ticks = np.vstack([np.zeros((1, 2)), np.floor(cum_ticks + _FLOOR_EPS_TICKS)])

    rate_true = dtheta / dt
    rate_true = np.concatenate([rate_true[:1] if n > 1 else np.zeros(1), rate_true])
    bias = bias0 + np.concatenate([[0.0], np.cumsum(walk)])
    gyro = rate_true + bias + white

    encoders = np.column_stack([t, ticks, gyro])
    _, T_odom_base = integrate_odometry(encoders, geometry, use_gyro=True)
    return OdometryStream(stamps=t.copy(), T_odom_base=T_odom_base, encoders=encoders)


def integrate_odometry(
    encoders: ArrayLike, geometry: BaseGeometry, *, use_gyro: bool = True
) -> tuple[F64, F64]:
    """Dead reckoning from raw encoder ticks and gyro, as the robot does it.

    Per step i the distance is the mean of the two wheels' travel,
    ``ds = (dL + dR) / 2`` with ``d = delta_ticks / ticks_per_m``; the heading change is
    ``dtheta = gyro_z[i] * dt`` (Kobuki style) or, with ``use_gyro=False``, the wheel
    difference ``(dR - dL) / b``. Midpoint integration, exact for constant-curvature steps:
    ``p += ds * sinc(dtheta / 2) * (cos, sin)(theta + dtheta / 2)``, ``theta += dtheta``.

    Args:
        encoders: (N, 4) rows ``stamp_s, left_ticks, right_ticks, gyro_z_rad_s`` with
            cumulative unwrapped tick counts; stamps strictly increasing.
        geometry: the base's geometry (``ticks_per_mm``, ``wheel_base_m``).
        use_gyro: heading from the integrated gyro (True) or from the wheels (False).

    Returns:
        ``(stamps, T_odom_base)``: (N,) seconds and (N, 4, 4) poses of base in odom, the
        base frame at the first stamp (identity at index 0); planar, z = 0.

    Raises:
        SimulationError: wrong shape, non-finite values or stamps not strictly increasing.
    """
    E = np.asarray(encoders, dtype=np.float64)
    if E.ndim != 2 or E.shape[1] != 4 or E.shape[0] < 1:
        raise SimulationError(f"encoders: expected shape (N>=1, 4), got {E.shape}")
    if not np.all(np.isfinite(E)):
        raise SimulationError("encoders: contains non-finite values")
    t = _check_stamps(E[:, 0], "encoders[:, 0] (stamps)")

    d_m = np.diff(E[:, 1:3], axis=0) / geometry.ticks_per_m  # (N-1, 2) left, right
    ds = 0.5 * (d_m[:, 0] + d_m[:, 1])
    # Heading change per step (rad): integrated gyro rate, or differential wheel travel.
    dtheta = E[1:, 3] * np.diff(t) if use_gyro else (d_m[:, 1] - d_m[:, 0]) / geometry.wheel_base_m
    yaw = np.concatenate([[0.0], np.cumsum(dtheta)])
    yaw_mid = yaw[:-1] + 0.5 * dtheta
    chord = ds * _sinc_half(dtheta)
    x = np.concatenate([[0.0], np.cumsum(chord * np.cos(yaw_mid))])
    y = np.concatenate([[0.0], np.cumsum(chord * np.sin(yaw_mid))])
    return t.copy(), _yaw_transforms(x, y, yaw)


def odometry_error_bound(
    distance_m: float,
    duration_s: float,
    noise: OdometryNoise,
    geometry: BaseGeometry,
    sigmas: float = 3.0,
    *,
    use_gyro: bool = True,
    rate_hz: float = KOBUKI_ODOMETRY_RATE_HZ,
) -> tuple[float, float]:
    """The noise model's n-sigma bound of accumulated odometry drift.

    Bounds the final position error (m, Euclidean norm) and yaw error (rad) of
    :func:`integrate_odometry` after the base drove ``distance_m`` along its path in
    ``duration_s``. Independent error sources are summed in quadrature into a 1-sigma
    value, multiplied by ``sigmas``, and a worst-case tick-quantisation term is added.
    Notation: D distance, T duration, v = D / T, dt = 1 / rate_hz, n = T / dt steps of
    mean length h = D / n, b wheel base, q one tick in metres.

    Along-track (distance) error, with either heading source:

    - wheel scale error: the mean of two independent per-wheel errors, std
      ``sigma_scale / sqrt(2)``, scales all of D: ``D * sigma_scale / sqrt(2)``.
    - per-step slip: n independent terms of std ``sigma_slip * h / sqrt(2)`` (mean of two
      wheels): ``sigma_slip * sqrt(D * h / 2)`` (sqrt of distance over step count).
    - slip events: Poisson, lambda * D per wheel, each of std s: ``s * sqrt(lambda * D / 2)``.

    Yaw error with the gyro (``use_gyro=True``, wheels do not affect heading):

    - constant bias: grows linearly with time, ``sigma_bias * T``.
    - bias random walk of density w: yaw is its integral, ``w * T**1.5 / sqrt(3)``.
    - white rate noise: a yaw random walk, ``sigma_gyro * dt * sqrt(n) = sigma_gyro *
      sqrt(dt * T)``.

    Yaw error from the wheels (``use_gyro=False``), assuming both wheels travel about D:

    - scale error: ``(e_R - e_L) * D / b``, std ``sqrt(2) * sigma_scale * D / b``
      (linear in distance).
    - slip: ``sigma_slip * sqrt(2 * D * h) / b``; slip events: ``s * sqrt(2 * lambda * D) / b``.

    Lateral error: a yaw error psi(t) moves the base sideways at ``v * psi(t)``, so the
    lateral error is ``v * integral(psi dt)`` — for a straight path (the worst case; turns
    make the terms partly cancel): a yaw error growing linearly (bias; wheel scale
    error) gives ``final_yaw * D / 2``; a yaw random walk (white gyro noise; slip) gives
    ``final_yaw * D / sqrt(3)``; the integrated bias walk gives ``w * v * T**2.5 /
    sqrt(20)``.

    Quantisation (added, not in quadrature): cumulative counts keep the fractional
    remainder, so the distance is off by less than one tick at any time; summed over
    the heading changes along the path this is at most ``q * (2 + turning)``, taken with
    an allowance of 8 rad of total turning. Heading from the wheels is additionally off by
    less than ``q / b`` at any time, which can shift the position by up to ``D * q / b``.

    The bound is a Gaussian small-angle approximation: it assumes modest speed variation
    (the slip term uses the mean step) and yaw errors well below a radian.

    Args:
        distance_m: path length driven (m), >= 0.
        duration_s: time taken (s), >= 0.
        noise: the noise model.
        geometry: the base's geometry.
        sigmas: how many standard deviations the bound spans (> 0).
        use_gyro: bound for gyro heading (True) or wheel heading (False).
        rate_hz: odometry sample rate (Hz) used for the per-step terms.

    Returns:
        ``(pos_bound_m, yaw_bound_rad)``.

    Raises:
        SimulationError: negative or non-finite distance or duration, non-positive sigmas
            or rate.
    """
    if not (np.isfinite(distance_m) and distance_m >= 0.0):
        raise SimulationError(f"distance_m: expected finite >= 0, got {distance_m}")
    if not (np.isfinite(duration_s) and duration_s >= 0.0):
        raise SimulationError(f"duration_s: expected finite >= 0, got {duration_s}")
    if not (np.isfinite(sigmas) and sigmas > 0.0):
        raise SimulationError(f"sigmas: expected finite > 0, got {sigmas}")
    if not (np.isfinite(rate_hz) and rate_hz > 0.0):
        raise SimulationError(f"rate_hz: expected finite > 0, got {rate_hz}")

    D, T = float(distance_m), float(duration_s)
    b = geometry.wheel_base_m
    q = 1.0 / geometry.ticks_per_m
    dt = 1.0 / rate_hz
    n_steps = max(T * rate_hz, 1.0)
    h = D / n_steps
    v = D / T if T > 0.0 else 0.0
    lam, s_ev = noise.slip_events_per_m, noise.slip_event_std_m

    along = np.hypot.reduce(
        [
            D * noise.wheel_scale_error_std / np.sqrt(2.0),
            noise.wheel_slip_std * np.sqrt(D * h / 2.0),
            s_ev * np.sqrt(lam * D / 2.0),
        ]
    )
    if use_gyro:
        yaw_linear = noise.gyro_bias_std_rad_s * T
        yaw_walk = noise.gyro_noise_std_rad_s * np.sqrt(dt * T)
        yaw_bias_walk = noise.gyro_bias_walk_rad_s_sqrt_s * T**1.5 / np.sqrt(3.0)
        lateral_bias_walk = noise.gyro_bias_walk_rad_s_sqrt_s * v * T**2.5 / np.sqrt(20.0)
        yaw_quant = 0.0
        pos_quant = q * (2.0 + _QUANT_TURN_ALLOWANCE_RAD)
    else:
        yaw_linear = np.sqrt(2.0) * noise.wheel_scale_error_std * D / b
        yaw_walk = float(
            np.hypot(
                noise.wheel_slip_std * np.sqrt(2.0 * D * h) / b,
                s_ev * np.sqrt(2.0 * lam * D) / b,
            )
        )
        yaw_bias_walk = lateral_bias_walk = 0.0
        yaw_quant = q / b
        pos_quant = q * (2.0 + _QUANT_TURN_ALLOWANCE_RAD) + D * q / b
    lateral = np.hypot.reduce(
        [yaw_linear * D / 2.0, yaw_walk * D / np.sqrt(3.0), lateral_bias_walk]
    )
    yaw_sigma = np.hypot.reduce([yaw_linear, yaw_walk, yaw_bias_walk])
    pos_sigma = np.hypot(along, lateral)
    return float(sigmas * pos_sigma + pos_quant), float(sigmas * yaw_sigma + yaw_quant)
