"""Offline runner of ``wardmap map``: perception + association over data-set folders.

For each data set: choose keyframes from the camera poses (ground truth, or a TUM
trajectory given with ``--poses``), find object instances (``oracle``: the simulator's
label images and ``objects.json``; or any segmenter spec of
``server/perception/models.py``: ``model`` (the packaged network), ``model:PATH`` or ``PATH``
(an ONNX segmentation network), ``yolox:PATH`` (a COCO detector); ground-truth instance ids
attached from the labels when present) and measure them in 3D with the
server's perception steps (``server/perception/keyframe.py``: ``moving`` classes such as
people left out, and for the model its instances split and checked against the floor when
the data set has a ``[base]`` calibration), then feed the keyframes to an
:class:`~wardmap.server.association.associator.Associator` (the same code the live server
runs) and write ``landmarks.json`` (format in docs/association.md).

Several data sets are associated into one map in the order given; their poses must be
in one world frame (true for the simulator's robots of one world). No group spans two
data sets. To keep memory bounded, each measurement's (H, W) mask is dropped after
measuring and its camera points are subsampled to ``MapConfig.keep_points``; the pixel
box, pose, size and appearance (what association uses) are kept.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from wardmap.server.association.associator import METHODS, AssociationConfig, Associator, Method, beyond_range
from wardmap.server.association.types import Landmark
from wardmap.server.perception.config import PerceptionConfig
from wardmap.server.perception.floor import floor_under
from wardmap.server.perception.instances import id_to_class, oracle_instances
from wardmap.server.perception.keyframe import FindInstances, measure_keyframe
from wardmap.server.perception.measure import SKIP_KINDS, MeasureConfig, mean_rgb
from wardmap.server.perception.types import Instance, ObjectMeasurement
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.config import load_config, to_mapping
from wardmap.shared.dataset import DatasetReader, pose_at, read_tum_trajectory
from wardmap.shared.errors import ConfigError, DatasetError, WardmapError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.se3 import rotation_angle
from wardmap.tools.evaluate import score_landmarks

__all__ = [
    "DatasetMeasurements",
    "KeyframeMeasurements",
    "MapConfig",
    "MeasurementSource",
    "associate",
    "landmarks_document",
    "measure_dataset",
    "run_map",
    "score_against_truth",
    "select_keyframes",
]

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
MeasurementSource = str
"""``oracle`` (the simulator's labels) or a segmenter spec (``make_segmenter``): ``model``,
``model:PATH``, ``yolox:PATH`` or ``PATH``."""
ORACLE = "oracle"
Progress = Callable[[str, int, int], None]
FORMAT_VERSION = 1


@dataclass(frozen=True)
class MapConfig:
    """Offline runner parameters (TOML table ``[map]``)."""

    keyframe_min_translation_m: float = 0.1
    """A frame is a keyframe when the camera moved this far since the last keyframe (metres) ..."""
    keyframe_min_rotation_deg: float = 10.0
    """... or turned this much (degrees). The first frame with a pose is always a keyframe."""
    min_pixels: int = 200
    """Oracle instances smaller than this many pixels are left out."""
    keep_points: int = 256
    """Camera points kept per measurement after measuring (fixed stride); 0 keeps none."""

    def __post_init__(self) -> None:
        if self.keyframe_min_translation_m < 0 or self.keyframe_min_rotation_deg < 0:
            raise ValueError("keyframe thresholds must be >= 0")
        if self.min_pixels < 1 or self.keep_points < 0:
            raise ValueError("need min_pixels >= 1 and keep_points >= 0")


@dataclass(frozen=True, eq=False)
class KeyframeMeasurements:
    """One keyframe: its key (``<dataset>/<stamp>``), stamp (s), camera pose (4, 4), measurements."""

    key: str
    stamp: float
    T_world_camera: F64
    measurements: tuple[ObjectMeasurement, ...]


@dataclass(frozen=True, eq=False)
class DatasetMeasurements:
    """Everything association needs from one data set.

    Attributes:
        name: the folder name.
        camera: colour camera of the data set.
        keyframes: the keyframes in time order.
        frames: number of frames in the data set.
        frames_without_pose: frames left out because the trajectory does not cover them.
        moving_left_out: measurements of ``moving`` classes left out.
        gt_classes: ground-truth instance id -> class (``objects.json``), or None.
        floating_left_out: network instances left out for floating above the floor
            (``PerceptionConfig.floor_gap_m``; only data sets with a ``[base]`` calibration).
        wall_pieces_left_out: network instances left out for lying on a surface taller than
            any object of their class (``PerceptionConfig.max_top_m``; the same data sets).
        floor_pieces_left_out: network instances left out for lying flat on the floor, lower
            than any object of their class (``PerceptionConfig.min_top_m``; the same data sets).
        skipped: instances found but not measured, by kind
            (:data:`~wardmap.server.perception.measure.SKIP_KINDS`).
    """

    name: str
    camera: PinholeCamera
    keyframes: list[KeyframeMeasurements]
    frames: int
    frames_without_pose: int
    moving_left_out: int
    gt_classes: dict[int, str] | None
    floating_left_out: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    wall_pieces_left_out: int = 0
    floor_pieces_left_out: int = 0


def select_keyframes(
    T_world_camera: Sequence[F64 | None], min_translation_m: float, min_rotation_deg: float
) -> list[int]:
    """Indices of keyframes: the first posed frame, then every frame whose camera moved at least
    ``min_translation_m`` metres or turned ``min_rotation_deg`` degrees since the last keyframe.

    Args:
        T_world_camera: (4, 4) camera pose per frame, None where unknown (never a keyframe).
    """
    out: list[int] = []
    last: F64 | None = None
    min_rot = math.radians(min_rotation_deg)
    for i, T in enumerate(T_world_camera):
        if T is None:
            continue
        if last is None:
            out.append(i)
            last = T
            continue
        moved = float(np.linalg.norm(T[:3, 3] - last[:3, 3]))
        turned = rotation_angle(last[:3, :3].T @ T[:3, :3])
        if moved >= min_translation_m or turned >= min_rot:
            out.append(i)
            last = T
    return out


def _frame_poses(reader: DatasetReader, poses: Path | None) -> list[F64 | None]:
    if poses is None:
        gt = reader.groundtruth()
        if gt is None:
            raise DatasetError(f"{reader.root}: no groundtruth.txt; give camera poses with --poses TRAJ.txt")
        stamps, T = gt
    else:
        if not poses.is_file():
            raise DatasetError(f"poses file not found: {poses}")
        stamps, T = read_tum_trajectory(poses)
        if len(stamps) == 0:
            raise DatasetError(f"{poses}: no poses in the file")
    return [pose_at(stamps, T, float(t)) for t in reader.stamps]


def _segmenter(source: MeasurementSource) -> FindInstances:
    """The segmenter of spec ``source``; a ConfigError naming the spec when it cannot be built."""
    try:
        from wardmap.server.perception.models import make_segmenter
    except ImportError as exc:
        raise WardmapError(f"--measurements {source}: the segmenter adapter is not available ({exc})") \
            from exc
    try:
        seg: FindInstances = make_segmenter(source)
    except ConfigError as exc:
        raise ConfigError(f"--measurements {source}: {exc}") from exc
    return seg


def _slim(m: ObjectMeasurement, keep_points: int) -> ObjectMeasurement:
    pts = m.points_camera
    if keep_points == 0:
        pts = pts[:0]
    elif len(pts) > keep_points:
        pts = pts[:: math.ceil(len(pts) / keep_points)]
    return dataclasses.replace(m, mask=np.zeros((0, 0), dtype=bool), points_camera=np.ascontiguousarray(pts))


def measure_dataset(
    path: str | Path,
    *,
    measurements: MeasurementSource = "oracle",
    poses: str | Path | None = None,
    config: MapConfig | None = None,
    measure_config: MeasureConfig | None = None,
    knowledge: KnowledgeGraph | None = None,
    progress: Progress | None = None,
) -> DatasetMeasurements:
    """Select keyframes of one data set and measure their objects.

    Args:
        path: data-set folder (docs/dataset.md).
        measurements: ``oracle`` (needs ``labels/`` and ``objects.json``) or a segmenter spec
            (``model``, ``model:PATH``, ``PATH``, ``yolox:PATH``; :data:`MeasurementSource`).
        poses: TUM trajectory of the camera (``T_world_camera``); None uses groundtruth.txt.
            Poses are interpolated at each frame stamp (``shared.dataset.pose_at``).
        config: keyframe selection and measurement slimming.
        measure_config: the 3D measurement parameters.
        knowledge: the knowledge graph (which classes are ``moving``); default the packaged one.
        progress: called as ``progress(dataset name, keyframes done, keyframes)``.

    Raises:
        DatasetError: missing folder, files, labels, poses or objects.json.
        ConfigError: ``measurements`` names a segmenter that cannot be built (bad spec or file).
        WardmapError: the segmenter adapter is not available.
    """
    cfg = config or MapConfig()
    if not measurements.strip():
        raise ConfigError("--measurements is empty; use oracle, model, model:PATH, yolox:PATH or PATH")
    reader = DatasetReader(path)
    name = Path(path).resolve().name
    kg = knowledge or KnowledgeGraph.load()
    objects = reader.objects()
    gt_classes = id_to_class(objects) if objects is not None else None
    if measurements == ORACLE and (gt_classes is None or not reader.has_labels):
        raise DatasetError(f"{reader.root}: --measurements oracle needs labels.txt + labels/ and "
                           "objects.json (a simulated data set)")
    segment = None if measurements == ORACLE else _segmenter(measurements)
    mcfg = measure_config or MeasureConfig()
    perception = PerceptionConfig(measure=mcfg)  # the split uses the usual widths too
    frame_poses = _frame_poses(reader, Path(poses) if poses is not None else None)
    without_pose = sum(1 for T in frame_poses if T is None)
    if without_pose == len(frame_poses):
        raise DatasetError(f"{reader.root}: the trajectory covers none of the {len(frame_poses)} "
                           "frame stamps")
    if without_pose:
        log.warning("%s: %d of %d frames have no pose and are left out", name, without_pose, len(frame_poses))
    chosen = select_keyframes(frame_poses, cfg.keyframe_min_translation_m, cfg.keyframe_min_rotation_deg)
    camera = reader.calibration.rgb
    keyframes: list[KeyframeMeasurements] = []
    moving = floating = walls = floors = 0
    skipped: Counter[str] = Counter()
    T_base_rgb = reader.calibration.T_base_rgb
    moving_classes = kg.moving_classes()
    for done, i in enumerate(chosen):
        frame = reader.frame(i)
        T = frame_poses[i]
        if T is None:  # select_keyframes never picks these
            raise DatasetError(f"{reader.root}: frame {i} has no pose")
        bgr: NDArray[np.uint8] = np.ascontiguousarray(cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR),
                                                      dtype=np.uint8)
        found: FindInstances | list[Instance]
        if segment is None:
            if frame.labels is None or gt_classes is None:
                raise DatasetError(f"{reader.root}: frame {frame.stamp:.6f} has no label image")
            found = oracle_instances(frame.labels, gt_classes, min_pixels=cfg.min_pixels)
        else:
            found = segment
        key = f"{name}/{frame.stamp:.6f}"
        seen = measure_keyframe(
            bgr, frame.depth_m, camera, T, keyframe=key, stamp=frame.stamp,
            floor_z_m=None if T_base_rgb is None else floor_under(T, T_base_rgb),
            instances=found, config=perception, moving=moving_classes, source=measurements,
            instance_ids=frame.labels if segment is not None else None,
        )
        moving += seen.moving
        floating += seen.left_out.floating
        walls += seen.left_out.walls
        floors += seen.left_out.floors
        skipped.update(seen.skipped_by_kind())
        ms = seen.measurements
        keyframes.append(KeyframeMeasurements(key, frame.stamp, T, tuple(_slim(m, cfg.keep_points)
                                                                          for m in ms)))
        if progress is not None:
            progress(name, done + 1, len(chosen))
    log.info("%s: %d frames, %d keyframes, %d measurements (%d moving, %d floating, %d wall and %d floor "
             "pieces left out, %d not measurable)", name, len(reader), len(keyframes),
             sum(len(k.measurements) for k in keyframes), moving, floating, walls, floors,
             sum(skipped.values()))
    return DatasetMeasurements(name, camera, keyframes, len(reader), without_pose, moving, gt_classes,
                               floating, dict(skipped), walls, floors)


def associate(
    datasets: Sequence[DatasetMeasurements], config: AssociationConfig | None = None,
    knowledge: KnowledgeGraph | None = None,
) -> list[Landmark]:
    """Run one :class:`Associator` over the keyframes of the data sets, in order; returns the
    landmarks. ``knowledge``: the graph whose related classes are never merged (default: the
    packaged one)."""
    assoc = Associator(config, knowledge)
    for ds in datasets:
        for kf in ds.keyframes:
            assoc.add_keyframe(kf.measurements, kf.T_world_camera, ds.camera, stream=ds.name)
        assoc.flush(ds.name)
    return assoc.landmarks()


def _measurement_json(m: ObjectMeasurement, dataset: str) -> dict[str, Any]:
    return {
        "dataset": dataset,
        "keyframe": m.keyframe,
        "stamp": round(m.stamp, 6),
        "category": m.category,
        "confidence": m.confidence,
        "box_xyxy": [float(v) for v in m.box_xyxy],
        "T_world_object": np.round(m.T_world_object, 6).tolist(),
        "size": [round(float(v), 6) for v in m.size],
        "gt_instance": m.gt_instance,
    }


def _rounded(rgb: tuple[float, float, float] | None) -> list[float] | None:
    return None if rgb is None else [round(c, 1) for c in rgb]


def landmarks_document(
    landmarks: Sequence[Landmark],
    *,
    method: Method,
    measurements: MeasurementSource,
    datasets: Sequence[DatasetMeasurements],
    config: AssociationConfig,
    hist_bins: tuple[int, int, int] = MeasureConfig.hist_bins,
) -> dict[str, Any]:
    """The ``landmarks.json`` document (docs/association.md); ``hist_bins`` are the bins of
    the measurements' colour histograms (for each landmark's mean colour)."""
    dataset_of = {kf.key: ds.name for ds in datasets for kf in ds.keyframes}
    return {
        "format_version": FORMAT_VERSION,
        "method": method,
        "measurements": measurements,
        "datasets": [
            {"name": ds.name, "frames": ds.frames, "keyframes": len(ds.keyframes),
             "frames_without_pose": ds.frames_without_pose, "moving_left_out": ds.moving_left_out,
             "floating_left_out": ds.floating_left_out,
             "wall_pieces_left_out": ds.wall_pieces_left_out,
             "floor_pieces_left_out": ds.floor_pieces_left_out,
             "skipped": {k: ds.skipped.get(k, 0) for k in SKIP_KINDS},
             "beyond_range": sum(beyond_range(m, config.max_range_m) for kf in ds.keyframes
                                 for m in kf.measurements)}
            for ds in datasets
        ],
        "config": to_mapping(config),
        "landmarks": [
            {
                "id": lm.id,
                "class": lm.category,
                "confirmed": lm.confirmed,
                "confidence": round(lm.confidence, 6),
                "T_world_object": np.round(lm.T_world_object, 6).tolist(),
                "size": [round(float(v), 6) for v in lm.size],
                "color_rgb": _rounded(mean_rgb([m.color_hist for m in lm.measurements], hist_bins)),
                "measurements": [_measurement_json(m, dataset_of.get(m.keyframe, ""))
                                 for m in lm.measurements],
            }
            for lm in landmarks
        ],
    }


def run_map(
    datasets: Sequence[str | Path],
    out: str | Path,
    *,
    method: Method | None = None,
    measurements: MeasurementSource = "oracle",
    poses: Sequence[str | Path] | None = None,
    config_path: str | Path | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """``wardmap map``: measure and associate the data sets, write ``out/landmarks.json``.

    Args:
        datasets: data-set folders, associated into one map in this order.
        out: output folder (created if needed).
        method: overrides ``[association] method`` of the config file.
        measurements: ``oracle`` or a segmenter spec (:data:`MeasurementSource`).
        poses: one TUM trajectory per data set, or None for their ground truth.
        config_path: TOML file with optional ``[association]``, ``[map]`` and ``[measure]`` tables.

    Returns:
        A summary (counts per data set, number of landmarks, output path, and ``score``:
        :func:`score_against_truth`, or None without ground truth).

    Raises:
        ConfigError, DatasetError, WardmapError: bad arguments, config or data.
    """
    if not datasets:
        raise WardmapError("give at least one data set")
    if method is not None and method not in METHODS:
        raise ConfigError(f"unknown association method {method!r}; use one of {', '.join(METHODS)}")
    if poses is not None and len(poses) != len(datasets):
        raise WardmapError(f"--poses given {len(poses)} time(s) for {len(datasets)} data set(s); give one "
                           "trajectory per data set, in the same order")
    assoc_cfg = load_config(AssociationConfig, config_path, section="association")
    if method is not None:
        assoc_cfg = dataclasses.replace(assoc_cfg, method=method)
    map_cfg = load_config(MapConfig, config_path, section="map")
    measure_cfg = load_config(MeasureConfig, config_path, section="measure")
    out_dir = Path(out)
    if out_dir.exists() and not out_dir.is_dir():
        raise WardmapError(f"--out {out_dir} exists and is not a folder")
    kg = KnowledgeGraph.load()
    measured = [
        measure_dataset(ds, measurements=measurements, poses=None if poses is None else poses[k],
                        config=map_cfg, measure_config=measure_cfg, knowledge=kg, progress=progress)
        for k, ds in enumerate(datasets)
    ]
    landmarks = associate(measured, assoc_cfg, kg)
    doc = landmarks_document(landmarks, method=assoc_cfg.method, measurements=measurements,
                             datasets=measured, config=assoc_cfg, hist_bins=measure_cfg.hist_bins)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        path = out_dir / "landmarks.json"
        path.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    except OSError as exc:
        raise WardmapError(f"cannot write {out_dir / 'landmarks.json'}: {exc.strerror or exc}") from exc
    return {
        "landmarks": len(landmarks),
        "measurements": sum(len(lm.measurements) for lm in landmarks),
        "keyframes": sum(len(ds.keyframes) for ds in measured),
        "method": assoc_cfg.method,
        "out": str(path),
        "score": score_against_truth(landmarks, measured, kg),
    }


def score_against_truth(landmarks: Sequence[Landmark], datasets: Sequence[DatasetMeasurements],
                        knowledge: KnowledgeGraph) -> dict[str, float | int] | None:
    """The association scores of ``evaluate.score_landmarks`` (accuracy, completeness, F-measure,
    confirmed landmarks against ground-truth objects) when every data set has ground truth from
    one world (their ``objects.json`` agree on every shared id); None otherwise."""
    gt: dict[int, str] = {}
    for ds in datasets:
        if ds.gt_classes is None:
            return None
        for i, name in ds.gt_classes.items():
            if gt.setdefault(i, name) != name:
                return None
    s = score_landmarks(landmarks, gt, knowledge.moving_classes())
    return {"accuracy": round(s.accuracy, 6), "completeness": round(s.completeness, 6),
            "f_measure": round(s.f_measure, 6), "objects": s.landmarks, "unconfirmed": s.unconfirmed,
            "gt_objects": s.gt_objects}
