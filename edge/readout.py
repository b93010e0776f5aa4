"""Self-calibration of the colour camera's rolling-shutter readout time, without ground truth.

Most RGB-D colour cameras (the Kinect among them) expose the image row by row: with
the camera turning at 100 deg/s and a 20 ms readout, the last row sees the scene 2 deg
later than the first, which a global-shutter pose estimate partly absorbs as a
translation of several centimetres. The tracker undoes this when the calibration gives
the readout time (``[rgb] readout_s``, or its ``[rgb] sensor``'s default:
:mod:`wardmap.shared.sensors`), fitting each frame's own spin with its pose
(:func:`wardmap.edge.pose.refine_pose_rolling_shutter`). This estimate is an offline check.

The readout time is seldom published. :func:`estimate_readout` finds it from a recording
with some rotation in it (offline, ``wardmap calibrate-readout``; or online while tracking, a
window of the first turning frames, :class:`OnlineReadout`): it tracks the frames once per
candidate time and keeps the one under which the most keypoints fit one rigid pose (mean
inliers per frame; the peak is placed between grid points by a parabola through the best
candidate and its neighbours).
No ground truth is used. A recording that barely turns cannot tell readout times apart (the
curve is flat within noise: on a simulated global-shutter drive the best candidate fits 1 %
more keypoints than 0 ms, at a random time); unless the best candidate beats 0 ms by
``min_gain`` (3 %), the estimate is 0 and marked not decisive.

Online (:class:`OnlineReadout`), when the recording says nothing of its readout (no ``[rgb]
readout_s``, no sensor with a known default): the tracking loop offers each frame with its
tracked pose; frames are kept in a window of ``window`` frames, and once a window has turned
``min_turn_deg`` the candidates (0-40 ms every 10 ms, parabola between them) are scored on it,
in a child process at niceness 19 for a live source (the tracker keeps its core) or in line for a recording
(the result does not depend on timing). A decisive result replaces the tracker's readout from
the next frame on; an undecided window is dropped and the next one tried, ``max_attempts``
times at most. Earlier frames keep the global-shutter model they were tracked with.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import os
import shutil
import tempfile
import threading
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wardmap.edge.tracker import Tracker, TrackerConfig, TrackInput, TrackResult
from wardmap.shared.dataset import MAX_READOUT_S, Calibration, DatasetReader, odom_at
from wardmap.shared.errors import WardmapError
from wardmap.shared.priority import nice_this_thread
from wardmap.shared.se3 import rotation_angle
from wardmap.shared.sensors import ReadoutModel

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
    inputs = [TrackInput(f.stamp, f.rgb, f.depth_m, f.thermal_k, odom_at(odo, f.stamp)) for f in frames]
    per_frame = score_candidates(inputs, reader.calibration, config, cands, progress)
    if max(per_frame) <= 0:
        raise WardmapError(f"{reader.root}: no frame tracked under any readout time; cannot estimate it")
    est = _decide(cands, per_frame, n, min_gain)
    if not est.decisive:
        log.warning(
            "%s: readout times are not told apart (best %+.1f %% inliers over 0 ms, need %.0f %%); "
            "keeping 0 (global shutter). Record the camera turning to estimate it.",
            reader.root, 100 * est.gain, 100 * min_gain,
        )
    return est


def score_candidates(inputs: Sequence[TrackInput], calibration: Calibration, config: TrackerConfig | None,
                     candidates_s: Sequence[float],
                     progress: Callable[[float, float], None] | None = None) -> list[float]:
    """Mean pose inliers per frame (lost frames count 0) of ``inputs`` tracked from the start
    under each candidate readout time, seconds."""
    per_frame = []
    config = config or TrackerConfig()
    config = replace(config, local_ba=replace(config.local_ba, enabled=False))  # inliers only: no BA
    for c in candidates_s:
        tracker = Tracker(replace(calibration, rgb_readout_s=c), config)
        inliers = 0
        for inp in inputs:
            res = tracker.track(inp)
            inliers += 0 if res.lost else res.n_inliers
        per_frame.append(inliers / max(len(inputs), 1))
        log.info("readout %.1f ms: %.1f inliers per frame", 1e3 * c, per_frame[-1])
        if progress is not None:
            progress(c, per_frame[-1])
    return per_frame


def _decide(cands: Sequence[float], per_frame: Sequence[float], frames: int,
            min_gain: float) -> ReadoutEstimate:
    """The estimate from candidates' scores (``cands[0]`` is 0 ms)."""
    gain = max(per_frame) / max(per_frame[0], 1e-9) - 1.0
    decisive = gain >= min_gain
    best = _peak(cands, per_frame) if decisive else 0.0
    return ReadoutEstimate(best, tuple(cands), tuple(per_frame), frames, float(gain), decisive)


