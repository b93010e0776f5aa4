"""Keyframe messages of a data set, as the edge daemon would send them, and a cache of them.

:func:`dataset_keyframes` runs the edge :class:`~wardmap.edge.tracker.Tracker` over frames
``[start, stop)`` of a data-set folder, exactly as ``wardmap edge`` does (same label source,
same wheel-odometry lookup, same message builder :func:`wardmap.edge.keyframes.build_keyframe_msg`),
and yields one :class:`~wardmap.shared.wire.KeyframeMsg` per keyframe with seq 0, 1, ... .
A run starting at ``start`` > 0 is a robot switched on at that frame: a fresh tracker whose
first frame is ``start``.

:func:`cache_keyframes` writes them as ``%06d.msgpack`` files (``wire.encode``; seq = file
number) plus ``keyframes.json`` (written last: its presence marks a complete cache) with
the parameters and, per keyframe, its stamp and the ground-truth camera pose
``T_world_camera`` at that stamp (:func:`wardmap.shared.dataset.pose_at`; None where the
data set has no ground truth there). :func:`read_keyframes` opens such a folder. A cache is
reused when its parameters equal the request; it does not notice changes of the tracker's
code (delete the folder to rebuild). Processes sharing a cache folder take turns: making or
checking it holds an exclusive lock on ``<folder>.lock`` beside it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import json
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wardmap.edge.agent import AgentConfig
from wardmap.edge.keyframes import build_keyframe_msg, thermal_due
from wardmap.edge.labels import make_label_source
from wardmap.edge.privacy import person_mask
from wardmap.edge.tracker import Tracker, TrackerConfig, TrackInput
from wardmap.shared.dataset import DatasetReader, odom_at, pose_at
from wardmap.shared.errors import DatasetError, WardmapError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.wire import Intrinsics, KeyframeMsg, decode_keyframe, encode

__all__ = [
    "CACHE_FORMAT",
    "KeyframeCache",
    "auto_labels",
    "cache_keyframes",
    "dataset_keyframes",
    "folder_lock",
    "groundtruth_at",
    "read_keyframes",
]

F64 = NDArray[np.float64]
CACHE_FORMAT = 3
"""3: keypoints carry the tracker's map point ids (``Keypoints.point_id``, int32)."""
INDEX = "keyframes.json"


def auto_labels(reader: DatasetReader) -> str:
    """The label source a robot with a good network would have: ``oracle`` for a simulated data
    set (``labels/`` and ``objects.json``: people removed exactly), else ``none``."""
    return "oracle" if reader.has_labels and (reader.root / "objects.json").is_file() else "none"


def _check_range(n: int, start: int, stop: int | None) -> int:
    stop = n if stop is None else stop
    if not 0 <= start < stop <= n:
        raise WardmapError(f"frame range [{start}, {stop}) is not inside the data set's 0..{n}")
    return stop


