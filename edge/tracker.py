"""The edge tracking frontend (papers 001 and 003): one camera frame in, one pose out.

Per frame: ORB features on a grid (paper 003 Eq. 3-5) -> dynamic-point removal with the
semantic descriptor and the knowledge graph (paper 001 Eq. 6-8) -> guided matching
against the local map, predicted by wheel odometry (or a constant-velocity model) ->
EPnP in RANSAC -> Huber motion-only refinement -> keyframe decision. When RGB is too
dark or yields too few inliers: relocalisation against recent keyframes, then tracking
on thermal SIFT with depth moved through the calibration (paper 003 Sec. IV-C), then
wheel odometry; without odometry (a hand-held or odometry-less camera), depth-only ICP
against the last measured frame (``edge/icp.py``) before giving up. Every result says
which source produced the pose.

The tracker's world frame is the robot's odom frame when odometry and ``T_base_rgb``
are known at the first frame (so poses are ``T_odom_camera``), else the first camera
frame.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from wardmap.edge.features import (
    Features,
    OrbConfig,
    OrbExtractor,
    SiftConfig,
    extract_sift_adaptive,
    match_descriptors,
    match_projected,
    thermal_to_gray8,
)
from wardmap.edge.icp import DepthPyramid, IcpConfig, icp
from wardmap.edge.localba import (
    BaProblem,
    CovisibilityGraph,
    Intrinsics,
    LocalBaConfig,
    LocalBundleAdjuster,
)
from wardmap.edge.mapstore import Keyframe, MapPoints
from wardmap.edge.pose import refine_pose_huber, refine_pose_rolling_shutter, solve_pnp_ransac
from wardmap.edge.sbi import SmallBlurryImage, rotation_between
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.dataset import Calibration
from wardmap.shared.errors import ConfigError
from wardmap.shared.se3 import (
    interpolate_transform,
    inverse,
    rotation_angle,
    se3_exp,
    se3_log,
    so3_log,
    transform_points,
    yaw_rotation,
)
from wardmap.shared.semantic import SemanticConfig, dynamic_mask, semantic_distance

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
PoseSource = Literal["init", "rgb", "relocalised", "thermal", "depth", "odometry", "motion_model", "none"]
GAP_RATIO = 1.5
"""A frame this many times the last step's time after the last frame follows a gap (dropped frames)."""
MOTION_MODEL_MAX_S = 0.2
"""The constant-velocity prior extrapolates the last step's twist over at most this long (seconds):
a frame after a gap (frames dropped by the stream) is predicted as far as the camera kept moving,
a long gap no further than this."""


def level_toward_floor(T_world_cam: F64, T_base_rgb: F64, gain: float) -> F64:
    """``T_world_cam`` (4, 4) moved ``gain`` (0..1) of the way to the camera pose of a level base.

    The level base keeps the base's x, y and yaw in the world (= odom) frame and sets its
    roll, pitch and height to 0 (the floor); the camera sits on it at ``T_base_rgb`` (4, 4).
    Rotation is slerped, translation interpolated (:func:`interpolate_transform`).
    """
    T_wb = T_world_cam @ inverse(T_base_rgb)
    level = np.eye(4)
    level[:3, :3] = yaw_rotation(float(np.arctan2(T_wb[1, 0], T_wb[0, 0])))
    level[:2, 3] = T_wb[:2, 3]
    return interpolate_transform(T_world_cam, level @ T_base_rgb, gain)


@dataclass(frozen=True)
class TrackerConfig:
    """Frontend parameters (``[tracker]`` table in a TOML config).

    Attributes:
        orb: ORB extraction (paper 003 grid).
        sift: thermal SIFT with adaptive contrast threshold (paper 003 Sec. IV-C).
        semantic: dynamic-point removal (paper 001: n = 21, delta = 55, distance 110).
        icp: the depth-only fallback for blurred RGB frames when there is no odometry.
        match_radius_px: search radius around a map point's predicted pixel.
        match_radius_lost_px: wider radius for a second attempt.
        refine_radius_px: window of the second, pose-refining match pass (0 disables it).
        max_hamming: largest ORB descriptor distance of a match.
        min_inliers: fewest PnP inliers for a visual pose.
        min_depth_m, max_depth_m: depth range for new map points.
        depth_edge_ratio: a keypoint whose depth exceeds the nearest valid depth of its 3x3
            neighbourhood by more than this fraction of its own reads the background beside an
            occluding contour: a corner there is made by the nearer edge and slides over the
            background as the camera moves, no fixed 3D point. It makes no map point and
            its depth is not fused into one; the pose still uses it. 0 (the default) disables
            it: it lowers drift on the simulated corridors but changes single frames of the TUM
            recording for the worse (decision 0052).
        dark_mean_level: mean grey level below which RGB is too dark to track.
        kf_max_interval_s: a keyframe at least this often while tracking.
        kf_translation_m, kf_rotation_deg: motion since the last keyframe that makes one.
        kf_tracked_ratio: a keyframe when fewer than this share of the last keyframe's
            inliers are still tracked (ORB-SLAM2's rule).
        local_keyframes: map points last seen this many keyframes ago are dropped.
        max_map_points: cap on the local map (oldest dropped first).
        reloc_keyframes: recent keyframes tried when relocalising.
        thermal: use the thermal fallback when the data has thermal images.
        direct_from_prior: refine from the prior without RANSAC when that keeps at least
            half of the matches (ORB-SLAM2's motion-model tracking); EPnP RANSAC otherwise.
        max_lost_before_restart: lost frames (no measured pose) after which a new map is
            started from the current guess; before that, relocalisation keeps trying.
        thermal_odometry_blend: weight of a thermal pose against the odometry prediction
            (1 = thermal alone); thermal poses are noisier frame to frame than odometry.
        max_fuse_weight: cap of a map point's averaging weight (lets points keep adapting).
        rgbd_bf: virtual stereo baseline times fx (ORB-SLAM2's ``Camera.bf``, 40 for a
            Kinect-class camera): keypoints with depth add a virtual right coordinate to
            the pose refinement (``refine_pose_huber``); 0 = reprojection only.
        rgbd_max_depth_m: keypoints farther than this are monocular observations
            (ORB-SLAM2's ``ThDepth`` x baseline: 40 x 40 / 517 = 3.1 m).
        floor_level_tau_s: ground robots (world = odom frame, ``T_base_rgb`` known): time
            constant (s) of a complementary filter that pulls each visual pose's roll, pitch
            and height toward those of a level base on the floor (the odom frame's z = 0
            plane); visual drift in tilt and height is slow, the base's wobble fast. Each
            frame moves ``1 - exp(-dt / tau)`` of the way. 0 disables it (e.g. ramps).
        rs_shear_sigma_rad: rolling shutter (a calibration with ``readout_s > 0``): each
            frame's own spin over one readout is fitted with its pose
            (:func:`wardmap.edge.pose.refine_pose_rolling_shutter`); this is the standard
            deviation (radians) of its prior, the motion model's spin times the readout.
        local_ba: local bundle adjustment of the keyframes covisible with each new one
            (:mod:`wardmap.edge.localba`).
        sbi_scale: when the motion model's prior finds no pose, the camera's rotation since
            the last tracked frame is measured on thumbnails of this scale
            (:mod:`wardmap.edge.sbi`, 1/16: 40x30 from VGA) and the local map matched again
            from that prior before relocalising; 0 turns it off.
        sbi_blur_px: Gaussian sigma of the thumbnails, in thumbnail pixels.
        fuse_radius_px: at each keyframe, a map point this frame did not match that projects
            within this many pixels of a keypoint about to make a new point, with a close
            descriptor and depth, takes that observation instead (ORB-SLAM2's Fuse, whose
            ``th`` is 3); 0 (the default) turns it off.
        fuse_max_hamming: largest ORB descriptor distance of such a match (ORB-SLAM2's
            ``TH_LOW = 50``).
    """

    orb: OrbConfig = field(default_factory=OrbConfig)
    sift: SiftConfig = field(default_factory=SiftConfig)
    semantic: SemanticConfig = field(default_factory=SemanticConfig)
    icp: IcpConfig = field(default_factory=IcpConfig)
    match_radius_px: float = 15.0
    match_radius_lost_px: float = 40.0
    refine_radius_px: float = 4.0
    max_hamming: int = 64
    min_inliers: int = 25
    min_depth_m: float = 0.3
    max_depth_m: float = 6.0
    depth_edge_ratio: float = 0.0
    dark_mean_level: float = 18.0
    kf_max_interval_s: float = 1.0
    kf_translation_m: float = 0.25
    kf_rotation_deg: float = 10.0
    kf_tracked_ratio: float = 0.7
    local_keyframes: int = 12
    max_map_points: int = 6000
    reloc_keyframes: int = 8
    thermal: bool = True
    thermal_odometry_blend: float = 0.15
    max_lost_before_restart: int = 5
    direct_from_prior: bool = True
    max_fuse_weight: float = 20.0
    rgbd_bf: float = 40.0
    rgbd_max_depth_m: float = 3.1
    floor_level_tau_s: float = 2.0
    rs_shear_sigma_rad: float = 0.02
    local_ba: LocalBaConfig = field(default_factory=LocalBaConfig)
    sbi_scale: float = 1 / 16
    sbi_blur_px: float = 0.75
    fuse_radius_px: float = 0.0
    fuse_max_hamming: int = 50

    def __post_init__(self) -> None:
        if not (np.isfinite(self.sbi_scale) and 0 <= self.sbi_scale <= 1):
            raise ConfigError(f"tracker.sbi_scale must be in [0, 1] (0 = off), got {self.sbi_scale}")
        if not (np.isfinite(self.sbi_blur_px) and self.sbi_blur_px >= 0):
            raise ConfigError(f"tracker.sbi_blur_px must be >= 0, got {self.sbi_blur_px}")
        if not (np.isfinite(self.fuse_radius_px) and self.fuse_radius_px >= 0):
            raise ConfigError(f"tracker.fuse_radius_px must be >= 0 (0 = off), got {self.fuse_radius_px}")
        if not 0 <= self.fuse_max_hamming <= 256:
            raise ConfigError(f"tracker.fuse_max_hamming must be in [0, 256], got {self.fuse_max_hamming}")
        if self.min_inliers < 6:
            raise ConfigError("tracker.min_inliers must be at least 6 (EPnP needs >= 4 + RANSAC)")
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise ConfigError("tracker: need 0 < min_depth_m < max_depth_m")
        if self.match_radius_px <= 0 or self.match_radius_lost_px < self.match_radius_px:
            raise ConfigError("tracker: need 0 < match_radius_px <= match_radius_lost_px")
        if not (np.isfinite(self.rs_shear_sigma_rad) and self.rs_shear_sigma_rad > 0):
            raise ConfigError(f"tracker.rs_shear_sigma_rad must be > 0, got {self.rs_shear_sigma_rad}")
        if not (np.isfinite(self.floor_level_tau_s) and self.floor_level_tau_s >= 0):
            raise ConfigError(
                f"tracker.floor_level_tau_s must be >= 0 (0 = off), got {self.floor_level_tau_s}"
            )


