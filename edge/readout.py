"""Self-calibration of the colour camera's rolling-shutter readout time, without ground truth.

Most RGB-D colour cameras (the Kinect among them) expose the image row by row: with
the camera turning at 100 deg/s and a 20 ms readout, the last row sees the scene 2 deg
later than the first, which a global-shutter pose estimate partly absorbs as a
translation of several centimetres. The tracker undoes this when the calibration gives
the readout time (``[rgb] readout_s``, or its ``[rgb] sensor``'s default:
:mod:`wardmap.shared.sensors`), fitting each frame's own spin with its pose
(:func:`wardmap.edge.pose.refine_pose_rolling_shutter`). This estimate is an offline check.

The readout time is seldom published. :func:`estimate_readout` finds it from a recording
with some rotation in it: it tracks the frames once per candidate time and keeps the one
under which the most keypoints fit one rigid pose (mean inliers per frame; the peak is
placed between grid points by a parabola through the best candidate and its neighbours).
No ground truth is used. A recording that barely turns cannot tell readout times apart (the
curve is flat within noise: on a simulated global-shutter drive the best candidate fits 1 %
more keypoints than 0 ms, at a random time); unless the best candidate beats 0 ms by
``min_gain`` (3 %), the estimate is 0 and marked not decisive.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from wardmap.edge.offline import odom_at
from wardmap.edge.tracker import Tracker, TrackerConfig, TrackInput
from wardmap.shared.dataset import MAX_READOUT_S, DatasetReader
from wardmap.shared.errors import WardmapError

log = logging.getLogger(__name__)

DEFAULT_CANDIDATES_S: tuple[float, ...] = tuple(round(0.0025 * i, 4) for i in range(17))
"""0 to 40 ms in 2.5 ms steps."""


@dataclass(frozen=True)
class ReadoutEstimate:
    """Result of :func:`estimate_readout`.

    Attributes:
        readout_s: the chosen readout time, seconds.
        candidates_s: (K,) candidate times tried, seconds, increasing.
        inliers_per_frame: (K,) mean pose inliers per frame under each candidate (lost
            frames count 0): the criterion.
        frames: frames tracked per candidate.
        gain: relative gain in inliers per frame of the best candidate over 0 ms.
        decisive: the gain reached ``min_gain`` (else ``readout_s`` is 0: no evidence of a
            rolling shutter in this recording).
    """

    readout_s: float
    candidates_s: tuple[float, ...]
    inliers_per_frame: tuple[float, ...]
    frames: int
    gain: float
    decisive: bool


def estimate_readout(
    reader: DatasetReader,
    config: TrackerConfig | None = None,
    *,
    candidates_s: Sequence[float] = DEFAULT_CANDIDATES_S,
    max_frames: int = 300,
    min_gain: float = 0.03,
    progress: Callable[[float, float], None] | None = None,
) -> ReadoutEstimate:
    """The readout time under which the tracker fits the most keypoints (module docstring).

    Cost: one tracking run over ``max_frames`` frames per candidate (about 25 s for the
    default 17 candidates and 100 VGA frames on one core).

    Args:
        reader: the recording (its calibration's own ``rgb_readout_s`` is ignored).
        config: tracker settings (defaults if None).
        candidates_s: readout times to try, seconds, each in [0, ``MAX_READOUT_S``].
        max_frames: track at most this many frames from the start.
        min_gain: smallest relative gain in inliers per frame over 0 ms that counts as
            evidence (0 is always tried).
        progress: called with (candidate, mean inliers per frame) after each candidate.

    Raises:
        WardmapError: no candidates, a candidate out of range, fewer than 10 frames, or
            no candidate tracked any frame (nothing to compare).
    """
    cands = sorted({0.0, *(float(c) for c in candidates_s)})
    if len(cands) < 2:
        raise WardmapError("estimate_readout: no candidate readout times besides 0")
    if cands[0] < 0 or cands[-1] > MAX_READOUT_S:
        raise WardmapError(
            f"readout candidates must lie in [0, {MAX_READOUT_S}] s, got {cands[0]}..{cands[-1]}"
        )
    n = min(len(reader), max_frames)
    if n < 10:
        raise WardmapError(f"{reader.root}: {n} frames; the readout estimate needs at least 10 with motion")
    odo = reader.odometry()
    frames = [reader.frame(i) for i in range(n)]
    odoms = [odom_at(odo, f.stamp) for f in frames]
    per_frame = []
    for c in cands:
        tracker = Tracker(replace(reader.calibration, rgb_readout_s=c), config)
        inliers = 0
        for f, T_odom in zip(frames, odoms, strict=True):
            res = tracker.track(TrackInput(f.stamp, f.rgb, f.depth_m, f.thermal_k, T_odom))
            inliers += 0 if res.lost else res.n_inliers
        per_frame.append(inliers / n)
        log.info("readout %.1f ms: %.1f inliers per frame", 1e3 * c, per_frame[-1])
        if progress is not None:
            progress(c, per_frame[-1])
    if max(per_frame) <= 0:
        raise WardmapError(f"{reader.root}: no frame tracked under any readout time; cannot estimate it")
    gain = max(per_frame) / max(per_frame[0], 1e-9) - 1.0
    decisive = gain >= min_gain
    if not decisive:
        log.warning(
            "%s: readout times are not told apart (best %+.1f %% inliers over 0 ms, need %.0f %%); "
            "keeping 0 (global shutter). Record the camera turning to estimate it.",
            reader.root, 100 * gain, 100 * min_gain,
        )
    best = _peak(cands, per_frame) if decisive else 0.0
    return ReadoutEstimate(best, tuple(cands), tuple(per_frame), n, float(gain), decisive)


def _peak(x: Sequence[float], y: Sequence[float]) -> float:
    """Argmax of y over x, refined by the parabola through the best point and its two
    neighbours (when it has both and they are evenly spaced)."""
    k = int(np.argmax(y))
    if 0 < k < len(x) - 1 and abs((x[k + 1] - x[k]) - (x[k] - x[k - 1])) < 1e-9:
        curv = y[k - 1] - 2.0 * y[k] + y[k + 1]
        if curv < 0:
            shift = 0.5 * (y[k - 1] - y[k + 1]) / curv  # in steps, within [-0.5, 0.5]
            return float(round(x[k] + shift * (x[k + 1] - x[k]), 5))
    return float(x[k])


__all__ = ["DEFAULT_CANDIDATES_S", "ReadoutEstimate", "estimate_readout"]
