"""Offline segmentation of a data-set folder (``wardmap segment``).

Writes, for every frame of the data set (an rgb image with its depth partner):

- ``OUT/<stamp>.png``: uint8 single-channel PNG, the knowledge-graph class index of each
  pixel (0 = background), named by the frame's rgb stamp with 6 decimals like the data
  set's own images (``docs/dataset.md``);
- ``OUT/classes.json``: ``{"0": "background", "1": "person", ...}``, index -> class name;
- ``OUT/segment.json``: what made the folder (data set, segmenter, frames, timing).

so results can be scored against the simulator's labels (``bench/perception.py``).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from wardmap.server.perception.config import PerceptionConfig
from wardmap.server.perception.models import make_segmenter
from wardmap.shared.dataset import DatasetReader
from wardmap.shared.errors import ConfigError, DatasetError

__all__ = ["segment_dataset"]

log = logging.getLogger(__name__)

PNG_COMPRESSION = 1
"""zlib level of the written PNGs (fixed, so output bytes never depend on library defaults)."""


def segment_dataset(
    dataset: str | Path,
    out: str | Path,
    spec: str,
    *,
    config: PerceptionConfig | None = None,
    threads: int | None = None,
    max_frames: int | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Segment every frame of ``dataset`` with the segmenter ``spec`` into ``out``.

    Args:
        dataset: data-set folder (ours or a real TUM folder).
        out: output folder; created; must be empty unless ``overwrite``.
        spec: segmenter spec of :func:`~wardmap.server.perception.models.make_segmenter`.
        config: perception parameters (defaults when None).
        threads: CPU threads of the network (``config.threads`` when None).
        max_frames: segment only the first ``max_frames`` frames.
        overwrite: allow a non-empty output folder (existing class PNGs are replaced).
        progress: called as ``progress(done, total)`` after each frame.

    Returns:
        A summary dict (also written to ``out/segment.json``).

    Raises:
        DatasetError: unreadable data set, or an output folder that cannot be written.
        ConfigError: bad segmenter spec or model, bad ``max_frames``.
    """
    if max_frames is not None and max_frames < 1:
        raise ConfigError(f"--max-frames must be positive, got {max_frames}")
    reader = DatasetReader(dataset)
    out_dir = Path(out)
    if out_dir.resolve() == reader.root.resolve():
        raise DatasetError(f"{out_dir}: the output folder must not be the data set itself")
    if out_dir.exists() and not out_dir.is_dir():
        raise DatasetError(f"{out_dir}: exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not overwrite:
        raise DatasetError(f"{out_dir}: output folder is not empty (use --overwrite to write into it)")
    segmenter = make_segmenter(spec, config, threads=threads)
    names = segmenter.class_names
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "classes.json").write_text(
            json.dumps({str(i): name for i, name in enumerate(names)}, indent=2) + "\n"
        )
    except OSError as exc:
        raise DatasetError(f"{out_dir}: cannot write: {exc}") from exc
    total = len(reader) if max_frames is None else min(max_frames, len(reader))
    times_ms: list[float] = []
    instances = 0
    started = time.perf_counter()
    for i in range(total):
        frame = reader.frame(i)
        bgr = np.ascontiguousarray(frame.rgb[..., ::-1])
        result = segmenter.segment(bgr, frame.depth_m)
        times_ms.append(result.inference_ms)
        instances += len(result.instances)
        path = out_dir / f"{frame.stamp:.6f}.png"
        if not cv2.imwrite(str(path), result.class_map, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION]):
            raise DatasetError(f"{path}: cannot write the class image")
        if progress is not None:
            progress(i + 1, total)
    summary: dict[str, Any] = {
        "dataset": str(reader.root),
        "out": str(out_dir),
        "segmenter": spec,
        "frames": total,
        "classes": len(names),
        "instances": instances,
        "inference_ms_median": float(np.median(times_ms)) if times_ms else None,
        "seconds": round(time.perf_counter() - started, 3),
    }
    (out_dir / "segment.json").write_text(json.dumps(summary, indent=2) + "\n")
    log.info("segmented %d frames of %s into %s", total, reader.root, out_dir)
    return summary