@dataclass(frozen=True)
class TrackInput:
    """One frame for the tracker.

    Attributes:
        stamp: seconds.
        rgb: uint8 (H, W, 3) RGB, or None if the colour image is missing.
        depth_m: float32 (H, W) metres, 0 = no data (NaN treated as no data).
        thermal_k: float32 (h, w) kelvin, or None.
        T_odom_base: wheel-odometry pose of the base at ``stamp`` (4, 4), or None.
        class_image: uint8 (H, W) knowledge-graph class per pixel, or None (no labels).
        problem: a known problem with this frame (e.g. an unreadable file); it is lost.
    """

    stamp: float
    rgb: NDArray[np.uint8] | None
    depth_m: NDArray[np.float32] | None
    thermal_k: NDArray[np.float32] | None = None
    T_odom_base: F64 | None = None
    class_image: NDArray[np.uint8] | None = None
    problem: str = ""


@dataclass(frozen=True)
class TrackResult:
    """The tracker's answer for one frame.

    ``T_world_camera`` is always set (a prediction when lost). ``lost`` is True when no
    sensor measured the pose (neither vision nor odometry); ``reason`` says why.
    """

    stamp: float
    T_world_camera: F64
    source: PoseSource
    lost: bool
    reason: str
    n_features: int
    n_dynamic: int
    n_matches: int
    n_inliers: int
    keyframe: bool
    timings_ms: dict[str, float]
    features: Features | None = None
    """On RGB keyframes: the frame's ORB features after dynamic-point removal (what the map
    was built from; for the wire). None otherwise."""
    point_ids: NDArray[np.int64] | None = None
    """With ``features``: int64 (N,) the local map point each keypoint observed (a matched
    inlier) or made, -1 for none; an id names one point for the tracker's lifetime (the map
    restarts keep counting), so equal ids in two keyframes are one observed point."""