@dataclass(frozen=True)
class OnlineReadoutConfig:
    """:class:`OnlineReadout` settings (``wardmap track`` and the edge use the defaults; a
    calibration's ``[rgb] readout_s``, 0 for a global shutter, turns the estimate off).

    Attributes:
        enabled: estimate the readout while tracking when the recording does not give it.
        window: frames per attempt (tracked again once per candidate).
        min_turn_deg: tracked rotation a window must hold, degrees (a straight drive tells little).
        candidates_s: readout times scored, seconds (0 is always added).
        min_gain: a candidate must fit this much more inliers per frame than 0 ms.
        max_attempts: windows scored before giving up (the global-shutter model stays).
    """

    enabled: bool = True
    window: int = 50
    min_turn_deg: float = 15.0
    candidates_s: tuple[float, ...] = (0.01, 0.02, 0.03, 0.04)
    min_gain: float = 0.03
    max_attempts: int = 3

    def __post_init__(self) -> None:
        if self.window < 10:
            raise WardmapError(f"online_readout.window must be >= 10 frames, got {self.window}")
        if not (math.isfinite(self.min_turn_deg) and self.min_turn_deg >= 0):
            raise WardmapError(f"online_readout.min_turn_deg must be >= 0, got {self.min_turn_deg}")
        if not self.candidates_s or not all(0 < c <= MAX_READOUT_S for c in self.candidates_s):
            raise WardmapError(f"online_readout.candidates_s must lie in (0, {MAX_READOUT_S}] s, got "
                               f"{self.candidates_s}")
        if self.max_attempts < 1 or not self.min_gain >= 0:
            raise WardmapError("online_readout.max_attempts must be >= 1 and min_gain >= 0")