def dataset_keyframes(
    dataset: str | Path,
    *,
    robot_id: str,
    session_id: str,
    start: int = 0,
    stop: int | None = None,
    labels: str | None = None,
    tracker_config: TrackerConfig | None = None,
    agent_config: AgentConfig | None = None,
    T_map_odom: F64 | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Iterator[KeyframeMsg]:
    """Track frames ``[start, stop)`` of ``dataset``; yield each keyframe's wire message.

    Args:
        robot_id, session_id: the ids the messages carry (1-64 characters ``[A-Za-z0-9_.-]``).
        start, stop: frame range (``stop`` None: to the end).
        labels: label source spec (``none``, ``oracle``, ``onnx:PATH``); None: :func:`auto_labels`.
        tracker_config, agent_config: as the daemon's (defaults: the defaults); of the agent
            settings the message builder's are used (keypoints, JPEG, strides, thermal, privacy:
            people are redacted as a robot would; with labels ``none``, where a robot refuses to
            start unless privacy is ``off``, the images are kept whole).
        T_map_odom: (4, 4) the session's known map pose (``wardmap edge --map-pose``), or None.
        progress: called as ``progress(frames_done, frames_total)``.

    Raises:
        WardmapError: a bad frame range; DatasetError / ConfigError from the data set or labels.
    """
    reader = DatasetReader(dataset)
    stop = _check_range(len(reader), start, stop)
    cfg = agent_config or AgentConfig()
    kg = KnowledgeGraph.load()
    spec = auto_labels(reader) if labels is None else labels
    if spec == "none" and cfg.privacy != "off":
        # a robot refuses this; offline, the images are already on this machine: keep them whole
        cfg = dataclasses.replace(cfg, privacy="off")
    source = make_label_source(spec, dataset=reader, kg=kg, threads=cfg.label_threads)
    mobility_lut = kg.mobility_lut()
    tracker = Tracker(reader.calibration, tracker_config, mobility_lut)
    odo = reader.odometry()
    intrinsics = Intrinsics.from_camera(reader.calibration.rgb, reader.calibration.depth_scale)
    seq = 0
    for i in range(start, stop):
        stamp = float(reader.stamps[i])
        T_odom_base = odom_at(odo, stamp)
        try:
            frame = reader.frame(i)
        except DatasetError:
            tracker.track(TrackInput(stamp, None, None, T_odom_base=T_odom_base, problem="cannot read frame"))
            continue
        lab = source.labels(frame)
        person = None if lab is None else person_mask(lab.class_image, mobility_lut)
        res = tracker.track(
            TrackInput(stamp, frame.rgb, frame.depth_m, frame.thermal_k, T_odom_base,
                       class_image=None if lab is None else lab.class_image)
        )
        if res.keyframe:
            yield build_keyframe_msg(
                frame, res, tracker, T_odom_base=T_odom_base, intrinsics=intrinsics, robot_id=robot_id,
                session_id=session_id, seq=seq, config=cfg,
                with_thermal=thermal_due(res.source, seq, cfg.thermal_every), T_map_odom=T_map_odom,
                person=person,
            )
            seq += 1
        if progress is not None:
            progress(i - start + 1, stop - start)


def groundtruth_at(reader: DatasetReader, stamps: list[float]) -> list[F64 | None]:
    """Ground-truth ``T_world_camera`` (4, 4) of the data set at each stamp, None where not covered
    (:func:`~wardmap.shared.dataset.pose_at` with its default tolerances) or without ground truth."""
    gt = reader.groundtruth()
    if gt is None:
        return [None] * len(stamps)
    return [pose_at(gt[0], gt[1], s) for s in stamps]


@dataclass(frozen=True)
class KeyframeCache:
    """A complete keyframe cache folder (:func:`cache_keyframes`).

    Attributes:
        folder: the folder.
        params: the parameters it was made with (dataset, ids, range, labels, config digest).
        stamps: (N,) keyframe stamps, seconds.
        truth: per keyframe the ground-truth ``T_world_camera`` (4, 4), or None.
    """

    folder: Path
    params: dict[str, Any]
    stamps: F64
    truth: list[F64 | None]

    def __len__(self) -> int:
        return len(self.truth)

    def path(self, seq: int) -> Path:
        return self.folder / f"{seq:06d}.msgpack"

    def payload(self, seq: int) -> bytes:
        """The encoded message of keyframe ``seq`` (``wire.encode``)."""
        try:
            return self.path(seq).read_bytes()
        except OSError as exc:
            raise DatasetError(f"{self.path(seq)}: cannot read: {exc.strerror or exc}") from exc

    def message(self, seq: int) -> KeyframeMsg:
        return decode_keyframe(self.payload(seq))

    def messages(self) -> Iterator[KeyframeMsg]:
        """Decoded messages in seq order (one at a time: the folder may be large)."""
        for seq in range(len(self)):
            yield self.message(seq)


def _params(dataset: Path, robot_id: str, session_id: str, start: int, stop: int, labels: str,
            tracker_config: TrackerConfig | None, agent_config: AgentConfig | None,
            T_map_odom: F64 | None) -> dict[str, Any]:
    digest = hashlib.sha256(
        repr((tracker_config or TrackerConfig(), agent_config or AgentConfig())).encode()
    ).hexdigest()[:16]
    return {
        "format": CACHE_FORMAT,
        "dataset": str(dataset.resolve()),
        "robot_id": robot_id,
        "session_id": session_id,
        "start": start,
        "stop": stop,
        "labels": labels,
        "config_sha256": digest,
        "T_map_odom": None if T_map_odom is None else np.asarray(T_map_odom, np.float64).tolist(),
    }


def read_keyframes(folder: str | Path) -> KeyframeCache:
    """Open a complete keyframe cache.

    Raises:
        DatasetError: no ``keyframes.json`` (never made, or interrupted), or a malformed one.
    """
    folder = Path(folder)
    try:
        doc = json.loads((folder / INDEX).read_text())
        params = doc["params"]
        stamps = np.asarray([k["stamp"] for k in doc["keyframes"]], np.float64)
        truth = [None if k["T_world_camera"] is None else np.asarray(k["T_world_camera"], np.float64)
                 for k in doc["keyframes"]]
    except OSError as exc:
        raise DatasetError(f"{folder}: no complete keyframe cache ({INDEX}: {exc.strerror or exc})") from exc
    except (ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"{folder / INDEX}: malformed: {exc}") from exc
    if params.get("format") != CACHE_FORMAT:
        raise DatasetError(
            f"{folder / INDEX}: cache format {params.get('format')!r}, expected {CACHE_FORMAT}"
        )
    return KeyframeCache(folder, params, stamps, truth)


def cache_keyframes(
    dataset: str | Path,
    folder: str | Path,
    *,
    robot_id: str,
    session_id: str,
    start: int = 0,
    stop: int | None = None,
    labels: str | None = None,
    tracker_config: TrackerConfig | None = None,
    agent_config: AgentConfig | None = None,
    T_map_odom: F64 | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> KeyframeCache:
    """:func:`dataset_keyframes` written to ``folder`` (made if missing), or the cache already
    there when its parameters are the same; returns it opened (:func:`read_keyframes`).

    Stale ``*.msgpack`` files of another run are removed first.
    """
    dataset = Path(dataset)
    folder = Path(folder)
    reader = DatasetReader(dataset)
    stop = _check_range(len(reader), start, stop)
    spec = auto_labels(reader) if labels is None else labels
    params = _params(
        dataset, robot_id, session_id, start, stop, spec, tracker_config, agent_config, T_map_odom
    )
    with folder_lock(folder):
        if (folder / INDEX).is_file():
            try:
                cached = read_keyframes(folder)
            except DatasetError:
                cached = None
            if cached is not None and cached.params == params:
                return cached
        try:
            folder.mkdir(parents=True, exist_ok=True)
            (folder / INDEX).unlink(missing_ok=True)
            for old in folder.glob("*.msgpack"):
                old.unlink()
        except OSError as exc:
            raise DatasetError(f"{folder}: cannot prepare the cache: {exc.strerror or exc}") from exc
        stamps: list[float] = []
        for msg in dataset_keyframes(
            dataset, robot_id=robot_id, session_id=session_id, start=start, stop=stop, labels=spec,
            tracker_config=tracker_config, agent_config=agent_config, T_map_odom=T_map_odom,
            progress=progress,
        ):
            _write(folder / f"{msg.seq:06d}.msgpack", encode(msg))
            stamps.append(msg.stamp)
        truth = groundtruth_at(reader, stamps)
        doc = {
            "params": params,
            "keyframes": [
                {"seq": k, "stamp": s, "T_world_camera": None if T is None else np.round(T, 9).tolist()}
                for k, (s, T) in enumerate(zip(stamps, truth, strict=True))
            ],
        }
        _write(folder / INDEX, (json.dumps(doc, indent=1) + "\n").encode())
        return read_keyframes(folder)


@contextlib.contextmanager
def folder_lock(folder: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``<folder>.lock`` (made if missing) while the block runs; another
    process asking for the same lock waits."""
    path = folder.with_name(folder.name + ".lock")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fh = path.open("a")
    except OSError as exc:
        raise DatasetError(f"{path}: cannot open the lock file: {exc.strerror or exc}") from exc
    with fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (a temporary file, then a rename)."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot write: {exc.strerror or exc}") from exc