class Tracker:
    """Stateful frontend for one camera stream. Not thread-safe: one owner calls ``track``.

    With ``local_ba`` enabled it owns a :class:`LocalBundleAdjuster` (a worker process in
    ``process`` mode): call :meth:`close` when done (or use the tracker as a context manager).
    """

    def __init__(
        self,
        calibration: Calibration,
        config: TrackerConfig | None = None,
        mobility_lut: NDArray[np.uint8] | None = None,
    ) -> None:
        self.cfg = config or TrackerConfig()
        self.calib = calibration
        self.cam: PinholeCamera = calibration.rgb
        self.readout = calibration.readout  # rolling-shutter readout time and where it came from
        self.orb = OrbExtractor(self.cfg.orb)
        self.mobility_lut = mobility_lut
        self.map = MapPoints()
        self.keyframes: list[Keyframe] = []  # the most recent ones, for relocalisation
        self._kf_count = 0  # keyframes made so far (indexes never repeat)
        self.fused_points = 0  # observations old points took instead of twins (fuse_radius_px)
        # Last RGB-tracked frame, for relocalisation; made into a Keyframe only when needed.
        self._last_frame_raw: tuple[float, F64, Features, NDArray[np.float64]] | None = None
        self._rgb_failures = 0  # consecutive frames whose RGB image did not fit the map
        self._sbi = (SmallBlurryImage(self.cam, self.cfg.sbi_scale, self.cfg.sbi_blur_px)
                     if self.cfg.sbi_scale else None)
        # The last RGB-tracked frame's grey image and pose, for the rotation fallback (thumbnails
        # are made only when it runs).
        self._sbi_ref: tuple[NDArray[np.uint8], F64] | None = None
        self._frame_index = -1
        self._T_world_cam: F64 | None = None
        self._velocity: F64 = np.eye(4)  # T_prev_cur of the last step (camera frames)
        self._prev_stamp: float | None = None
        self._prev_dt = 0.0  # seconds spanned by self._velocity
        self._cpu_start = 0.0
        self._prev_odom: F64 | None = None
        self._kf_inliers = 0
        self._kf_T: F64 | None = None
        self._kf_stamp = -np.inf
        self._thermal_ref: tuple[Features, F64] | None = None
        self._thermal_ref_T: F64 = np.eye(4)
        self._thermal_last: tuple[Features, int, int] | None = None  # last thermal match
        # Last keyframe's thermal image, depth and pose: turned into a SIFT reference only
        # when RGB fails, so normal tracking pays nothing for the thermal fallback.
        self._thermal_pending: tuple[NDArray[np.float32], NDArray[np.float32], F64] | None = None
        self._sift_contrast: float | None = None
        self._T_world_odom: F64 | None = None
        # Depth of the last frame with a measured pose, for the ICP fallback: the array and
        # its pose are kept, the pyramid is built only when a frame needs it.
        self._depth_ref: tuple[F64, NDArray[np.float32]] | None = None
        self._depth_ref_index = -1  # its frame index
        self._depth_ref_pyr: DepthPyramid | None = None
        self._rays: F64 | None = None
        # Local bundle adjustment: the graph is this thread's; problems are copies of it,
        # solutions are applied at the start of the next frame (_apply_local_ba).
        self._map_epoch = 0  # +1 when the map restarts: older solutions are stale
        self._ba_graph = CovisibilityGraph(self.cam, self.cfg.local_ba)
        self._ba_problem: BaProblem | None = None  # made at a keyframe, submitted after the frame
        self._ba: LocalBundleAdjuster | None = None
        if self.cfg.local_ba.enabled:
            self._ba = LocalBundleAdjuster(
                Intrinsics(self.cam.fx, self.cam.fy, self.cam.cx, self.cam.cy, self.cfg.local_ba.stereo_bf,
                           self.cfg.rgbd_max_depth_m),
                self.cfg.local_ba,
            )

    def __enter__(self) -> Tracker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the bundle-adjustment worker, if any."""
        if self._ba is not None:
            self._ba.close()

    def local_ba_stats(self) -> dict[str, float | int] | None:
        """The bundle adjuster's counters (:class:`~wardmap.edge.localba.BaStats`), or None when off."""
        return None if self._ba is None else self._ba.stats.summary()

    # ------------------------------------------------------------------ public
    def track(self, inp: TrackInput) -> TrackResult:
        """Estimate the camera pose of one frame; never raises on bad frame content.

        A keyframe's bundle-adjustment problem is handed to the adjuster after the frame's
        timing ends (``inline``: solved here, its time in :meth:`local_ba_stats`).
        """
        result = self._track(inp)
        if self._ba is not None and self._ba_problem is not None:
            self._ba.submit(self._ba_problem)
        self._ba_problem = None
        return result

    def _track(self, inp: TrackInput) -> TrackResult:
        self._frame_index += 1
        timings: dict[str, float] = {}
        t_start = time.perf_counter()
        self._cpu_start = time.thread_time()
        if self._ba is not None:
            t0 = time.perf_counter()
            self._apply_local_ba()
            timings["local_ba"] = _ms(t0)
        prior, prior_source = self._predict(inp)
        bad = _frame_problem(inp, self.cam)
        if bad:
            return self._fallback(inp, prior, prior_source, bad, timings, t_start, n_feat=0)

        assert inp.rgb is not None and inp.depth_m is not None  # checked by _frame_problem
        depth = inp.depth_m.copy()
        depth[~np.isfinite(depth)] = 0.0  # 3x faster than np.nan_to_num on a VGA frame
        gray: NDArray[np.uint8] = np.asarray(cv2.cvtColor(inp.rgb, cv2.COLOR_RGB2GRAY), np.uint8)
        dark = float(gray.mean()) < self.cfg.dark_mean_level
        t0 = time.perf_counter()
        feats = self.orb.extract(gray) if not dark else None
        timings["features"] = _ms(t0)

        n_dyn = 0
        sem = None
        if (
            feats is not None
            and len(feats.uv)
            and inp.class_image is not None
            and self.mobility_lut is not None
            and self.cfg.semantic.enabled
        ):
            t0 = time.perf_counter()
            res = dynamic_mask(
                inp.class_image,
                feats.uv,
                feats.angle_deg,
                self.mobility_lut,
                n=self.cfg.semantic.n,
                delta=self.cfg.semantic.delta,
            )
            keep = ~res.dynamic
            n_dyn = int(res.dynamic.sum())
            feats = feats.select(keep)
            sem = res.descriptors[keep]
            timings["dynamic"] = _ms(t0)

        if feats is None or len(feats.uv) < self.cfg.min_inliers:
            reason = "RGB too dark" if dark else f"too few features ({0 if feats is None else len(feats.uv)})"
            return self._fallback(
                inp,
                prior,
                prior_source,
                reason,
                timings,
                t_start,
                n_feat=0 if feats is None else len(feats.uv),
                n_dyn=n_dyn,
                depth=depth,
            )

        kp_depth = _depth_at(depth, feats.uv)
        # Keypoints behind a depth edge: no map point, no depth fused (the pose still uses them).
        on_edge = _behind_depth_edge(depth, feats.uv, self.cfg.depth_edge_ratio)
        feats_raw, kp_depth_raw = feats, kp_depth
        readout = self.readout.readout_s
        if readout > 0 and self._prev_dt > 0:
            # Rolling shutter: keypoints moved to the middle row's instant (motion model's spin).
            omega = so3_log(self._velocity[:3, :3]) / self._prev_dt
            if np.linalg.norm(omega) * readout * self.cam.fx > 0.1:  # the edge rows move > 0.05 px
                t0 = time.perf_counter()
                feats, kp_depth = unroll_keypoints(self.cam, readout, omega, feats, kp_depth)
                timings["unroll"] = _ms(t0)
        if len(self.map) == 0:
            T = prior
            z_map = np.where(on_edge, 0.0, kp_depth)
            made = self._insert_keyframe(inp.stamp, T, feats, z_map, sem, new_all=True)
            self._accept(inp, T, n_inliers=len(feats.uv))
            self._set_depth_ref(T, depth)
            self._maybe_thermal_ref(inp, depth, T, timings)
            return self._result(
                inp, T, "init", False, "", feats, n_dyn, 0, len(feats.uv), True, timings, t_start,
                point_ids=made,
            )

        t0 = time.perf_counter()
        T_cw_prior = inverse(prior)
        m_idx, f_idx = self._match_map(T_cw_prior, feats, sem, self.cfg.match_radius_px)
        if len(m_idx) < self.cfg.min_inliers:
            m_idx, f_idx = self._match_map(T_cw_prior, feats, sem, self.cfg.match_radius_lost_px)
        timings["match"] = _ms(t0)

        t0 = time.perf_counter()
        T_cw, inl = self._pose_from_matches(m_idx, f_idx, feats, kp_depth, T_cw_prior)
        timings["pose"] = _ms(t0)
        if T_cw is None and self._sbi is not None and self._sbi_ref is not None:
            t0 = time.perf_counter()
            T_cw, inl, m_idx, f_idx = self._track_from_rotation(gray, prior, feats, sem, kp_depth,
                                                                 (m_idx, f_idx))
            timings["sbi"] = _ms(t0)
        source: PoseSource = "rgb"
        if T_cw is None:
            t0 = time.perf_counter()
            T_cw, inl, m_idx, f_idx = self._relocalise(feats, kp_depth)
            timings["relocalise"] = _ms(t0)
            source = "relocalised"
            if T_cw is not None and prior_source == "odometry" and not _near(inverse(T_cw), prior, 0.5, 20.0):
                T_cw = None  # wheel odometry says the match is elsewhere: a look-alike place
        if T_cw is None:
            # Image is fine but the map does not fit: thermal / odometry give the pose, and a
            # fresh map is started from this frame so RGB tracking resumes.
            result = self._fallback(
                inp,
                prior,
                prior_source,
                "RGB tracking failed",
                timings,
                t_start,
                n_feat=len(feats.uv),
                n_dyn=n_dyn,
                depth=depth,
                n_matches=len(m_idx),
            )
            # Start a fresh map from this frame when its pose was measured (thermal, odometry);
            # after a guess, keep the old map a few frames so relocalisation can recover.
            # A depth pose keeps the old map: the next sharp frame is still likely to fit it.
            self._rgb_failures += 1
            measured = not result.lost and result.source != "depth"
            if measured or self._rgb_failures > self.cfg.max_lost_before_restart:
                z_map = np.where(on_edge, 0.0, kp_depth)
                self._restart_map(inp.stamp, result.T_world_camera, feats, z_map, sem)
                self._rgb_failures = 0
            return result

        if source == "rgb" and self.cfg.refine_radius_px > 0:
            # ORB-SLAM2's TrackLocalMap: re-project the local map with the estimated pose in
            # a small window, gaining matches, and refine once more (no RANSAC needed).
            t0 = time.perf_counter()
            m2, f2 = self._match_map(T_cw, feats, sem, self.cfg.refine_radius_px)
            if len(m2) >= int(inl.sum()):
                sigma = np.power(self.cfg.orb.scale_factor, feats.octave[f2].astype(np.float64))
                T2, inl2 = self._refine(
                    self.map.pos_world[m2], feats.uv[f2].astype(np.float64), T_cw, sigma, kp_depth[f2]
                )
                if int(inl2.sum()) >= self.cfg.min_inliers:
                    T_cw, inl, m_idx, f_idx = T2, inl2, m2, f2
            timings["refine"] = _ms(t0)
        if readout > 0:
            # Rolling shutter: this frame's own spin, fitted with its pose (the prior's lags).
            t0 = time.perf_counter()
            fit = self._rolling_shutter_refit(T_cw, m_idx, f_idx, inl, feats_raw, kp_depth_raw)
            if fit is not None:
                T_cw, inl, feats, kp_depth = fit
            timings["rolling_shutter"] = _ms(t0)
        T = self._level(inverse(T_cw), inp.stamp)
        T_cw = inverse(T)
        n_inl = int(inl.sum())
        t0 = time.perf_counter()
        kp_depth_map = np.where(on_edge, 0.0, kp_depth)
        self._fuse(T_cw, m_idx[inl], feats.uv[f_idx[inl]], kp_depth_map[f_idx[inl]])
        is_kf = self._need_keyframe(inp.stamp, T, n_inl)
        ids = None
        if is_kf:
            matched = np.zeros(len(feats.uv), bool)
            matched[f_idx[inl]] = True
            self.map.kf_last[m_idx[inl]] = self._kf_count
            ids = self._insert_keyframe(inp.stamp, T, feats, kp_depth_map, sem, skip=matched,
                                        observed=(m_idx[inl], f_idx[inl]))
            self._maybe_thermal_ref(inp, depth, T, timings)
        self._last_frame_raw = (inp.stamp, T, feats, kp_depth)
        if self._sbi is not None:
            self._sbi_ref = (gray, T)
        self._rgb_failures = 0
        timings["map"] = _ms(t0)
        self._accept(inp, T, n_inliers=n_inl, keyframe=is_kf)
        self._set_depth_ref(T, depth)
        return self._result(
            inp, T, source, False, "", feats, n_dyn, len(m_idx), n_inl, is_kf, timings, t_start,
            point_ids=ids,
        )

    # ------------------------------------------------------------------ prediction
    def _level(self, T_world_cam: F64, stamp: float) -> F64:
        """A visual pose moved part-way to a level base on the floor (``floor_level_tau_s``)."""
        T_base_rgb, tau = self.calib.T_base_rgb, self.cfg.floor_level_tau_s
        if tau <= 0 or self._T_world_odom is None or T_base_rgb is None or self._prev_stamp is None:
            return T_world_cam
        dt = min(max(stamp - self._prev_stamp, 0.0), 1.0)
        return level_toward_floor(T_world_cam, T_base_rgb, 1.0 - float(np.exp(-dt / tau)))

    def _predict(self, inp: TrackInput) -> tuple[F64, PoseSource]:
        """Prior pose ``T_world_camera``: odometry increment, else constant velocity."""
        T_base_rgb = self.calib.T_base_rgb
        if self._T_world_cam is None:
            if inp.T_odom_base is not None and T_base_rgb is not None:
                self._T_world_odom = np.eye(4)
                return inp.T_odom_base @ T_base_rgb, "odometry"
            return np.eye(4), "none"
        if inp.T_odom_base is not None and self._prev_odom is not None and T_base_rgb is not None:
            step = inverse(T_base_rgb) @ inverse(self._prev_odom) @ inp.T_odom_base @ T_base_rgb
            return self._T_world_cam @ step, "odometry"
        return self._T_world_cam @ self._motion_step(inp.stamp), "motion_model"

    def _motion_step(self, stamp: float) -> F64:
        """``T_prev_cur`` predicted for a frame at ``stamp``: after a gap (frames dropped: more
        than :data:`GAP_RATIO` times the last step's time since the last frame) the last step's
        twist over that time, at most :data:`MOTION_MODEL_MAX_S`; otherwise the last step as
        measured (a recording's stamp jitter is not motion: scaling by it made the TUM excerpt's
        early keyframes worse)."""
        if self._prev_stamp is None or self._prev_dt <= 0:
            return self._velocity
        ratio = min(stamp - self._prev_stamp, MOTION_MODEL_MAX_S) / self._prev_dt
        if ratio < GAP_RATIO:
            return self._velocity
        return se3_exp(ratio * se3_log(self._velocity))

    def _track_from_rotation(
        self, gray: NDArray[np.uint8], prior: F64, feats: Features, sem: NDArray[np.uint8] | None,
        kp_depth: NDArray[np.float64], failed: tuple[NDArray[np.intp], NDArray[np.intp]],
    ) -> tuple[F64 | None, NDArray[np.bool_], NDArray[np.intp], NDArray[np.intp]]:
        """The local map matched from a second prior: the last RGB-tracked frame's pose turned by
        the rotation between its thumbnail and that of this frame's ``gray`` (H, W)
        (:func:`~wardmap.edge.sbi.rotation_between`, from the prior's rotation), the prior's
        translation kept. ``(T_cw, inliers, m_idx, f_idx)``;
        ``T_cw`` None (and ``failed``'s matches) when that finds no pose either."""
        assert self._sbi is not None and self._sbi_ref is not None
        ref_gray, T_world_ref = self._sbi_ref
        T_ref_cur = inverse(T_world_ref) @ prior
        R_cur_ref = rotation_between(self._sbi, self._sbi.make(ref_gray), self._sbi.make(gray),
                                     T_ref_cur[:3, :3].T)
        no = (None, np.zeros(0, bool), *failed)
        if R_cur_ref is None:
            return no
        T_ref_cur[:3, :3] = R_cur_ref.T
        T_cw_prior = inverse(T_world_ref @ T_ref_cur)
        m_idx, f_idx = self._match_map(T_cw_prior, feats, sem, self.cfg.match_radius_px)
        if len(m_idx) < self.cfg.min_inliers:
            return no
        T_cw, inl = self._pose_from_matches(m_idx, f_idx, feats, kp_depth, T_cw_prior)
        return no if T_cw is None else (T_cw, inl, m_idx, f_idx)

    # ------------------------------------------------------------------ matching / pose
    def _match_map(
        self, T_cw: F64, feats: Features, sem: NDArray[np.uint8] | None, radius: float, *,
        among: NDArray[np.bool_] | None = None, max_hamming: int | None = None,
    ) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """Map points (rows; only those in ``among`` (M,) when given) that project within
        ``radius`` px of a feature with a close descriptor (``max_hamming``, default the
        config's) and, with ``sem``, a close semantic descriptor: ``(map rows, feature rows)``."""
        if len(self.map) == 0:
            return np.zeros(0, np.intp), np.zeros(0, np.intp)
        pts_c = transform_points(T_cw, self.map.pos_world)
        uv, ok = self.cam.project(pts_c)
        ok &= self.cam.in_image(uv, margin=2.0) & (pts_c[:, 2] > 0.1)
        if among is not None:
            ok &= among
        vis = np.flatnonzero(ok)
        if len(vis) == 0:
            return np.zeros(0, np.intp), np.zeros(0, np.intp)
        mi, fi = match_projected(self.map.desc[vis], uv[vis], feats, radius,
                                 max_hamming=self.cfg.max_hamming if max_hamming is None else max_hamming)
        m_idx, f_idx = vis[mi], np.asarray(fi, np.intp)
        if sem is not None and self.map.sem is not None and len(m_idx):
            d = semantic_distance(self.map.sem[m_idx], sem[f_idx])
            good = d <= self.cfg.semantic.max_semantic_distance
            m_idx, f_idx = m_idx[good], f_idx[good]
        return m_idx, f_idx

    def _refine(
        self, P: F64, uv: F64, T_cw: F64, sigma: F64, z: NDArray[np.float64]
    ) -> tuple[F64, NDArray[np.bool_]]:
        """Huber motion-only refinement with the RGB-D term for keypoint depths ``z`` (N,), metres."""
        T, inl, _ = refine_pose_huber(
            P, uv, self.cam, T_cw, sigma_px=sigma, depth_m=z, bf=self.cfg.rgbd_bf,
            max_stereo_depth_m=self.cfg.rgbd_max_depth_m,
        )
        return T, inl

    def _rolling_shutter_refit(
        self, T_cw: F64, m_idx: NDArray[np.intp], f_idx: NDArray[np.intp], inl: NDArray[np.bool_],
        feats_raw: Features, depth_raw: NDArray[np.float64],
    ) -> tuple[F64, NDArray[np.bool_], Features, NDArray[np.float64]] | None:
        """The pose and this frame's own rolling-shutter spin, fitted together on the inliers.

        The spin comes from the image's shear (:func:`refine_pose_rolling_shutter`), with the
        motion model's spin times the readout as a weak prior; the previous step's spin alone
        lags the motion (a hand-held camera reverses within a few frames). The keypoints as
        measured (``feats_raw`` / ``depth_raw``) are unrolled with the fitted spin and the
        pose refined once more on all matches, which re-classifies the inliers.
        Returns (T_cw, inliers, unrolled features, their depth), or None when the fit fails
        or keeps too few inliers.
        """
        m_in, f_in = m_idx[inl], f_idx[inl]
        sigma = np.power(self.cfg.orb.scale_factor, feats_raw.octave.astype(np.float64))
        omega_prev = so3_log(self._velocity[:3, :3]) / self._prev_dt if self._prev_dt > 0 else np.zeros(3)
        fit = refine_pose_rolling_shutter(
            self.map.pos_world[m_in], feats_raw.uv[f_in].astype(np.float64), self.cam, T_cw,
            self.readout.readout_s * omega_prev, sigma_px=sigma[f_in],
            shear_sigma_rad=self.cfg.rs_shear_sigma_rad,
            depth_m=depth_raw[f_in], bf=self.cfg.rgbd_bf, max_stereo_depth_m=self.cfg.rgbd_max_depth_m,
        )
        if not fit.ok:
            return None
        feats_u, z_u = unroll_keypoints(self.cam, 1.0, fit.shear_rad, feats_raw, depth_raw)
        T2, inl2 = self._refine(
            self.map.pos_world[m_idx], feats_u.uv[f_idx].astype(np.float64), fit.T_cam_world,
            sigma[f_idx], z_u[f_idx],
        )
        if int(inl2.sum()) < self.cfg.min_inliers:
            return None
        return T2, inl2, feats_u, z_u

    def _pose_from_matches(
        self,
        m_idx: NDArray[np.intp],
        f_idx: NDArray[np.intp],
        feats: Features,
        kp_depth: NDArray[np.float64],
        T_cw_prior: F64,
    ) -> tuple[F64 | None, NDArray[np.bool_]]:
        if len(m_idx) < self.cfg.min_inliers:
            return None, np.zeros(len(m_idx), bool)
        P = self.map.pos_world[m_idx]
        uv = feats.uv[f_idx].astype(np.float64)
        sigma = np.power(self.cfg.orb.scale_factor, feats.octave[f_idx].astype(np.float64))
        z = kp_depth[f_idx]
        if self.cfg.direct_from_prior:
            # ORB-SLAM2 tracks from its motion model without RANSAC: the Huber refinement
            # started at the prior. RANSAC (EPnP) only when that keeps too few inliers.
            T_cw, inl = self._refine(P, uv, T_cw_prior, sigma, z)
            if int(inl.sum()) >= max(self.cfg.min_inliers, 0.5 * len(m_idx)):
                return T_cw, inl
        pnp = solve_pnp_ransac(P, uv, self.cam, T_cam_world_guess=T_cw_prior)
        if not pnp.ok or int(pnp.inliers.sum()) < self.cfg.min_inliers:
            return None, np.zeros(len(m_idx), bool)
        T_cw, inl = self._refine(P, uv, pnp.T_cam_world, sigma, z)
        if int(inl.sum()) < self.cfg.min_inliers:
            return None, inl
        return T_cw, inl

    def _relocalise(
        self, feats: Features, kp_depth: NDArray[np.float64]
    ) -> tuple[F64 | None, NDArray[np.bool_], NDArray[np.intp], NDArray[np.intp]]:
        """Match against the last frame and recent keyframes by descriptor alone, EPnP in RANSAC on
        each; the candidate with the most refined inliers (stopping early at three times
        ``min_inliers``) is re-matched against the local map and its pose refined: ``(T_cam_world,
        inliers, map indexes, feature indexes)``, else None."""
        # The last tracked frame first (ORB-SLAM2's reference-frame tracking), then keyframes
        # newest first (the last one is skipped when it is that frame).
        candidates = [self._frame_snapshot(*self._last_frame_raw)] if self._last_frame_raw is not None else []
        last_stamp = self._last_frame_raw[0] if self._last_frame_raw is not None else None
        candidates += [kf for kf in reversed(self.keyframes[-self.cfg.reloc_keyframes :])
                       if kf.stamp != last_stamp]
        best: F64 | None = None
        best_n = 0
        for kf in candidates:
            if best_n >= 3 * self.cfg.min_inliers:
                break
            if len(kf.desc) < self.cfg.min_inliers:
                continue
            ki, fi, _ = match_descriptors(kf.desc, feats.descriptors, ratio=0.8)
            if len(ki) < self.cfg.min_inliers:
                continue
            pnp = solve_pnp_ransac(kf.points_world[ki], feats.uv[fi].astype(np.float64), self.cam)
            n = int(pnp.inliers.sum()) if pnp.ok else 0
            if n >= self.cfg.min_inliers and n > best_n:
                T_cw, inl, _ = refine_pose_huber(
                    kf.points_world[ki], feats.uv[fi].astype(np.float64), self.cam, pnp.T_cam_world
                )
                best_n, best = int(inl.sum()), T_cw
        if best is not None:
            # Re-match the local map from the relocalised pose so map points are fused as usual.
            m_idx, f_idx = self._match_map(best, feats, None, self.cfg.match_radius_px)
            T_new, inl = self._pose_from_matches(m_idx, f_idx, feats, kp_depth, best)
            if T_new is not None:
                return T_new, inl, m_idx, f_idx
        return None, np.zeros(0, bool), np.zeros(0, np.intp), np.zeros(0, np.intp)

    # ------------------------------------------------------------------ thermal fallback
    def _thermal_pose(
        self, inp: TrackInput, depth: NDArray[np.float32] | None, prior: F64, timings: dict[str, float]
    ) -> F64 | None:
        """Paper 003 Sec. IV-C: SIFT on thermal, 3D from depth through the calibration, EPnP."""
        th = self.calib.thermal
        T_rgb_th = self.calib.T_rgb_thermal
        if not self.cfg.thermal or th is None or T_rgb_th is None or inp.thermal_k is None:
            return None
        t0 = time.perf_counter()
        if self._thermal_pending is not None:
            ref_k, ref_depth, ref_T = self._thermal_pending
            self._thermal_pending = None
            ref_feats, self._sift_contrast = extract_sift_adaptive(
                thermal_to_gray8(ref_k), self.cfg.sift, start_contrast=self._sift_contrast
            )
            self._set_thermal_ref(ref_feats, ref_depth, ref_T)
        if self._thermal_ref is None:
            return None
        gray = thermal_to_gray8(inp.thermal_k)
        feats, self._sift_contrast = extract_sift_adaptive(
            gray, self.cfg.sift, start_contrast=self._sift_contrast
        )
        ref_feats, ref_world = self._thermal_ref
        ri, fi, _ = match_descriptors(ref_feats.descriptors, feats.descriptors, ratio=0.8)
        timings["thermal"] = _ms(t0)
        if len(ri) < self.cfg.min_inliers:
            return None
        T_th_world_prior = inverse(T_rgb_th) @ inverse(prior)
        pnp = solve_pnp_ransac(
            ref_world[ri],
            feats.uv[fi].astype(np.float64),
            th,
            T_cam_world_guess=T_th_world_prior,
            reprojection_px=2.5,
        )
        if not pnp.ok or int(pnp.inliers.sum()) < self.cfg.min_inliers:
            return None
        T_th_w, inl, _ = refine_pose_huber(
            ref_world[ri], feats.uv[fi].astype(np.float64), th, pnp.T_cam_world
        )
        if int(inl.sum()) < self.cfg.min_inliers:
            return None
        self._thermal_last = (feats, int(inl.sum()), len(ref_world))
        return inverse(T_rgb_th @ T_th_w)

    def _depth_pose(self, depth: NDArray[np.float32], prior: F64, timings: dict[str, float]) -> F64 | None:
        """``T_world_camera`` by depth ICP against the previous frame when its pose was measured, or
        None (logged). After a lost frame it is not tried: the reference is older and the prior a
        guess, so ICP (about 100 ms of CPU at 640x480) seldom converges, and a lost tracker that
        pays it on every frame falls further behind a live camera."""
        cfg = self.cfg.icp
        if not cfg.enabled or self._depth_ref is None or self._depth_ref_index != self._frame_index - 1:
            return None
        t0 = time.perf_counter()
        if self._rays is None:
            self._rays = self.cam.pixel_rays()
        T_ref, ref_depth = self._depth_ref
        if self._depth_ref_pyr is None:
            self._depth_ref_pyr = DepthPyramid(ref_depth, self.cam, cfg, self._rays)
        cur = DepthPyramid(depth, self.cam, cfg, self._rays)
        res = icp(self._depth_ref_pyr, cur, self.cam, inverse(T_ref) @ prior, cfg)
        timings["depth"] = _ms(t0)
        if not res.ok:
            log.debug("depth fallback refused: %s", res.reason)
            return None
        T = T_ref @ res.T_ref_cur
        self._set_depth_ref(T, depth, cur)
        return T

    def _set_depth_ref(self, T: F64, depth: NDArray[np.float32], pyramid: DepthPyramid | None = None) -> None:
        self._depth_ref = (T, depth)
        self._depth_ref_index = self._frame_index
        self._depth_ref_pyr = pyramid

    def _maybe_thermal_ref(
        self, inp: TrackInput, depth: NDArray[np.float32], T: F64, timings: dict[str, float]
    ) -> None:
        if not self.cfg.thermal or inp.thermal_k is None or self.calib.thermal is None:
            return
        self._thermal_pending = (inp.thermal_k, depth, T.copy())

    def _set_thermal_ref(self, feats: Features, depth: NDArray[np.float32], T_world_cam: F64) -> None:
        th, T_rgb_th = self.calib.thermal, self.calib.T_rgb_thermal
        if th is None or T_rgb_th is None:
            return
        depth_th = depth_in_other_camera(depth, self.cam, th, inverse(T_rgb_th))
        z = _depth_at(depth_th, feats.uv)
        ok = (z > self.cfg.min_depth_m) & (z < 1.4 * self.cfg.max_depth_m)
        if ok.sum() < self.cfg.min_inliers:
            return
        pts_th = th.unproject(feats.uv[ok].astype(np.float64), z[ok])
        pts_world = transform_points(T_world_cam @ T_rgb_th, pts_th)
        self._thermal_ref = (feats.select(ok), pts_world)
        self._thermal_ref_T = T_world_cam.copy()

    # ------------------------------------------------------------------ map upkeep
    def _fuse(
        self, T_cw: F64, idx: NDArray[np.intp], uv: NDArray[np.float32], z: NDArray[np.float64]
    ) -> None:
        ok = (z > self.cfg.min_depth_m) & (z < self.cfg.max_depth_m)
        self.map.n_seen[idx] += 1
        if not ok.any():
            return
        pts = transform_points(inverse(T_cw), self.cam.unproject(uv[ok].astype(np.float64), z[ok]))
        self.map.fuse(idx[ok], pts, 1.0 / np.maximum(z[ok], 0.5) ** 4, self.cfg.max_fuse_weight)

    def _need_keyframe(self, stamp: float, T: F64, n_inliers: int) -> bool:
        if self._kf_T is None:
            return True
        rel = inverse(self._kf_T) @ T
        return bool(
            stamp - self._kf_stamp >= self.cfg.kf_max_interval_s
            or np.linalg.norm(rel[:3, 3]) >= self.cfg.kf_translation_m
            or np.degrees(rotation_angle(rel[:3, :3])) >= self.cfg.kf_rotation_deg
            or n_inliers < self.cfg.kf_tracked_ratio * self._kf_inliers
        )

    def _insert_keyframe(
        self,
        stamp: float,
        T: F64,
        feats: Features,
        kp_depth: NDArray[np.float64],
        sem: NDArray[np.uint8] | None,
        *,
        skip: NDArray[np.bool_] | None = None,
        new_all: bool = False,
        observed: tuple[NDArray[np.intp], NDArray[np.intp]] | None = None,
    ) -> NDArray[np.int64]:
        """Make keyframe ``_kf_count`` at pose ``T`` (4, 4): map points for keypoints with
        depth (not ``skip``), and with local BA its observations: ``observed`` = (map rows,
        keypoint rows) of its matched inliers, plus the points it made.

        Returns int64 (N,) per keypoint of ``feats``: the id of the map point it observed
        (``observed``) or made, -1 for none."""
        kf_index = self._kf_count
        self._kf_count += 1
        ok = (kp_depth > self.cfg.min_depth_m) & (kp_depth < self.cfg.max_depth_m)
        pts_world = transform_points(T, self.cam.unproject(feats.uv[ok].astype(np.float64), kp_depth[ok]))
        desc = np.asarray(feats.descriptors, np.uint8)  # ORB: (N, 32) uint8
        self.keyframes.append(
            Keyframe(kf_index, self._frame_index, stamp, T.copy(), desc[ok], pts_world, feats.uv[ok])
        )
        self.keyframes = self.keyframes[-max(self.cfg.reloc_keyframes, 2) :]
        new = ok & ~skip if skip is not None and not new_all else ok
        if skip is not None and not new_all and self.cfg.fuse_radius_px > 0:
            observed = self._fuse_unmatched_points(T, feats, kp_depth, sem, ok, new, observed, kf_index)
        z = kp_depth[new]
        pts_new = transform_points(T, self.cam.unproject(feats.uv[new].astype(np.float64), z))
        ids = np.full(len(feats.uv), -1, np.int64)
        if observed is not None:
            ids[observed[1]] = self.map.pid[observed[0]]
        first_new = self.map.next_pid
        self.map.add(
            pts_new,
            desc[new],
            None if sem is None else sem[new],
            1.0 / np.maximum(z, 0.5) ** 4,
            kf_index,
        )
        ids[new] = np.arange(first_new, first_new + int(new.sum()), dtype=np.int64)
        if self._ba is not None:
            self._record_keyframe(kf_index, T, feats, kp_depth, int(new.sum()), observed)
        # Forget points not seen for a while and cap the map size.
        keep = self.map.kf_last >= kf_index - self.cfg.local_keyframes
        cull = self.cfg.local_ba.cull_after_keyframes
        if self._ba is not None and cull > 0:
            # ORB-SLAM2's MapPointCulling: a point no other keyframe confirmed is dropped.
            keep &= ~((self.map.kf_first <= kf_index - cull) & (self.map.n_kf < 2))
        if keep.sum() > self.cfg.max_map_points:
            order = np.argsort(-self.map.kf_last, kind="stable")
            keep = np.zeros(len(self.map), bool)
            keep[order[: self.cfg.max_map_points]] = True
        self.map.keep(keep)
        self._kf_T = T.copy()
        self._kf_stamp = stamp
        if self._ba is not None:
            self._ba_problem = self._ba_graph.problem(kf_index, self._map_epoch, self.map.pid,
                                                      self.map.pos_world)
        return ids

    def _fuse_unmatched_points(
        self, T: F64, feats: Features, kp_depth: NDArray[np.float64], sem: NDArray[np.uint8] | None,
        ok: NDArray[np.bool_], new: NDArray[np.bool_],
        observed: tuple[NDArray[np.intp], NDArray[np.intp]] | None, kf_index: int,
    ) -> tuple[NDArray[np.intp], NDArray[np.intp]] | None:
        """ORB-SLAM2's Fuse at keyframe ``kf_index`` (pose ``T``), half of it: a map point this
        frame did not match that projects onto one of its keypoints with depth (within
        ``fuse_radius_px``, Hamming distance <= ``fuse_max_hamming``, with labels a close semantic
        descriptor, stereo chi-square
        ``|(du, dv, du_right)|^2 / sigma^2 < 7.815`` at ``sigma = 1.2^octave``) is the point that
        keypoint sees. On a keypoint about to make a new point (``new``, cleared there) the old
        point takes the observation (position averaged in, last seen now) instead of a twin being
        made; a keypoint matched as an inlier keeps its point (dropping the unmatched twin there,
        the other half, made tracking worse: docs/decisions/0049). Returns ``observed`` (map
        rows, keypoint rows) with the taken observations added."""
        m_obs = np.zeros(0, np.intp) if observed is None else observed[0]
        f_obs = np.zeros(0, np.intp) if observed is None else observed[1]
        cand = np.flatnonzero(ok)
        free = np.ones(len(self.map), bool)
        free[m_obs] = False
        T_cw = inverse(T)
        mi, fi = self._match_map(T_cw, feats.select(cand), None if sem is None else sem[cand],
                                 self.cfg.fuse_radius_px, among=free, max_hamming=self.cfg.fuse_max_hamming)
        rows, kps = mi, cand[fi]
        if len(rows) == 0:
            return observed
        pts_c = transform_points(T_cw, self.map.pos_world[rows])
        uv, _ = self.cam.project(pts_c)
        bf = self.cfg.rgbd_bf
        z_pred, z_kp = pts_c[:, 2], kp_depth[kps]
        e = uv - feats.uv[kps].astype(np.float64)
        e_r = e[:, 0] - bf / z_pred + bf / z_kp
        sigma = np.power(self.cfg.orb.scale_factor, feats.octave[kps].astype(np.float64))
        good = (np.sum(e**2, axis=1) + e_r**2) / sigma**2 < 7.815
        rows, kps = rows[good], kps[good]
        takes = new[kps]  # a keypoint already matched as an inlier keeps its point
        t_rows, t_kps = rows[takes], kps[takes]
        new[t_kps] = False
        self.map.kf_last[t_rows] = kf_index
        self._fuse(T_cw, t_rows, feats.uv[t_kps], kp_depth[t_kps])
        self.fused_points += len(t_rows)
        m_all = np.concatenate([m_obs, t_rows]).astype(np.intp)
        f_all = np.concatenate([f_obs, t_kps]).astype(np.intp)
        return m_all, f_all

    # ------------------------------------------------------------------ local bundle adjustment
    def _record_keyframe(
        self, kf_index: int, T: F64, feats: Features, kp_depth: NDArray[np.float64], n_new: int,
        observed: tuple[NDArray[np.intp], NDArray[np.intp]] | None,
    ) -> None:
        """Keyframe ``kf_index``'s observations into the covisibility graph: its matched
        map points (``observed``) and the ``n_new`` points it just added (the map's last rows)."""
        m_idx, f_idx = observed if observed is not None else (np.zeros(0, np.intp), np.zeros(0, np.intp))
        self.map.n_kf[m_idx] += 1
        new_rows = np.arange(len(self.map) - n_new, len(self.map))
        ok = (kp_depth > self.cfg.min_depth_m) & (kp_depth < self.cfg.max_depth_m)
        made = np.flatnonzero(ok)
        if observed is None:
            f_new = made
        else:
            skip = np.zeros(len(feats.uv), bool)
            skip[f_idx] = True
            f_new = made[~skip[made]]
        rows = np.concatenate([m_idx, new_rows]).astype(np.intp)
        f_all = np.concatenate([f_idx, f_new]).astype(np.intp)
        sigma = np.power(self.cfg.orb.scale_factor, feats.octave[f_all].astype(np.float64))
        self._ba_graph.add(kf_index, T, self.map.pid[rows], feats.uv[f_all], kp_depth[f_all], sigma)

    def _apply_local_ba(self) -> None:
        """Take finished bundle adjustments (at a frame boundary, on the tracking thread).

        Adjusted points replace their map positions and the keyframe poses in the graph. The
        keyframe that triggered the problem moved by ``D = T_new T_old^-1`` (world frame);
        what was estimated from it afterwards moves with it: the current pose, later
        keyframes, points made since, the depth reference.
        """
        assert self._ba is not None
        for sol in self._ba.poll():
            pr = sol.problem
            if not sol.accepted or pr.epoch != self._map_epoch:
                continue
            self._ba_graph.apply(sol)
            rows = np.searchsorted(self.map.pid, pr.pid)
            found = rows < len(self.map)
            found[found] = self.map.pid[rows[found]] == pr.pid[found]
            self.map.pos_world[rows[found]] = sol.points_world[found]
            r = int(np.flatnonzero(pr.kf_index == pr.trigger)[0])
            delta = sol.T_world_cam[r] @ inverse(pr.T_world_cam[r])
            later = np.ones(len(self.map), bool)
            later[rows[found]] = False
            later &= self.map.kf_first >= pr.trigger
            self.map.pos_world[later] = transform_points(delta, self.map.pos_world[later])
            self._ba_graph.move_after(pr.trigger, delta)
            if self._T_world_cam is not None:
                self._T_world_cam = delta @ self._T_world_cam
            if self._kf_T is not None:
                self._kf_T = delta @ self._kf_T
            if self._last_frame_raw is not None:
                st, T_l, f_l, z_l = self._last_frame_raw
                self._last_frame_raw = (st, delta @ T_l, f_l, z_l)
            if self._depth_ref is not None:
                self._depth_ref = (delta @ self._depth_ref[0], self._depth_ref[1])

    def _frame_snapshot(
        self, stamp: float, T: F64, feats: Features, kp_depth: NDArray[np.float64]
    ) -> Keyframe:
        ok = (kp_depth > self.cfg.min_depth_m) & (kp_depth < self.cfg.max_depth_m)
        pts = transform_points(T, self.cam.unproject(feats.uv[ok].astype(np.float64), kp_depth[ok]))
        desc = np.asarray(feats.descriptors, np.uint8)[ok]
        return Keyframe(-1, self._frame_index, stamp, T.copy(), desc, pts, feats.uv[ok])

    def _restart_map(
        self,
        stamp: float,
        T: F64,
        feats: Features,
        kp_depth: NDArray[np.float64],
        sem: NDArray[np.uint8] | None,
    ) -> None:
        ok = (kp_depth > self.cfg.min_depth_m) & (kp_depth < self.cfg.max_depth_m)
        if ok.sum() < 2 * self.cfg.min_inliers:
            return
        self.map = MapPoints(next_pid=self.map.next_pid)  # ids stay unique for the wire
        self._map_epoch += 1
        self._ba_graph.reset()
        self._insert_keyframe(stamp, T, feats, kp_depth, sem, new_all=True)
        self._kf_inliers = int(ok.sum())

    # ------------------------------------------------------------------ bookkeeping
    def _accept(self, inp: TrackInput, T: F64, *, n_inliers: int, keyframe: bool = True) -> None:
        if self._T_world_cam is not None:
            self._velocity = inverse(self._T_world_cam) @ T
            self._prev_dt = inp.stamp - (self._prev_stamp if self._prev_stamp is not None else inp.stamp)
        self._T_world_cam = T
        self._prev_stamp = inp.stamp
        if inp.T_odom_base is not None:
            self._prev_odom = inp.T_odom_base
        if keyframe:
            self._kf_inliers = n_inliers

    def _fallback(
        self,
        inp: TrackInput,
        prior: F64,
        prior_source: PoseSource,
        reason: str,
        timings: dict[str, float],
        t_start: float,
        *,
        n_feat: int,
        n_dyn: int = 0,
        depth: NDArray[np.float32] | None = None,
        n_matches: int = 0,
    ) -> TrackResult:
        """No RGB pose: try thermal, then odometry; else keep the prediction and report lost."""
        T_th = self._thermal_pose(inp, depth, prior, timings) if depth is not None else None
        if T_th is not None and prior_source == "odometry" and self.cfg.thermal_odometry_blend < 1.0:
            # Complementary filter: thermal poses are jittery (low resolution), odometry
            # increments are smooth but drift; move the odometry prediction part-way.
            T_th = interpolate_transform(prior, T_th, self.cfg.thermal_odometry_blend)
        if T_th is not None and depth is not None and self._thermal_last is not None:
            # Refresh the thermal reference (a thermal keyframe) with the fused pose, and only
            # when it wears out: chaining thermal poses frame to frame accumulates drift.
            feats_th, n_inl, n_ref = self._thermal_last
            worn = n_inl < max(2 * self.cfg.min_inliers, 0.3 * n_ref)
            if worn or np.linalg.norm(T_th[:3, 3] - self._thermal_ref_T[:3, 3]) > 0.5:
                self._set_thermal_ref(feats_th, depth, T_th)
        T_depth = None
        if T_th is None and prior_source == "motion_model" and depth is not None:
            T_depth = self._depth_pose(depth, prior, timings)
        source: PoseSource
        if T_th is not None:
            T, source, lost = T_th, "thermal", False
        elif prior_source == "odometry":
            T, source, lost = prior, "odometry", False
        elif T_depth is not None:
            T, source, lost = T_depth, "depth", False
        else:
            T, source, lost = prior, "none" if prior_source == "none" else "motion_model", True
        self._accept(inp, T, n_inliers=self._kf_inliers, keyframe=False)
        return self._result(
            inp, T, source, lost, reason, None, n_dyn, n_matches, 0, False, timings, t_start, n_feat=n_feat
        )

    def _result(
        self,
        inp: TrackInput,
        T: F64,
        source: PoseSource,
        lost: bool,
        reason: str,
        feats: Features | None,
        n_dyn: int,
        n_matches: int,
        n_inliers: int,
        keyframe: bool,
        timings: dict[str, float],
        t_start: float,
        *,
        n_feat: int | None = None,
        point_ids: NDArray[np.int64] | None = None,
    ) -> TrackResult:
        timings["total"] = _ms(t_start)
        # CPU time of this thread: the frame's compute, without time other processes took.
        timings["cpu_total"] = (time.thread_time() - self._cpu_start) * 1e3
        n = n_feat if n_feat is not None else (0 if feats is None else len(feats.uv))
        wire = keyframe and feats is not None and feats.kind == "orb"
        return TrackResult(
            inp.stamp, T.copy(), source, lost, reason, n, n_dyn, n_matches, n_inliers, keyframe, timings,
            features=feats if wire else None, point_ids=point_ids if wire else None,
        )


