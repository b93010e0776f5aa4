"""Sensor models of the simulated robot: RGB-D camera, thermal camera, their rig.

RGB: 640x480, registered depth with Kinect-v2-like noise (axial std growing with the
square of range), missing depth beyond range, at depth edges and on dark or specular
materials; a global shutter by default, or a rolling shutter (``rgb_readout_s``: each band
of rows rendered at its own instant, depth and labels registered with it). Thermal:
388x284, 37.7 x 28.7 deg (paper 003), beside the RGB camera, rendered from per-material
temperatures with optics blur and sensor noise (NETD).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import SimulationError
from wardmap.shared.se3 import inverse, make_transform, so3_exp
from wardmap.sim import raster
from wardmap.sim.geometry import TriangleSoup
from wardmap.sim.materials import MATERIALS

F64 = NDArray[np.float64]
KELVIN_OFFSET = 273.15


def _default_T_rgb_thermal() -> F64:
    # 6 cm to the right of the RGB camera, slightly toed in (0.4 deg about y, 0.2 deg about x).
    return make_transform(so3_exp([np.radians(0.2), np.radians(-0.4), 0.0]), [0.06, 0.0, 0.0])


def _default_T_base_rgb() -> F64:
    # Camera 1.05 m above the floor, 12 cm ahead of the wheel axle, tilted 6 deg down.
    # Base: x forward, y left, z up. Camera: x right, y down, z forward.
    R_base_cam = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    tilt = so3_exp([np.radians(6.0), 0.0, 0.0])  # about the camera x axis: look down
    return make_transform(R_base_cam @ tilt, [0.12, 0.0, 1.05])


@dataclass(frozen=True)
class SensorRig:
    """Cameras, their mounting and noise parameters.

    Attributes:
        rgb: RGB camera (depth is registered to it).
        thermal: thermal camera.
        T_rgb_thermal: thermal camera pose in the RGB camera frame (4, 4).
        T_base_rgb: RGB camera pose in the robot base frame (4, 4).
        depth_min_m, depth_max_m: valid depth range.
        depth_noise_a_m, depth_noise_b_per_m: axial depth std = a + b * z^2 (metres).
        depth_edge_dropout: probability of no depth on pixels next to a depth edge.
        rgb_noise_std: colour noise std in 8-bit levels.
        thermal_blur_px: Gaussian optics blur of the thermal image (pixels).
        thermal_netd_k: thermal noise std in kelvin.
        rgb_readout_s: rolling-shutter readout time of the RGB camera (first row to last),
            seconds; row ``v`` is exposed ``(v - cy) / height`` readouts after the frame's
            stamp (the middle row's instant, the tracker's convention, docs/tracking.md);
            registered depth and labels follow the same rows. 0: global shutter.
        readout_band_rows: rows rendered at one instant under a rolling shutter (the pose
            is interpolated no finer: 16 rows of 480 at 30 ms are 1 ms apart).
    """

    rgb: PinholeCamera = field(default_factory=lambda: PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5))
    thermal: PinholeCamera = field(default_factory=lambda: PinholeCamera.from_fov(388, 284, 37.7, 28.7))
    T_rgb_thermal: F64 = field(default_factory=_default_T_rgb_thermal)
    T_base_rgb: F64 = field(default_factory=_default_T_base_rgb)
    depth_min_m: float = 0.4
    depth_max_m: float = 8.0
    depth_noise_a_m: float = 0.0015
    depth_noise_b_per_m: float = 0.0005
    depth_edge_dropout: float = 0.5
    rgb_noise_std: float = 1.5
    thermal_blur_px: float = 0.8
    thermal_netd_k: float = 0.05
    rgb_readout_s: float = 0.0
    readout_band_rows: int = 16

    def __post_init__(self) -> None:
        if not (np.isfinite(self.rgb_readout_s) and 0.0 <= self.rgb_readout_s <= 0.1):
            raise SimulationError(f"rgb_readout_s must be in [0, 0.1] seconds, got {self.rgb_readout_s}")
        if self.readout_band_rows < 1:
            raise SimulationError(f"readout_band_rows must be >= 1, got {self.readout_band_rows}")

    def readout_bands(self) -> list[tuple[int, int, float]]:
        """Under a rolling shutter, ``(first row, end row, seconds after the stamp)`` per band
        of rows (its middle row's instant); one band at 0 for a global shutter."""
        cam = self.rgb
        if self.rgb_readout_s == 0.0:
            return [(0, cam.height, 0.0)]
        return [(r0, min(r0 + self.readout_band_rows, cam.height),
                 ((r0 + min(r0 + self.readout_band_rows, cam.height) - 1) / 2.0 - cam.cy) / cam.height
                 * self.rgb_readout_s)
                for r0 in range(0, cam.height, self.readout_band_rows)]


@dataclass(frozen=True)
class SensorFrame:
    """One synchronised capture.

    Attributes:
        rgb: uint8 (H, W, 3) RGB.
        depth_m: float32 (H, W) metres along the RGB camera z axis, 0 = no data.
        labels: uint16 (H, W) instance id per RGB pixel, 0 = none.
        thermal_k: float32 (h, w) temperature in kelvin.
        depth_true_m: float32 (H, W) noise-free depth (for tests), 0 = nothing hit.
    """

    rgb: NDArray[np.uint8]
    depth_m: NDArray[np.float32]
    labels: NDArray[np.uint16]
    thermal_k: NDArray[np.float32]
    depth_true_m: NDArray[np.float32]


class SensorSimulator:
    """Renders sensor frames of one world. Owns the texture mip atlas and material tables."""

    def __init__(
        self, static: TriangleSoup, texture_stack: NDArray[np.uint8], rig: SensorRig | None = None
    ) -> None:
        self.rig = rig or SensorRig()
        self.static = static
        self.atlas = raster.build_mipmaps(texture_stack)
        self.temp_k = np.array([m.temperature_c + KELVIN_OFFSET for m in MATERIALS], np.float32)
        self.contrast_k = np.array([m.thermal_contrast_k for m in MATERIALS], np.float32)
        self.dropout = depth_dropout_table()
        self.emissive = np.array([m.emissive for m in MATERIALS], bool)
        self.T_rgb_thermal = self.rig.T_rgb_thermal

    def mesh(self, dynamic: TriangleSoup | None) -> raster.Mesh:
        soup = TriangleSoup.concat([self.static, dynamic]) if dynamic is not None else self.static
        return raster.Mesh(soup.vertices, soup.uv, soup.texture, soup.instance, soup.material, soup.shade)

    def capture(
        self, T_world_rgb: F64, dynamic: TriangleSoup | None, light: float, rng: np.random.Generator,
        *, band_poses: Sequence[F64] | None = None,
    ) -> SensorFrame:
        """Render RGB, depth, labels and thermal at the RGB camera pose ``T_world_rgb``.

        ``light`` scales scene illumination (1 normal, 0.02 lights off); emissive
        materials keep glowing. All noise comes from ``rng``. ``band_poses``: under a rolling
        shutter, the RGB camera's pose (4, 4) at each band of :meth:`SensorRig.readout_bands`
        (RGB, depth and labels of its rows rendered there; thermal stays at ``T_world_rgb``).
        """
        rig, cam = self.rig, self.rig.rgb
        mesh = self.mesh(dynamic)
        bands = rig.readout_bands()
        poses = [T_world_rgb] if band_poses is None else list(band_poses)
        if len(poses) != len(bands):
            raise SimulationError(f"capture: {len(poses)} band poses for {len(bands)} bands")
        parts = [
            raster.render(mesh, self.atlas, (cam.fx, cam.fy, cam.cx, cam.cy - r0), cam.width, r1 - r0,
                          inverse(T), sample_gray=False)
            for (r0, r1, _), T in zip(bands, poses, strict=True)
        ]
        out = parts[0] if len(parts) == 1 else _stack_rows(parts)
        if out.color is None:
            raise RuntimeError("renderer returned no colour")
        gain = np.where(self.emissive[out.material], np.float32(max(light, 0.8)), np.float32(light))
        noise = rng.standard_normal(size=out.color.shape, dtype=np.float32) * np.float32(rig.rgb_noise_std)
        rgb_f = out.color * (255.0 * gain)[..., None] + noise
        rgb = np.clip(rgb_f + 0.5, 0, 255).astype(np.uint8)

        depth_true = out.depth
        depth = depth_noise(depth_true, out.material, rig, self.dropout, rng)

        th = self.rig.thermal
        T_world_th = T_world_rgb @ self.T_rgb_thermal
        tout = raster.render(
            mesh,
            self.atlas,
            (th.fx, th.fy, th.cx, th.cy),
            th.width,
            th.height,
            inverse(T_world_th),
            sample_color=False,
            sample_gray=True,
        )
        if tout.texel_gray is None:
            raise RuntimeError("renderer returned no grey level")
        temp = self.temp_k[tout.material] + self.contrast_k[tout.material] * (tout.texel_gray - 0.5)
        temp_blur = cv2.GaussianBlur(temp, (0, 0), rig.thermal_blur_px)
        temp_noisy = temp_blur + rng.standard_normal(size=temp.shape, dtype=np.float32) * np.float32(
            rig.thermal_netd_k
        )
        return SensorFrame(rgb, depth, out.instance.copy(), temp_noisy.astype(np.float32), depth_true)


def _stack_rows(parts: Sequence[raster.RenderOut]) -> raster.RenderOut:
    """Bands of rows rendered apart, as one image (top to bottom)."""
    colors = [p.color for p in parts]
    return raster.RenderOut(
        np.concatenate([p.depth for p in parts]), np.concatenate([p.instance for p in parts]),
        np.concatenate([p.material for p in parts]),
        None if any(c is None for c in colors) else np.concatenate([c for c in colors if c is not None]),
        None,
    )


def depth_dropout_table() -> NDArray[np.float32]:
    """Per-material probability (n_materials,) of a pixel without depth."""
    return np.array([m.depth_dropout for m in MATERIALS], np.float32)


def depth_noise(
    z: NDArray[np.float32],
    material: NDArray[np.uint16],
    rig: SensorRig,
    dropout: NDArray[np.float32],
    rng: np.random.Generator,
) -> NDArray[np.float32]:
    """The depth sensor's reading (H, W) float32 metres, 0 = no data, of true depth ``z`` (H, W).

    Axial noise ``a + b z^2``, no data out of range, blob-shaped holes on materials with a
    ``depth_dropout`` (``dropout`` indexed by ``material`` (H, W)) and at depth edges.
    """
    h, w = z.shape
    sigma = rig.depth_noise_a_m + rig.depth_noise_b_per_m * z * z
    noisy = z + sigma * rng.standard_normal(size=z.shape, dtype=np.float32)
    valid = (z >= rig.depth_min_m) & (z <= rig.depth_max_m)
    # Holes on dark / specular materials come in blobs: threshold a smooth random field.
    coarse = rng.random((h // 8 + 1, w // 8 + 1), dtype=np.float32)
    blobs = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_LINEAR)
    valid &= blobs >= dropout[material]
    # Depth edges: mixed pixels are rejected by the sensor (dilated edge band).
    zmax = cv2.dilate(z, np.ones((3, 3), np.uint8))
    zmin = cv2.erode(z, np.ones((3, 3), np.uint8))
    edge = (zmax - zmin) > 0.04 * np.maximum(z, 0.1)
    edge = cv2.dilate(edge.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    valid &= ~(edge & (rng.random(z.shape, dtype=np.float32) < rig.depth_edge_dropout))
    return np.where(valid, noisy, 0.0).astype(np.float32)
