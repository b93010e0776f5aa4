"""Trajectory metrics (evo): absolute trajectory error after alignment, relative pose error.

Thin wrappers around evo's ``core`` (pure math), so every tool in wardmap scores
trajectories the same way: associate by stamp, align (SE3 by default, Umeyama/Horn),
then the RMSE of translation differences (metres). The relative pose error (RPE) is the
frame-to-frame drift: the translation of ``inv(inv(Q_i) Q_{i+1}) inv(P_i) P_{i+1}`` (Sturm
et al. 2012, Eq. 1), which needs no alignment.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.shared.errors import DatasetError

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class AteResult:
    """Translation error statistics (metres) over ``n`` associated poses (ATE) or pose pairs (RPE)."""

    rmse: float
    mean: float
    median: float
    max: float
    n: int


@dataclass(frozen=True)
class AteSeries:
    """The associated, aligned poses behind an :class:`AteResult` (for plots).

    Attributes:
        stamps: (N,) the reference's stamps of the associated poses, seconds.
        positions_ref: (N, 3) reference camera positions, metres, in the reference's world frame.
        positions_est: (N, 3) estimated camera positions after the alignment, same frame.
        errors_m: (N,) translation error of each pose, metres.
    """

    stamps: F64
    positions_ref: F64
    positions_est: F64
    errors_m: F64


def ate(
    stamps_est: ArrayLike,
    T_est: ArrayLike,
    stamps_ref: ArrayLike,
    T_ref: ArrayLike,
    *,
    align: Literal["se3", "sim3", "none"] = "se3",
    max_diff_s: float = 0.02,
) -> AteResult:
    """ATE of an estimate (N, 4, 4) against a reference (M, 4, 4), both ``T_world_camera``.

    Poses are associated by nearest stamp within ``max_diff_s`` (evo's sync), the estimate
    is aligned to the reference (``se3``: rotation + translation; ``sim3``: plus scale),
    and the translation error statistics are returned.

    Raises:
        DatasetError: fewer than 3 associated poses.
    """
    return ate_series(stamps_est, T_est, stamps_ref, T_ref, align=align, max_diff_s=max_diff_s)[0]


def ate_series(
    stamps_est: ArrayLike,
    T_est: ArrayLike,
    stamps_ref: ArrayLike,
    T_ref: ArrayLike,
    *,
    align: Literal["se3", "sim3", "none"] = "se3",
    max_diff_s: float = 0.02,
) -> tuple[AteResult, AteSeries]:
    """:func:`ate` and the poses and errors it came from (same arguments, same errors)."""
    from evo.core import metrics

    ref_s, est_s = _associated(stamps_est, T_est, stamps_ref, T_ref, max_diff_s)
    if align != "none":
        est_s.align(ref_s, correct_scale=(align == "sim3"))
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref_s, est_s))
    s = ape.get_all_statistics()
    result = AteResult(
        float(s["rmse"]), float(s["mean"]), float(s["median"]), float(s["max"]), int(ref_s.num_poses)
    )
    series = AteSeries(
        np.asarray(ref_s.timestamps, np.float64), np.asarray(ref_s.positions_xyz, np.float64),
        np.asarray(est_s.positions_xyz, np.float64), np.asarray(ape.error, np.float64),
    )
    return result, series


def _associated(
    stamps_est: ArrayLike, T_est: ArrayLike, stamps_ref: ArrayLike, T_ref: ArrayLike, max_diff_s: float
) -> tuple[Any, Any]:
    """evo trajectories (reference, estimate) associated by nearest stamp within ``max_diff_s``."""
    from evo.core import sync
    from evo.core.trajectory import PoseTrajectory3D

    est = PoseTrajectory3D(
        poses_se3=list(np.asarray(T_est, np.float64)), timestamps=np.asarray(stamps_est, np.float64)
    )
    ref = PoseTrajectory3D(
        poses_se3=list(np.asarray(T_ref, np.float64)), timestamps=np.asarray(stamps_ref, np.float64)
    )
    try:
        ref_s, est_s = sync.associate_trajectories(ref, est, max_diff=max_diff_s)
    except sync.SyncException as exc:
        raise DatasetError(f"cannot associate trajectories: {exc}") from exc
    if ref_s.num_poses < 3:
        raise DatasetError(f"only {ref_s.num_poses} poses associate within {max_diff_s} s")
    return ref_s, est_s


def rpe(
    stamps_est: ArrayLike,
    T_est: ArrayLike,
    stamps_ref: ArrayLike,
    T_ref: ArrayLike,
    *,
    max_diff_s: float = 0.02,
) -> AteResult:
    """Frame-to-frame relative pose error, translation part (metres per frame).

    Poses (N, 4, 4) and (M, 4, 4) ``T_world_camera`` are associated as in :func:`ate`;
    each pair of consecutive associated poses gives one error (evo's RPE, delta 1 frame).

    Raises:
        DatasetError: fewer than 3 associated poses.
    """
    from evo.core import metrics

    ref_s, est_s = _associated(stamps_est, T_est, stamps_ref, T_ref, max_diff_s)
    r = metrics.RPE(metrics.PoseRelation.translation_part, delta=1, delta_unit=metrics.Unit.frames)
    r.process_data((ref_s, est_s))
    s = r.get_all_statistics()
    return AteResult(float(s["rmse"]), float(s["mean"]), float(s["median"]), float(s["max"]), len(r.error))
