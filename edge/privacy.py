"""Redaction of people in keyframe images, on the robot, before anything leaves it.

Keyframe colour images show patients, staff and visitors; the thermal raster shows their
body heat. The edge already labels every frame for dynamic-point removal
(:mod:`wardmap.edge.labels`); the pixels whose class is ``moving`` in the knowledge graph
(people) form the *person mask*, which is dilated by a margin (labels miss a person's edge,
hair, a raised hand) and then:

- ``blur``: the colour image inside the mask is replaced by a pixelated, Gaussian-smoothed
  copy (cells of :data:`BLUR_CELL_PX`), so a face or a badge cannot be read while the
  scene keeps its colours;
- ``blank``: the colour image inside the mask is set to :data:`BLANK_RGB`;
- ``off``: nothing is changed (a site's privacy officer decides; docs/security.md).

In both redacting modes the thermal raster is blanked inside the mask projected into the
thermal camera (through the depth image and ``T_rgb_thermal``): kelvin 0 is the raster's
"no data" value, so nothing downstream mistakes it for a temperature.

Keypoints are computed by the tracker on the raw frame before redaction, so tracking and the
features a keyframe carries are unchanged; only the images are redacted. The functions are pure
(new arrays out, inputs untouched).
"""

from __future__ import annotations

from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import ConfigError
from wardmap.shared.knowledge import Mobility
from wardmap.shared.se3 import transform_points

__all__ = [
    "BLANK_RGB",
    "BLUR_CELL_PX",
    "PRIVACY_MODES",
    "dilate",
    "mask_in_other_camera",
    "person_mask",
    "redact_rgb",
    "redact_thermal",
]

PRIVACY_MODES: Final = ("blur", "blank", "off")
"""Values of ``[agent] privacy``."""

BLUR_CELL_PX: Final = 16
"""Side of the pixelation cells of ``blur`` (pixels of the colour image); a face 60 px tall
keeps about four cells."""

BLANK_RGB: Final = (0, 0, 0)
"""Colour of ``blank`` pixels (RGB): black, which no JPEG ringing turns back into a face."""

Mask = NDArray[np.bool_]


def person_mask(class_image: NDArray[np.integer], mobility_lut: NDArray[np.uint8]) -> Mask:
    """Pixels of people: bool (H, W), True where the class is ``moving`` in the knowledge graph.

    Args:
        class_image: uint8/uint16 (H, W) class index per pixel (0 = background).
        mobility_lut: (C,) mobility code per class index (:meth:`KnowledgeGraph.mobility_lut`).

    Raises:
        ConfigError: a class index is outside the LUT.
    """
    classes = np.asarray(class_image)
    if classes.ndim != 2:
        raise ConfigError(f"person_mask: class image must be (H, W), got shape {classes.shape}")
    if classes.size and int(classes.max()) >= len(mobility_lut):
        raise ConfigError(f"person_mask: class index {int(classes.max())} outside the knowledge graph "
                          f"({len(mobility_lut)} classes)")
    moving: NDArray[np.bool_] = np.asarray(mobility_lut) == Mobility.MOVING.code
    return moving[classes]


def dilate(mask: Mask, margin_px: int) -> Mask:
    """``mask`` grown by ``margin_px`` pixels in every direction (a disc), as a new array."""
    if margin_px < 0:
        raise ConfigError(f"dilate: margin must be >= 0 px, got {margin_px}")
    if margin_px == 0 or not mask.any():
        return mask.copy()
    k = 2 * margin_px + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    return cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)


def redact_rgb(rgb: NDArray[np.uint8], mask: Mask, mode: str) -> NDArray[np.uint8]:
    """The colour image with ``mask`` redacted by ``mode`` (``blur``/``blank``/``off``).

    Args:
        rgb: uint8 (H, W, 3) colour image.
        mask: bool (H, W) pixels to redact (already dilated).

    Returns:
        A new uint8 (H, W, 3) image; pixels outside ``mask`` are unchanged.
    """
    if mode not in PRIVACY_MODES:
        raise ConfigError(f"privacy mode must be one of {', '.join(PRIVACY_MODES)}, got {mode!r}")
    if mask.shape != rgb.shape[:2]:
        raise ConfigError(f"redact_rgb: mask {mask.shape} does not match the image {rgb.shape[:2]}")
    out = rgb.copy()
    if mode == "off" or not mask.any():
        return out
    if mode == "blank":
        out[mask] = BLANK_RGB
        return out
    h, w = mask.shape
    small = cv2.resize(rgb, (max(1, w // BLUR_CELL_PX), max(1, h // BLUR_CELL_PX)),
                       interpolation=cv2.INTER_AREA)
    coarse = cv2.resize(small, (w, h), interpolation=cv2.INTER_NEAREST)
    smooth = cv2.GaussianBlur(coarse, (0, 0), BLUR_CELL_PX / 2)
    out[mask] = smooth[mask]
    return out


def mask_in_other_camera(
    mask: Mask, depth_m: NDArray[np.float32], cam: PinholeCamera, other: PinholeCamera,
    T_other_cam: NDArray[np.float64], margin_px: int,
) -> Mask:
    """``mask`` of ``cam``'s image seen by ``other``: bool (other.height, other.width).

    Every masked pixel with depth is moved to ``other`` with ``T_other_cam`` (4, 4; maps
    ``cam`` points to ``other`` points) and marked at its projection; the result is dilated by
    ``margin_px`` scaled to ``other``'s focal length plus one pixel (closes the gaps between
    projected pixels). Masked pixels without depth cannot be placed and are not projected.

    Args:
        depth_m: float32 (H, W) depth of ``cam``'s image in metres (0 = none).
    """
    out = np.zeros((other.height, other.width), bool)
    v, u = np.nonzero(mask & (depth_m > 0))
    if len(v) == 0:
        return out
    pts = transform_points(T_other_cam, cam.unproject(np.column_stack([u, v]).astype(np.float64),
                                                      depth_m[v, u]))
    uv, ok = other.project(pts)
    ok &= other.in_image(uv)
    out[np.rint(uv[ok, 1]).astype(np.intp), np.rint(uv[ok, 0]).astype(np.intp)] = True
    scale = other.fx / cam.fx
    return dilate(out, int(np.ceil(margin_px * scale)) + 1)


def redact_thermal(thermal_k: NDArray[np.float32], mask: Mask) -> NDArray[np.float32]:
    """The thermal image (h, w, kelvin) with ``mask`` set to 0 K ("no data"), as a new array."""
    if mask.shape != thermal_k.shape:
        raise ConfigError(f"redact_thermal: mask {mask.shape} does not match the image {thermal_k.shape}")
    out = np.array(thermal_k, np.float32, copy=True)
    out[mask] = 0.0
    return out
