"""Run the tracking frontend over a recorded source (``wardmap track``).

The edge daemon runs the very same :class:`~wardmap.edge.tracker.Tracker`; this module
only feeds it the frames of a source (a data-set folder, a ROS recording, the simulator;
:mod:`wardmap.edge.stream`) and writes the trajectory (TUM format, every frame).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from wardmap.edge.labels import make_label_source
from wardmap.edge.readout import OnlineReadout, OnlineReadoutConfig
from wardmap.edge.stream import FrameSourceStream, FrameStream, StreamSource
from wardmap.edge.tracker import Tracker, TrackerConfig, TrackInput, TrackResult
from wardmap.shared.dataset import Calibration, DatasetReader
from wardmap.shared.errors import DatasetError, WardmapError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.se3 import transform_to_tum

log = logging.getLogger(__name__)


def track_dataset(dataset: str | Path, out: str | Path, **options: Any) -> dict[str, Any]:
    """Track every frame of the data-set folder ``dataset``; ``options`` are :func:`track_source`'s."""
    return track_source(FrameSourceStream(DatasetReader(dataset)), out, **options)


def track_source(
    source: StreamSource,
    out: str | Path,
    *,
    config: TrackerConfig | None = None,
    labels: str = "none",
    max_frames: int | None = None,
    label_threads: int = 1,
    progress: Callable[[int, int, TrackResult], None] | None = None,
    calibration: Calibration | None = None,
    online_readout: OnlineReadoutConfig | None = None,
) -> dict[str, Any]:
    """Track every frame of ``source``; write ``out`` (TUM trajectory); return a summary.

    The source is replayed as fast as the tracker goes (a :class:`FrameStream` that blocks,
    never drops; a live source drops what the tracker cannot keep up with, counted).
    ``calibration`` replaces the source's own (e.g. with a readout time estimated by
    :func:`wardmap.edge.readout.estimate_readout`). When neither gives a readout time, it is
    estimated while tracking (:class:`~wardmap.edge.readout.OnlineReadout`, in line, so a run
    repeats exactly; ``online_readout``'s settings).

    The summary has frames, keyframes, lost frames (with the reasons), pose sources, the
    stream's counters (``stream``: received, dropped, late), the rolling-shutter model
    (``readout``: seconds, where it came from, whether it is a guess, as used at the end; ``online``:
    the online estimate's state, when one ran) and milliseconds per frame (median
    and p95) for each stage and in total; label inference is timed apart (``labels_ms``) and is
    not part of ``total``.
    """
    out = Path(out)
    if out.is_dir():
        raise DatasetError(f"--out {out} is a folder; give a file name for the trajectory")
    if not out.parent.exists():
        raise DatasetError(f"--out: folder {out.parent} does not exist")
    if max_frames is not None and max_frames <= 0:
        raise WardmapError(f"--max-frames must be positive, got {max_frames}")
    kg = KnowledgeGraph.load()
    label_source = make_label_source(labels, dataset=source.dataset, kg=kg, threads=label_threads)
    config = config or TrackerConfig()
    # Bundle adjustment solved at each keyframe, in order: the same trajectory on every run
    # (the edge daemon solves in a worker process, as fast as it can).
    config = replace(config, local_ba=replace(config.local_ba, worker="inline"))
    cal = calibration or source.calibration
    tracker = Tracker(cal, config, kg.mobility_lut())
    readout = tracker.readout
    online = (OnlineReadout(cal, config, online_readout, background=False)
              if OnlineReadout.wanted(readout, online_readout) else None)
    log.debug("%s: rolling-shutter readout %.1f ms: %s", source.name, 1e3 * readout.readout_s, readout.source)
    n = source.frame_count or 0  # for progress only: 0 when unknown
    if max_frames is not None and n:
        n = min(n, max_frames)
    results: list[TrackResult] = []
    label_ms: list[float] = []
    with tracker, FrameStream(source, max_frames=max_frames) as stream:
        for item in stream:
            frame = item.frame
            if frame is None:
                problem = item.problem or "no frame"
                results.append(tracker.track(TrackInput(item.stamp, None, None, T_odom_base=item.T_odom_base,
                                                        problem=problem)))
                continue
            class_image = None
            t0 = time.perf_counter()
            lab = label_source.labels(frame)
            if lab is not None:
                class_image = lab.class_image
                label_ms.append(lab.inference_ms if lab.inference_ms else (time.perf_counter() - t0) * 1e3)
            inp = TrackInput(item.stamp, frame.rgb, frame.depth_m, frame.thermal_k, item.T_odom_base,
                             class_image)
            res = tracker.track(inp)
            results.append(res)
            if online is not None and (found := online.offer(inp, res)) is not None:
                tracker.readout = readout = found  # from the next frame on
            if progress is not None:
                progress(len(results), max(n, len(results)), res)
    if not results:
        raise DatasetError(f"{source.name}: no frame to track")
    _write_tum(out, results)
    return {
        **summarize(results, label_ms),
        "stream": stream.counters(),
        "readout": {"readout_s": readout.readout_s, "source": readout.source, "assumed": readout.assumed,
                    **({"online": online.summary()} if online is not None else {})},
        "local_ba": tracker.local_ba_stats(),
    }


def _write_tum(path: Path, results: list[TrackResult]) -> None:
    lines = ["# timestamp tx ty tz qx qy qz qw  (wardmap track: T_world_camera, every frame)"]
    for r in results:
        v = transform_to_tum(r.T_world_camera)
        lines.append(f"{r.stamp:.6f} " + " ".join(f"{x:.9f}" for x in v))
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text("\n".join(lines) + "\n")
        os.replace(tmp, path)
    except OSError as exc:
        raise DatasetError(f"cannot write {path}: {exc}") from exc


def summarize(results: list[TrackResult], label_ms: list[float]) -> dict[str, Any]:
    """Counts and per-stage timing statistics (ms) of a tracking run."""
    stages: dict[str, list[float]] = {}
    for r in results:
        for k, v in r.timings_ms.items():
            stages.setdefault(k, []).append(v)
    sources: dict[str, int] = {}
    for r in results:
        sources[r.source] = sources.get(r.source, 0) + 1
    lost = [r for r in results if r.lost]
    reasons: dict[str, int] = {}
    for r in lost:
        reasons[r.reason] = reasons.get(r.reason, 0) + 1

    def stats(v: list[float]) -> dict[str, float]:
        a = np.asarray(v, np.float64)
        return {
            "median": round(float(np.median(a)), 3),
            "p95": round(float(np.percentile(a, 95)), 3),
            "n": len(v),
        }

    return {
        "frames": len(results),
        "keyframes": sum(r.keyframe for r in results),
        "lost_frames": len(lost),
        "dynamic_points": sum(r.n_dynamic for r in results),
        "lost_reasons": reasons,
        "sources": sources,
        "ms_per_frame": {k: stats(v) for k, v in sorted(stages.items())},
        "labels_ms": stats(label_ms) if label_ms else None,
    }