# ---------------------------------------------------------------------- helpers
def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


def _frame_problem(inp: TrackInput, cam: PinholeCamera) -> str:
    """Why a frame cannot be tracked visually at all ('' when it can)."""
    if inp.problem:
        return inp.problem
    if inp.rgb is None or inp.rgb.size == 0:
        return "empty colour image"
    if inp.rgb.shape[:2] != (cam.height, cam.width) or inp.rgb.ndim != 3:
        return f"colour image has shape {inp.rgb.shape}, expected ({cam.height}, {cam.width}, 3)"
    if inp.depth_m is None or inp.depth_m.size == 0:
        return "empty depth image"
    if inp.depth_m.shape != (cam.height, cam.width):
        return f"depth image has shape {inp.depth_m.shape}, expected ({cam.height}, {cam.width})"
    finite = np.isfinite(inp.depth_m)
    if not np.any(finite & (inp.depth_m > 0)):
        return "depth image has no valid pixel"
    return ""


def _near(T_a: F64, T_b: F64, max_m: float, max_deg: float) -> bool:
    """Whether two poses are within ``max_m`` metres and ``max_deg`` degrees of each other."""
    rel = inverse(T_a) @ T_b
    return bool(np.linalg.norm(rel[:3, 3]) <= max_m and np.degrees(rotation_angle(rel[:3, :3])) <= max_deg)