class OnlineReadout:
    """The readout estimated while tracking (see the module docstring). Owned by the tracking
    loop: call :meth:`offer` after each frame and :meth:`close` at the end.

    Args:
        calibration: the recording's calibration (the candidates replace its readout).
        tracker_config: the live tracker's settings (the candidates use the same).
        config: settings.
        background: score in a child process (a live source); False: in line (a recording).
    """

    def __init__(self, calibration: Calibration, tracker_config: TrackerConfig | None,
                 config: OnlineReadoutConfig | None = None, *, background: bool = True) -> None:
        self.cfg = config or OnlineReadoutConfig()
        self._cal, self._tracker_cfg = calibration, tracker_config
        self._background = background
        self._window: deque[TrackInput] = deque(maxlen=self.cfg.window)
        self._turns: deque[float] = deque(maxlen=self.cfg.window)  # degrees from the frame before each
        self._prev: NDArray[np.float64] | None = None
        self._pool: ProcessPoolExecutor | None = None
        self._job: Future[list[float]] | None = None
        self._starter: threading.Thread | None = None
        self.attempts = 0
        self.estimate: ReadoutEstimate | None = None
        """The last scored window's estimate (None: none scored yet)."""
        self.state = "collecting"
        """``collecting``, ``scoring``, ``done`` (decisive) or ``gave up``."""

    @staticmethod
    def wanted(model: ReadoutModel, config: OnlineReadoutConfig | None = None) -> bool:
        """Whether a recording tracked with ``model`` should have its readout estimated online."""
        return (config or OnlineReadoutConfig()).enabled and model.assumed

    def offer(self, inp: TrackInput, res: TrackResult) -> ReadoutModel | None:
        """Take one tracked frame; a new readout model once an estimate is decisive (once)."""
        if self.state == "scoring":
            return self._collect()
        if self.state != "collecting":
            return None
        if inp.rgb is None or res.lost:
            self._restart()  # a gap: start the window over
            return None
        T = res.T_world_camera
        turn = 0.0 if self._prev is None else math.degrees(rotation_angle(self._prev[:3, :3].T @ T[:3, :3]))
        self._prev = T
        self._window.append(inp)  # a full window slides: its oldest frame goes
        self._turns.append(turn)
        if len(self._window) < self.cfg.window or sum(self._turns) - self._turns[0] < self.cfg.min_turn_deg:
            return None  # the turn within the window: summed from its first frame to its last
        self.attempts += 1
        self.state = "scoring"
        cands = [0.0, *self.cfg.candidates_s]
        if not self._background:
            return self._scored(score_candidates(self._window, self._cal, self._tracker_cfg, cands))
        job: Future[list[float]] = Future()
        self._job = job
        self._starter = threading.Thread(target=self._submit, args=(list(self._window), cands, job),
                                         name="readout-start", daemon=True)
        self._starter.start()
        return None

    def _submit(self, window: list[TrackInput], cands: list[float], job: Future[list[float]]) -> None:
        """Hand ``window`` to the scoring child; ``job`` gets its scores or its error.

        Runs on a thread of its own made :data:`CHILD_NICE` nicer first, so that the copy of the
        frames, the executor's threads and the child it spawns (which inherit the value) all
        yield to the tracker. The frames go through files (in shared memory where it has room;
        one copy; pickling them, about 100 MB for 50 VGA frames, held the interpreter lock for
        over 0.1 s).
        """
        nice_this_thread(CHILD_NICE)
        folder: Path | None = None
        try:
            folder, rest = _write_window(window)
            if self._pool is None:
                self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                                 initializer=_yield_cpu)
            inner = self._pool.submit(_score_window_files, folder, rest, self._cal, self._tracker_cfg,
                                      cands)
        except Exception as exc:  # no shared memory left, the child did not start: the job fails
            if folder is not None:
                shutil.rmtree(folder, ignore_errors=True)
            job.set_exception(exc)
            return

        def done(f: Future[list[float]]) -> None:
            shutil.rmtree(folder, ignore_errors=True)
            if f.cancelled():
                job.cancel()
            elif (exc := f.exception()) is not None:
                job.set_exception(exc)
            else:
                job.set_result(f.result())

        inner.add_done_callback(done)

    def _collect(self) -> ReadoutModel | None:
        if self._job is None or not self._job.done():
            return None
        job, self._job = self._job, None
        try:
            scores = job.result()
        except Exception as exc:  # the child died or the tracker failed: the model stays
            log.warning("online readout estimate failed: %s", exc)
            self.state = "gave up"
            return None
        return self._scored(scores)

    def _scored(self, scores: list[float]) -> ReadoutModel | None:
        cands = [0.0, *self.cfg.candidates_s]
        n = len(self._window)
        self._restart()
        if max(scores) <= 0:
            self.state = "gave up" if self.attempts >= self.cfg.max_attempts else "collecting"
            return None
        est = self.estimate = _decide(cands, scores, n, self.cfg.min_gain)
        if est.decisive:
            self.state = "done"
            log.info("rolling-shutter readout estimated online: %.1f ms (%+.0f %% inliers over 0 ms, "
                     "%d frames)", 1e3 * est.readout_s, 100 * est.gain, n)
            return ReadoutModel(est.readout_s, f"estimated online from {n} frames ({100 * est.gain:+.0f} % "
                                f"inliers over 0 ms)", False)
        self.state = "gave up" if self.attempts >= self.cfg.max_attempts else "collecting"
        log.info("online readout: window %d not decisive (%+.1f %% inliers over 0 ms)%s", self.attempts,
                 100 * est.gain, "; keeping the global-shutter model" if self.state == "gave up" else "")
        return None

    def _restart(self) -> None:
        self._window.clear()
        self._turns.clear()
        self._prev = None

    def summary(self) -> dict[str, object]:
        """For a run's summary: state, windows scored, the last estimate."""
        est = self.estimate
        return {"state": self.state, "attempts": self.attempts,
                "readout_s": None if est is None else est.readout_s,
                "gain": None if est is None else round(est.gain, 4)}

    def close(self) -> None:
        """Stop a child process still scoring (its result is dropped)."""
        if self._starter is not None:
            self._starter.join()
            self._starter = None
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None