def warm_up(
    calibration: Calibration,
    config: TrackerConfig | None = None,
    mobility_lut: NDArray[np.uint8] | None = None,
) -> float:
    """Compile the tracker's numba kernels before a camera starts streaming; seconds spent.

    A throwaway tracker (local bundle adjustment off) tracks four synthetic frames of the
    colour camera's size: a textured wall 2 m ahead, still, then moving 3 px a frame
    sideways (initialisation, tracking with the rolling-shutter fit when the camera has a
    readout, a keyframe). Numba keeps what it compiles (``NUMBA_CACHE_DIR``), so after the
    first start this costs a fraction of a second; without it, the first run of a live
    camera would drop its frames for as long as the kernels take to compile (about 20 s on
    this project's 2-core x86 machine, more on an ARM board).
    """
    cfg = config or TrackerConfig()
    cfg = replace(cfg, local_ba=replace(cfg.local_ba, enabled=False))
    cam = calibration.rgb
    rng = np.random.default_rng(0)
    wall = np.full((cam.height, cam.width + 16, 3), 128, np.uint8)
    for _ in range(400):
        x, y = int(rng.integers(0, cam.width + 16)), int(rng.integers(0, cam.height))
        w, h = (int(v) for v in rng.integers(6, 40, size=2))
        cv2.rectangle(wall, (x, y), (x + w, y + h), tuple(int(c) for c in rng.integers(0, 256, 3)), -1)
    depth = np.full((cam.height, cam.width), 2.0, np.float32)
    t0 = time.perf_counter()
    with Tracker(calibration, cfg, mobility_lut) as tracker:
        for i, shift in enumerate((0, 0, 3, 6)):
            rgb = np.ascontiguousarray(wall[:, shift : shift + cam.width])
            tracker.track(TrackInput(float(i) / 30.0, rgb, depth))
    return time.perf_counter() - t0