CHILD_NICE = 19
"""Niceness of the scoring child: it tracks the window once per candidate (several seconds of
CPU) and must not take the tracker's core when the two share one (a pinned edge, a busy board)."""


def _yield_cpu() -> None:
    """The scoring child's initializer: run at :data:`CHILD_NICE` (a refusal is only logged)."""
    try:
        os.nice(max(0, CHILD_NICE - os.nice(0)))
    except OSError as exc:
        log.warning("online readout: cannot lower the scoring child's priority: %s", exc)


_FRAME_ARRAYS = ("rgb", "depth_m", "class_image")
"""The per-frame images that go to the scoring child through files; the rest is pickled."""


def _write_window(window: Sequence[TrackInput]) -> tuple[Path, list[TrackInput]]:
    """Write the window's images to a new folder, one ``.npy`` file of ``(N, ...)`` per field
    present in every frame; in shared memory (``/dev/shm``) when it has room for them twice
    over (a container's is often 64 MB), else in the temporary folder. Plain writes, not a
    memory map: a full file system is an ``OSError`` here, never a crash. Returns the folder
    and the frames with those fields set to None."""
    fields = [f for f in _FRAME_ARRAYS if all(getattr(inp, f) is not None for inp in window)]
    need = sum(getattr(inp, f).nbytes for f in fields for inp in window)
    shm = Path("/dev/shm")
    roomy = shm.is_dir() and os.access(shm, os.W_OK) and shutil.disk_usage(shm).free > 2 * need
    folder = Path(tempfile.mkdtemp(prefix="wardmap-readout-", dir=shm if roomy else None))
    try:
        for name in fields:
            first = np.asarray(getattr(window[0], name))
            header = {"descr": np.lib.format.dtype_to_descr(first.dtype), "fortran_order": False,
                      "shape": (len(window), *first.shape)}
            with open(folder / f"{name}.npy", "wb") as fh:
                np.lib.format.write_array_header_1_0(fh, header)
                for inp in window:
                    a = np.ascontiguousarray(getattr(inp, name), dtype=first.dtype)
                    if a.shape != first.shape:
                        raise WardmapError(f"online readout: {name} of frame {inp.stamp:.6f} is "
                                           f"{a.shape}, the window's first is {first.shape}")
                    fh.write(a.data.cast("B"))
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    cleared: dict[str, Any] = dict.fromkeys(fields)
    return folder, [replace(inp, **cleared) for inp in window]


def _score_window_files(folder: Path, rest: Sequence[TrackInput], calibration: Calibration,
                        config: TrackerConfig | None, candidates_s: Sequence[float]) -> list[float]:
    """:func:`score_candidates` in the child on a window written by :func:`_write_window`. The
    files are removed once mapped (their memory lives as long as the maps), so nothing is left
    in shared memory whatever happens to either process afterwards."""
    arrays = {p.stem: np.load(p, mmap_mode="r") for p in folder.glob("*.npy")}
    shutil.rmtree(folder, ignore_errors=True)
    inputs = []
    for i, inp in enumerate(rest):
        images: dict[str, Any] = {name: np.array(a[i]) for name, a in arrays.items()}
        inputs.append(replace(inp, **images))
    return score_candidates(inputs, calibration, config, candidates_s)


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


__all__ = ["DEFAULT_CANDIDATES_S", "OnlineReadout", "OnlineReadoutConfig", "ReadoutEstimate",
           "estimate_readout", "score_candidates"]