def unroll_keypoints(
    cam: PinholeCamera, readout_s: float, omega_cam: F64, feats: Features, kp_depth: NDArray[np.float64]
) -> tuple[Features, NDArray[np.float64]]:
    """Keypoints of a rolling-shutter frame moved to where a global shutter at the middle
    row's instant would have seen them.

    Row v is exposed ``dt = (v - cy) / height * readout_s`` after the middle row; over
    ``dt`` the camera turned by ``omega_cam dt`` (rad/s, camera frame), so the point it saw
    at ``X`` is at ``X + dt omega x X`` in the middle row's frame (first order: 0.02 rad at
    100 deg/s and 20 ms). Translation during the readout is ignored (millimetres).

    Args:
        cam: the colour camera (distortion handled through ``unproject`` / ``project``).
        readout_s: first-row-to-last readout time, seconds.
        omega_cam: (3,) angular velocity in the camera frame, rad/s (the motion model's).
        feats: keypoints; only ``uv`` changes.
        kp_depth: (N,) depth at each keypoint, metres (0 = none: the ray is moved alone).

    Returns:
        (features with moved ``uv``, depth (N,) of the moved points, 0 where there was none).
    """
    uv = feats.uv.astype(np.float64)
    has = kp_depth > 0
    X = cam.unproject(uv, np.where(has, kp_depth, 1.0))
    dt = (uv[:, 1] - cam.cy) / cam.height * readout_s
    Xm = X + dt[:, None] * np.cross(omega_cam, X)
    uv_m, _ = cam.project(Xm)
    return replace(feats, uv=uv_m.astype(np.float32)), np.where(has, Xm[:, 2], 0.0)


_NEIGHBOURS_3X3 = np.array([(dv, du) for dv in (-1, 0, 1) for du in (-1, 0, 1)], np.intp)


def _nearest_pixel(
    shape: tuple[int, ...], uv: NDArray[np.float32]
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Row and column (N,) of the pixel nearest each keypoint ``uv`` (N, 2), clipped to ``shape``."""
    h, w = shape[:2]
    return (np.clip(np.rint(uv[:, 1]).astype(np.intp), 0, h - 1),
            np.clip(np.rint(uv[:, 0]).astype(np.intp), 0, w - 1))


def _depth_at(depth: NDArray[np.float32], uv: NDArray[np.float32]) -> NDArray[np.float64]:
    """Depth (N,) metres at the nearest pixel of each keypoint ``uv`` (N, 2); 0 = none."""
    v, u = _nearest_pixel(depth.shape, uv)
    return depth[v, u].astype(np.float64)


def _behind_depth_edge(
    depth: NDArray[np.float32], uv: NDArray[np.float32], ratio: float
) -> NDArray[np.bool_]:
    """Which keypoints ``uv`` (N, 2) read the far side of a depth edge (N,): the depth at the
    nearest pixel exceeds the nearest valid depth of its 3x3 neighbourhood by more than ``ratio``
    times itself (pixels without depth are ignored). All False for ``ratio`` <= 0
    (``TrackerConfig.depth_edge_ratio``)."""
    if ratio <= 0.0 or len(uv) == 0:
        return np.zeros(len(uv), bool)
    h, w = depth.shape
    v, u = _nearest_pixel((h, w), uv)
    win = depth[np.clip(v[:, None] + _NEIGHBOURS_3X3[:, 0], 0, h - 1),
                np.clip(u[:, None] + _NEIGHBOURS_3X3[:, 1], 0, w - 1)]
    nearest = np.where(win > 0.0, win, np.inf).min(axis=1)
    z = depth[v, u]
    with np.errstate(invalid="ignore"):
        return (z > 0.0) & (z - nearest > ratio * z)


def depth_in_other_camera(
    depth: NDArray[np.float32], cam: PinholeCamera, other: PinholeCamera, T_other_cam: F64
) -> NDArray[np.float32]:
    """Re-project a depth image (H, W) of ``cam`` into ``other``'s image: (h, w) metres, 0 = none.

    Every valid depth pixel is moved with ``T_other_cam`` and splatted (nearest wins) at
    its projection; small holes are closed with a 3x3 min-of-valid filter.
    """
    v, u = np.nonzero(depth > 0)
    if len(v) == 0:
        return np.zeros((other.height, other.width), np.float32)
    step = max(1, int(np.sqrt(len(v) / (other.width * other.height * 2.0))))
    v, u = v[::step], u[::step]
    pts = transform_points(
        T_other_cam, cam.unproject(np.column_stack([u, v]).astype(np.float64), depth[v, u])
    )
    uv, ok = other.project(pts)
    ok &= other.in_image(uv)
    ui = np.rint(uv[ok, 0]).astype(np.intp)
    vi = np.rint(uv[ok, 1]).astype(np.intp)
    z = pts[ok, 2].astype(np.float32)
    out = np.full((other.height, other.width), np.inf, np.float32)
    np.minimum.at(out, (vi, ui), z)
    filled = cv2.erode(out, np.ones((3, 3), np.uint8))
    out = np.where(np.isinf(out), filled, out)
    out[np.isinf(out)] = 0.0
    return out
