"""Keyframe pose graph on gtsam iSAM2 (issue 37 back-end).

Frames (docs/ARCHITECTURE.md "Conventions"): each robot session ``(robot_id, session_id)`` has
its own ``odom`` frame, in which its tracker reports ``T_odom_camera`` (4, 4) of every
keyframe. The graph estimates ``T_map_camera`` (4, 4) of every keyframe in the shared ``map``
frame, and from a session's latest keyframe its ``T_map_odom = T_map_camera @ inv(T_odom_camera)``.
Units: metres and radians.

Variables and factors (integer gtsam keys, assigned when a keyframe enters iSAM2):

- one ``Pose3`` per keyframe: ``T_map_camera``;
- ``odometry``: ``BetweenFactorPose3`` between consecutive keyframes of a session, measured
  ``T_a_b = inv(T_odom_a) @ T_odom_b``, Gaussian, sigmas from the later keyframe's
  ``pose_source`` (:class:`OdometrySigmas`);
- ``loop``: ``BetweenFactorPose3`` on a verified ``T_a_b`` (pose of keyframe b in keyframe a's
  camera frame) under a robust kernel (Cauchy or Huber), sigmas from the PnP inlier count;
- ``prior``: ``PriorFactorPose3`` on ``T_map_a``: the gauge of the first session (its first
  keyframe, tight) or a ``--map-pose`` prior (``prior_T_map_odom @ T_odom_a``, loose);
- ``bundle``: ``BetweenFactorPose3`` between consecutive keyframes of an anchored session on
  their relative pose after a bundle adjustment over their features (``bundle.py``), Gaussian
  and tight (``bundle_sigmas``): added once per pair, after a loop closure.

gtsam's ``Pose3`` tangent order is (rx, ry, rz, tx, ty, tz); a between factor's error is
``Log(T_a_b^-1 @ inv(T_map_a) @ T_map_b)``, expressed in keyframe b's camera frame, so sigmas
are rad about the camera axes and m along them.

Anchored and floating sessions: a session is *anchored* when its ``T_map_odom`` is known
(the first session ever, a session started with a ``--map-pose`` prior, or one tied to an
anchored session by a loop edge, directly or through other floating sessions); its keyframes
are iSAM2 variables. A *floating* session's keyframes and edges are held aside until a loop
edge or a prior anchors it; loop edges between two floating sessions wait for one of them to
be anchored, then the other follows through them.

Single owner, not thread-safe: the back-end stage calls every method from one thread.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal, TypeAlias

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.shared.errors import ConfigError, GeometryError, WardmapError
from wardmap.shared.se3 import inverse, rotation_angle
from wardmap.shared.wire import POSE_SOURCES, PoseSource

__all__ = [
    "EdgeRecord",
    "GraphConfig",
    "GraphError",
    "GraphUpdate",
    "NodeKey",
    "NodeRecord",
    "OdometrySigmas",
    "PoseGraph",
    "PoseSourceSigmas",
    "SessionKey",
]

_log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
NodeKey: TypeAlias = tuple[str, str, int]
"""A keyframe: ``(robot_id, session_id, seq)``."""
SessionKey: TypeAlias = tuple[str, str]
"""A robot session, i.e. one ``odom`` frame: ``(robot_id, session_id)``."""
EdgeKind: TypeAlias = Literal["odometry", "loop", "prior", "bundle"]
LoopResult: TypeAlias = Literal["loop", "anchored", "floating"]
Sigmas6: TypeAlias = tuple[float, float, float, float, float, float]


class GraphError(WardmapError):
    """A keyframe or edge does not fit the graph (duplicate or unknown key, seq out of order)."""


@dataclass(frozen=True)
class OdometrySigmas:
    """Standard deviations of one odometry step for one tracker pose source.

    For a step ``T_a_b`` of length ``d`` m and rotation angle ``theta`` rad, every rotation
    axis gets ``radians(rot_deg + rot_deg_per_m * d) + rot_per_rad * theta`` rad and every
    translation axis ``trans_m + trans_per_m * d`` m.
    """

    rot_deg: float
    """Rotation sigma of any step, degrees."""
    trans_m: float
    """Translation sigma of any step, metres."""
    rot_deg_per_m: float
    """Rotation sigma added per metre of step length, degrees per metre."""
    rot_per_rad: float
    """Rotation sigma added per radian of step rotation (a fraction, rad/rad)."""
    trans_per_m: float
    """Translation sigma added per metre of step length (a fraction, m/m)."""

    def __post_init__(self) -> None:
        for name in ("rot_deg", "trans_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("rot_deg_per_m", "rot_per_rad", "trans_per_m"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(self, name)}")

    def sigmas(self, T_a_b: F64) -> F64:
        """Sigmas (6,) (rx, ry, rz rad, tx, ty, tz m) of the odometry step ``T_a_b`` (4, 4)."""
        step_m = float(np.linalg.norm(T_a_b[:3, 3]))
        step_rad = rotation_angle(T_a_b[:3, :3])
        rot = math.radians(self.rot_deg + self.rot_deg_per_m * step_m) + self.rot_per_rad * step_rad
        trans = self.trans_m + self.trans_per_m * step_m
        return np.array([rot, rot, rot, trans, trans, trans])


_VISION = OdometrySigmas(rot_deg=0.1, trans_m=0.003, rot_deg_per_m=0.2, rot_per_rad=0.02, trans_per_m=0.01)
_VISION_WEAK = OdometrySigmas(
    rot_deg=0.2, trans_m=0.005, rot_deg_per_m=0.5, rot_per_rad=0.03, trans_per_m=0.02)
_WHEEL = OdometrySigmas(rot_deg=0.5, trans_m=0.01, rot_deg_per_m=1.0, rot_per_rad=0.05, trans_per_m=0.03)
_PREDICTED = OdometrySigmas(rot_deg=2.0, trans_m=0.05, rot_deg_per_m=5.0, rot_per_rad=0.2, trans_per_m=0.2)
_LOST = OdometrySigmas(rot_deg=5.0, trans_m=0.2, rot_deg_per_m=10.0, rot_per_rad=0.5, trans_per_m=0.5)


@dataclass(frozen=True)
class PoseSourceSigmas:
    """Odometry step sigmas per tracker ``pose_source`` (``wardmap.shared.wire.PoseSource``).

    Visual tracking (``init``, ``rgb``, ``relocalised``: pose from PnP on ORB features against
    the tracker's map) is tight; thermal and depth-only tracking a little looser; wheel
    odometry looser; a constant-velocity guess (``motion_model``) and a lost tracker
    (``none``) much looser, so that a loop edge can bend the graph there.
    """

    init: OdometrySigmas = _VISION
    rgb: OdometrySigmas = _VISION
    relocalised: OdometrySigmas = _VISION
    thermal: OdometrySigmas = _VISION_WEAK
    depth: OdometrySigmas = _VISION_WEAK
    odometry: OdometrySigmas = _WHEEL
    motion_model: OdometrySigmas = _PREDICTED
    none: OdometrySigmas = _LOST

    def for_source(self, pose_source: str) -> OdometrySigmas:
        """The sigmas of ``pose_source`` (one of ``wardmap.shared.wire.POSE_SOURCES``)."""
        if pose_source not in POSE_SOURCES:
            raise GraphError(f"unknown pose source {pose_source!r}; expected one of {POSE_SOURCES}")
        sigmas: OdometrySigmas = getattr(self, pose_source)
        return sigmas


@dataclass(frozen=True)
class GraphConfig:
    """Pose-graph parameters: odometry, loop and prior noise, robust kernel, iSAM2 settings."""

    odometry: PoseSourceSigmas = field(default_factory=PoseSourceSigmas)
    """Odometry step sigmas per tracker pose source."""
    loop_rot_deg: float = 5.0
    """Loop edge rotation sigma is ``max(loop_rot_floor_deg, loop_rot_deg / sqrt(inliers))``
    degrees (100 PnP inliers: 0.5 deg)."""
    loop_trans_m: float = 0.2
    """Loop edge translation sigma is ``max(loop_trans_floor_m, loop_trans_m / sqrt(inliers))``
    metres (100 PnP inliers: 2 cm)."""
    loop_rot_floor_deg: float = 0.2
    """Smallest loop edge rotation sigma, degrees."""
    loop_trans_floor_m: float = 0.01
    """Smallest loop edge translation sigma, metres."""
    loop_sigma_scale: float = 10.0
    """Factor on the verification's own pose sigmas (which model only pixel noise: the
    candidate's depth errors and biased keypoint depths at object edges come on top)."""
    robust_kernel: Literal["cauchy", "huber"] = "cauchy"
    """M-estimator on loop edges (gtsam ``noiseModel.Robust``)."""
    robust_param: float = 2.0
    """Kernel parameter k on the whitened loop error (units of sigma): a loop edge whose
    whitened error norm is e weighs ``1 / (1 + (e / k)^2)`` (Cauchy) or ``min(1, k / e)``
    (Huber). With k = 2 an edge within a few sigma keeps most of its weight; one 2 m off at
    2 cm sigma weighs 4e-4. Local: a correct edge far beyond the odometry sigmas (drift the
    odometry model does not allow) is down-weighted too."""
    prior_sigmas: Sigmas6 = (0.035, 0.035, 0.035, 0.1, 0.1, 0.1)
    """Sigmas (rx, ry, rz rad, tx, ty, tz m) of a ``--map-pose`` prior on ``T_map_camera``
    of the session's keyframe that carried it (2 deg, 10 cm)."""
    gauge_sigmas: Sigmas6 = (1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6)
    """Sigmas (rad, m) of the prior that fixes the map frame on the first session's first
    keyframe when it has no ``--map-pose`` prior."""
    relinearize_rot_rad: float = 3e-4
    """iSAM2: a keyframe is relinearized when a rotation component of its delta exceeds this
    (rad) ... Tighter than translations: an error in a rotation's linearization point turns
    everything beyond it by a lever arm (0.01 rad over 150 m of chain is 1.5 m)."""
    relinearize_trans_m: float = 0.01
    """... or a translation component exceeds this (m)."""
    relinearize_skip: int = 1
    """iSAM2: relinearization is checked every this many updates (the extra iterations after
    a loop or an anchoring always check)."""
    factorization: Literal["cholesky", "qr"] = "cholesky"
    """iSAM2 elimination. Cholesky is about three times faster on graphs with many loops, but
    on a long loop-free chain the lever arm of the heading uncertainty makes its pivots
    ill-conditioned (a straight chain of 0.5 m steps is declared indeterminate after about
    500 m); when it fails, the graph is rebuilt once with QR, which stays stable, and keeps QR
    (``PoseGraph.factorization``)."""
    loop_iterations: int = 3
    """At most this many extra ``ISAM2.update()`` calls after an update that added a loop edge
    or anchored a session, each relinearizing the keyframes that moved beyond the thresholds
    (and re-weighting their robust loop edges), until one relinearizes none. Not forced over
    the whole graph: at 5000 keyframes of many sessions a forced relinearization costs hundreds
    of milliseconds, and a loop that confirms the map moves nothing."""
    refresh_tail: int = 3
    """After a plain update (no loop, no anchoring), the estimates re-read are the new
    keyframes' and those of the last ``refresh_tail`` keyframes of each session that grew."""
    bundle_sigmas: Sigmas6 = (1e-4, 1e-4, 1e-4, 1e-3, 1e-3, 1e-3)
    """Sigmas (rx, ry, rz rad, tx, ty, tz m) of a ``bundle`` edge: the relative pose of two
    consecutive keyframes after a bundle adjustment, which then outweighs their odometry edge."""
    report_trans_m: float = 0.001
    """``GraphUpdate.sessions`` reports a session whose ``T_map_odom`` moved more than this
    (metres) ..."""
    report_rot_deg: float = 0.05
    """... or turned more than this (degrees) since it was last reported."""

    def __post_init__(self) -> None:
        for name in ("loop_rot_deg", "loop_trans_m", "loop_rot_floor_deg", "loop_trans_floor_m",
                     "loop_sigma_scale",
                     "robust_param", "relinearize_rot_rad", "relinearize_trans_m", "report_trans_m",
                     "report_rot_deg"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a finite number > 0, got {value!r}")
        for name in ("prior_sigmas", "gauge_sigmas", "bundle_sigmas"):
            value = getattr(self, name)
            if len(value) != 6 or not all(math.isfinite(v) and v > 0 for v in value):
                raise ConfigError(f"{name} must be 6 finite numbers > 0 (rad x3, m x3), got {value!r}")
        if self.robust_kernel not in ("cauchy", "huber"):
            raise ConfigError(f"robust_kernel must be 'cauchy' or 'huber', got {self.robust_kernel!r}")
        if self.factorization not in ("cholesky", "qr"):
            raise ConfigError(f"factorization must be 'cholesky' or 'qr', got {self.factorization!r}")
        if self.relinearize_skip < 1:
            raise ConfigError(f"relinearize_skip must be >= 1, got {self.relinearize_skip}")
        for name in ("loop_iterations", "refresh_tail"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(self, name)}")

    def loop_sigmas_from(self, sigmas: F64) -> F64:
        """Sigmas (6,) of a loop edge from its verification's estimate (6,) (rad x3, m x3):
        scaled by ``loop_sigma_scale`` (depth noise of the 3D points and unmodelled errors),
        and no smaller than the floors; non-finite ones fall back to the floor-free
        ``loop_rot_deg`` / ``loop_trans_m``."""
        s = np.asarray(sigmas, np.float64).reshape(6) * self.loop_sigma_scale
        rot = np.where(np.isfinite(s[:3]), s[:3], math.radians(self.loop_rot_deg))
        trans = np.where(np.isfinite(s[3:]), s[3:], self.loop_trans_m)
        return np.concatenate([np.maximum(rot, math.radians(self.loop_rot_floor_deg)),
                               np.maximum(trans, self.loop_trans_floor_m)])

    def loop_sigmas(self, inliers: int) -> F64:
        """Sigmas (6,) (rad, m) of a loop edge verified with ``inliers`` (>= 1) PnP inliers."""
        root = math.sqrt(inliers)
        rot = math.radians(max(self.loop_rot_floor_deg, self.loop_rot_deg / root))
        trans = max(self.loop_trans_floor_m, self.loop_trans_m / root)
        return np.array([rot, rot, rot, trans, trans, trans])


_I3 = np.eye(3)
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def _pose(value: ArrayLike, name: str) -> F64:
    """A read-only float64 copy of a rigid transform (4, 4); the checks of
    ``wardmap.shared.se3.check_transform`` at a fifth of its cost (records come by thousands)."""
    M = np.array(value, dtype=np.float64)
    if M.shape != (4, 4):
        raise GeometryError(f"{name}: expected shape (4, 4), got {M.shape}")
    R = M[:3, :3]
    # NaN fails every comparison, so non-finite values are refused too.
    if not (np.abs(R @ R.T - _I3).max() <= 1e-6 and np.array_equal(M[3], _LAST_ROW)
            and np.linalg.det(R) > 0 and np.isfinite(M[:3, 3]).all()):
        raise GeometryError(f"{name}: not a rigid transform (rotation block, last row or finiteness)")
    M.setflags(write=False)
    return M


def _check_node_key(key: object, name: str = "key") -> NodeKey:
    if not (isinstance(key, tuple) and len(key) == 3 and isinstance(key[0], str)
            and isinstance(key[1], str) and isinstance(key[2], int) and not isinstance(key[2], bool)):
        raise GraphError(f"{name}: expected (robot_id: str, session_id: str, seq: int), got {key!r:.80}")
    return key


@dataclass(frozen=True)
class EdgeRecord:
    """One factor of the graph, as persisted (node keys, not gtsam keys).

    Attributes:
        kind: ``odometry`` (consecutive keyframes of a session), ``loop`` (verified place
            recognition), ``prior`` (on one keyframe's map pose) or ``bundle`` (consecutive
            keyframes of a session, their relative pose from a bundle adjustment).
        a: first keyframe.
        b: second keyframe; None for a prior.
        T_a_b: (4, 4) pose of keyframe b's camera in keyframe a's camera frame; for a prior
            the prior pose ``T_map_a`` of keyframe a's camera in the map frame.
        sigmas: (6,) float64 standard deviations (rx, ry, rz rad, tx, ty, tz m), gtsam
            ``Pose3`` tangent order.
        robust: the factor is under the configured robust kernel (loop edges).
    """

    kind: EdgeKind
    a: NodeKey
    b: NodeKey | None
    T_a_b: F64
    sigmas: F64
    robust: bool

    def __post_init__(self) -> None:
        if self.kind not in ("odometry", "loop", "prior", "bundle"):
            raise GraphError(f"kind: expected odometry, loop, prior or bundle, got {self.kind!r:.40}")
        _check_node_key(self.a, "a")
        if (self.b is None) != (self.kind == "prior"):
            raise GraphError("b: must be None exactly for a prior edge")
        if self.b is not None:
            _check_node_key(self.b, "b")
        object.__setattr__(self, "T_a_b", _pose(self.T_a_b, "T_a_b"))
        sigmas = np.array(self.sigmas, dtype=np.float64)
        if sigmas.shape != (6,) or not (np.all(np.isfinite(sigmas)) and np.all(sigmas > 0)):
            raise GraphError(f"sigmas: expected 6 finite values > 0, got {sigmas}")
        sigmas.setflags(write=False)
        object.__setattr__(self, "sigmas", sigmas)


def _end_b(rec: EdgeRecord) -> NodeKey:
    """Second keyframe of an odometry or loop edge."""
    if rec.b is None:
        raise GraphError(f"a {rec.kind} edge needs two keyframes, b is None")
    return rec.b


@dataclass(frozen=True)
class NodeRecord:
    """One keyframe of the graph, as persisted.

    Attributes:
        key: the keyframe.
        T_odom_camera: (4, 4) its camera pose in its session's odom frame (from the robot).
        pose_source: what produced ``T_odom_camera`` (tracker pose source).
        T_map_camera: (4, 4) its map pose estimate when the record was taken; None while its
            session floats.
        prior_T_map_odom: (4, 4) the ``--map-pose`` prior the keyframe carried, or None.
    """

    key: NodeKey
    T_odom_camera: F64
    pose_source: PoseSource
    T_map_camera: F64 | None
    prior_T_map_odom: F64 | None

    def __post_init__(self) -> None:
        _check_node_key(self.key)
        if self.pose_source not in POSE_SOURCES:
            raise GraphError(f"pose_source: unknown {self.pose_source!r:.40}; expected one of {POSE_SOURCES}")
        object.__setattr__(self, "T_odom_camera", _pose(self.T_odom_camera, "T_odom_camera"))
        for name in ("T_map_camera", "prior_T_map_odom"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, _pose(value, name))


@dataclass(frozen=True)
class GraphUpdate:
    """What one :meth:`PoseGraph.update` changed.

    Attributes:
        moved_m: largest translation change (m) of any anchored keyframe's ``T_map_camera``
            estimate since the previous update (keyframes new to iSAM2 are not counted).
        sessions: ``T_map_odom`` (4, 4) of each session that was anchored in this update or
            whose ``T_map_odom`` moved more than ``report_trans_m`` / turned more than
            ``report_rot_deg`` since it was last reported.
        anchored: the sessions anchored since the previous update, in anchoring order.
    """

    moved_m: float
    sessions: dict[SessionKey, F64]
    anchored: tuple[SessionKey, ...]


@dataclass
class _Node:
    T_odom_camera: F64
    pose_source: PoseSource
    prior_T_map_odom: F64 | None
    index: int = -1
    """gtsam key; -1 while the session floats."""


@dataclass
class _Session:
    nodes: list[NodeKey] = field(default_factory=list)
    anchored: bool = False
    held: list[EdgeRecord] = field(default_factory=list)
    """Odometry and own loop edges kept aside while the session floats."""


def _isam_params(config: GraphConfig, factorization: str | None = None) -> gtsam.ISAM2Params:
    params = gtsam.ISAM2Params()
    # Thresholds per variable type, keyed by the gtsam Symbol character of the key: the
    # integer keys used here (< 2**56) all have character 0. Pose3 tangent order: rot, trans.
    thresholds = gtsam.ISAM2ThresholdMap()
    thresholds.insert(("\0", np.array([config.relinearize_rot_rad] * 3 + [config.relinearize_trans_m] * 3)))
    params.setRelinearizeThreshold(thresholds)
    params.relinearizeSkip = config.relinearize_skip
    params.setFactorization((factorization or config.factorization).upper())
    return params


class PoseGraph:
    """Keyframe pose graph of all robot sessions, optimised incrementally with iSAM2.

    Usage: :meth:`add_keyframe` for every keyframe in arrival order, :meth:`add_loop` for each
    verified loop edge, then :meth:`update` (once per keyframe, after its edges). Estimates
    (:meth:`estimate`, :meth:`T_map_odom`) are those of the last update; a keyframe added since
    has its initial value (its session's ``T_map_odom`` @ ``T_odom_camera``).
    """

    def __init__(self, config: GraphConfig | None = None) -> None:
        self.config = config if config is not None else GraphConfig()
        self.factorization: Literal["cholesky", "qr"] = self.config.factorization
        """The elimination in use: the configured one, or ``qr`` after a Cholesky failure."""
        self._isam = gtsam.ISAM2(_isam_params(self.config))
        self._factor_recs: list[EdgeRecord] = []
        """Every edge given to iSAM2, in order (to rebuild it with QR)."""
        if self.config.robust_kernel == "cauchy":
            self._kernel: gtsam.noiseModel.mEstimator.Base = gtsam.noiseModel.mEstimator.Cauchy.Create(
                self.config.robust_param)
        else:
            self._kernel = gtsam.noiseModel.mEstimator.Huber.Create(self.config.robust_param)
        self._nodes: dict[NodeKey, _Node] = {}
        self._order: list[NodeKey] = []
        """All keyframes in arrival order."""
        self._sessions: dict[SessionKey, _Session] = {}
        self._keys: list[NodeKey] = []
        """Keyframe of each gtsam key."""
        self._est: F64 = np.zeros((64, 4, 4))
        """(capacity, 4, 4) ``T_map_camera`` by gtsam key: the last update's estimate, or the
        initial value of a keyframe inserted since."""
        self._n_estimated = 0
        """gtsam keys below this had an estimate after the last update."""
        self._edges: list[EdgeRecord] = []
        self._pending: list[EdgeRecord] = []
        """Loop edges between two floating sessions."""
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._grown: set[SessionKey] = set()
        """Anchored sessions that got keyframes since the last update."""
        self._big_change = False
        """A loop factor or an anchoring since the last update."""
        self._settling = False
        """The last full re-read still saw keyframes move: re-read everything again."""
        self._anchored_new: list[SessionKey] = []
        self._reported: dict[SessionKey, F64] = {}
        self._emitted_nodes = 0
        self._emitted_edges = 0
        self._hints: dict[NodeKey, F64] = {}
        """During :meth:`restore`: stored ``T_map_camera`` estimates, used as initial values."""
        self._bundled: set[tuple[NodeKey, NodeKey]] = set()
        """Consecutive keyframe pairs that have a ``bundle`` edge."""

    # ------------------------------------------------------------------ input

    def add_keyframe(self, key: NodeKey, T_odom_camera: ArrayLike, *, pose_source: PoseSource,
                     prior_T_map_odom: ArrayLike | None = None) -> None:
        """Add a keyframe and the odometry edge from its session's previous keyframe.

        Args:
            key: ``(robot_id, session_id, seq)``. Keyframes of a session may come in any seq
                order (a resent keyframe after later ones): the odometry edge links each to the
                session's previous arrival (any two keyframes of a session share its odom frame).
            T_odom_camera: (4, 4) camera pose in the session's odom frame (m).
            pose_source: what produced ``T_odom_camera``; picks the odometry sigmas.
            prior_T_map_odom: (4, 4) the session's odom frame in the map frame (``--map-pose``),
                or None. It anchors a floating session at once (prior factor with
                ``prior_sigmas`` on this keyframe); on an anchored session it is ignored.

        The first session ever is anchored with ``T_map_odom`` = its prior or the identity; a
        gauge prior (``gauge_sigmas``, or ``prior_sigmas`` for a given prior) on its first
        keyframe fixes the map frame.

        Raises:
            GraphError: duplicate key, unknown pose source.
            GeometryError: a pose is not a rigid transform.
        """
        key = self._register(key, T_odom_camera, pose_source, prior_T_map_odom)
        node = self._nodes[key]
        skey: SessionKey = (key[0], key[1])
        sess = self._sessions[skey]
        if len(sess.nodes) > 1:
            prev = sess.nodes[-2]
            T_a_b = inverse(self._nodes[prev].T_odom_camera) @ node.T_odom_camera
            sigmas = self.config.odometry.for_source(pose_source).sigmas(T_a_b)
            odo = EdgeRecord("odometry", prev, key, T_a_b, sigmas, robust=False)
            self._edges.append(odo)
            if sess.anchored:
                self._insert_node(key, self._est[self._nodes[prev].index] @ T_a_b)
                self._add_factor(odo)
            else:
                sess.held.append(odo)
        if sess.anchored:
            return
        prior = node.prior_T_map_odom
        if prior is None and any(s.anchored for s in self._sessions.values()):
            return
        T_map_odom = np.eye(4) if prior is None else prior
        sigmas6 = self.config.gauge_sigmas if prior is None else self.config.prior_sigmas
        rec = EdgeRecord("prior", key, None, T_map_odom @ node.T_odom_camera, np.array(sigmas6), robust=False)
        self._edges.append(rec)
        self._anchor(skey, T_map_odom, rec)
        self._resolve_pending()

    def add_loop(self, a: NodeKey, b: NodeKey, T_a_b: ArrayLike, *, inliers: int,
                 sigmas: ArrayLike | None = None) -> LoopResult:
        """Add a verified loop edge: ``T_a_b`` (4, 4) = pose of keyframe b's camera in a's.

        Sigmas come from ``inliers`` (:meth:`GraphConfig.loop_sigmas`), or, given the
        verification's own estimate ``sigmas`` (6,) (rad x3, m x3, right perturbation of
        ``T_a_b``), from those (:meth:`GraphConfig.loop_sigmas_from`); the factor is robust.

        Returns:
            ``"loop"``: both sessions anchored, the factor goes into iSAM2 at the next update;
            ``"anchored"``: exactly one was anchored, the other session (and any floating session
            tied to it by pending edges) is now anchored through this edge;
            ``"floating"``: neither is anchored; the edge waits (in its session, or pending
            between the two sessions until one of them is anchored).

        Raises:
            GraphError: unknown keyframe, ``a == b``, ``inliers < 1``.
            GeometryError: ``T_a_b`` is not a rigid transform.
        """
        a = _check_node_key(a, "a")
        b = _check_node_key(b, "b")
        for name, k in (("a", a), ("b", b)):
            if k not in self._nodes:
                raise GraphError(f"{name}: unknown keyframe {k!r:.80}")
        if a == b:
            raise GraphError(f"a loop edge needs two keyframes, got {a!r:.80} twice")
        if isinstance(inliers, bool) or not isinstance(inliers, int | np.integer) or inliers < 1:
            raise GraphError(f"inliers: expected an integer >= 1, got {inliers!r}")
        edge_sigmas = (self.config.loop_sigmas(int(inliers)) if sigmas is None
                       else self.config.loop_sigmas_from(np.asarray(sigmas, np.float64)))
        rec = EdgeRecord("loop", a, b, _pose(T_a_b, "T_a_b"), edge_sigmas, robust=True)
        self._edges.append(rec)
        return self._place_loop(rec)

    def add_bundle_edges(self, poses: Mapping[NodeKey, ArrayLike]) -> int:
        """Add a ``bundle`` edge between every two consecutive keyframes of an anchored session
        that are both in ``poses`` (``key -> (4, 4) T_map_camera`` from a bundle adjustment) and
        have none yet: ``T_a_b = inv(P_a) @ P_b`` with ``bundle_sigmas``. Returns how many."""
        added = 0
        for sess in self._sessions.values():
            if not sess.anchored:
                continue
            for a, b in itertools.pairwise(sess.nodes):
                if (a, b) in self._bundled or a not in poses or b not in poses:
                    continue
                T_a_b = inverse(_pose(poses[a], "poses")) @ _pose(poses[b], "poses")
                rec = EdgeRecord("bundle", a, b, T_a_b, np.array(self.config.bundle_sigmas), robust=False)
                self._edges.append(rec)
                self._add_factor(rec)
                self._bundled.add((a, b))
                added += 1
        return added

    def unbundled(self, session: SessionKey) -> list[int]:
        """Consecutive keyframe pairs of a session without a ``bundle`` edge: index i stands
        for the pair (i, i + 1) of :meth:`session_keys`."""
        nodes = self._sessions[session].nodes if session in self._sessions else []
        return [i for i, (a, b) in enumerate(itertools.pairwise(nodes)) if (a, b) not in self._bundled]

    def session_keys(self, session: SessionKey) -> list[NodeKey]:
        """The keyframes of a session in arrival order."""
        return list(self._sessions[session].nodes) if session in self._sessions else []

    # ----------------------------------------------------------------- update

    def update(self) -> GraphUpdate:
        """Run one incremental iSAM2 update with the keyframes and edges added since the last.

        After a loop edge or an anchoring, up to ``loop_iterations`` more ``ISAM2.update()``
        calls (relinearizing what moved beyond the thresholds, until nothing does) and a full
        re-read of all estimates; otherwise only the new keyframes and the last
        ``refresh_tail`` of each grown session are re-read.
        """
        cfg = self.config
        n_prev = self._n_estimated
        big = self._big_change
        try:
            self._solve(big)
        except RuntimeError as exc:  # gtsam's IndeterminateLinearSystemException and kin
            if self.factorization != "cholesky":
                raise GraphError(f"iSAM2 update failed, the graph is unusable: {exc}") from exc
            _log.warning("iSAM2 Cholesky failed (%s); rebuilding the graph with QR",
                         str(exc).strip().splitlines()[0])
            self._rebuild_qr()
            big = True
            try:
                self._solve(big)
            except RuntimeError as exc2:
                raise GraphError(f"iSAM2 update failed, the graph is unusable: {exc2}") from exc2
        n = len(self._keys)
        moved = 0.0
        check: Iterable[SessionKey]
        if big or self._settling:
            rows = gtsam.utilities.extractPose3(self._isam.calculateEstimate()) if n else np.zeros((0, 12))
            new = np.zeros((n, 4, 4))
            new[:, :3, :3] = rows[:, :9].reshape(n, 3, 3)
            new[:, :3, 3] = rows[:, 9:]
            new[:, 3, 3] = 1.0
            if n_prev:
                moved = float(np.max(np.linalg.norm(new[:n_prev, :3, 3] - self._est[:n_prev, :3, 3], axis=1)))
            self._est[:n] = new
            self._settling = moved > cfg.report_trans_m
            check = [s for s, sess in self._sessions.items() if sess.anchored]
        else:
            indices = set(range(n_prev, n))
            for skey in self._grown:
                indices.update(self._tail(skey, n_prev))
            for i in sorted(indices):
                M = self._isam.calculateEstimatePose3(i).matrix()
                if i < n_prev:
                    moved = max(moved, float(np.linalg.norm(M[:3, 3] - self._est[i, :3, 3])))
                self._est[i] = M
            check = self._grown
        self._n_estimated = n
        reports: dict[SessionKey, F64] = {}
        for skey in [*self._anchored_new, *check]:
            if skey in reports:
                continue
            T = self._T_map_odom_now(skey)
            last = self._reported.get(skey)
            if skey in self._anchored_new or last is None or self._moved(last, T):
                reports[skey] = T
                self._reported[skey] = T
        anchored = tuple(self._anchored_new)
        self._anchored_new = []
        self._grown = set()
        self._big_change = False
        return GraphUpdate(moved_m=moved, sessions={k: v.copy() for k, v in reports.items()},
                           anchored=anchored)

    # ---------------------------------------------------------------- queries

    def _solve(self, big: bool) -> None:
        """Give iSAM2 the new factors and values; after a big change, relinearize and iterate."""
        if self._new_factors.size() > 0 or self._new_values.size() > 0:
            factors, values = self._new_factors, self._new_values
            self._new_factors = gtsam.NonlinearFactorGraph()
            self._new_values = gtsam.Values()
            self._isam.update(factors, values)
        if big:
            for _ in range(self.config.loop_iterations):
                if self._isam.update().getVariablesRelinearized() == 0:
                    break  # converged: nothing moved beyond the thresholds

    def _rebuild_qr(self) -> None:
        """Replace iSAM2 by a QR one holding every factor so far, from the last estimates."""
        self.factorization = "qr"
        self._isam = gtsam.ISAM2(_isam_params(self.config, "qr"))
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        for i in range(len(self._keys)):
            self._new_values.insert(i, gtsam.Pose3(self._est[i]))
        for rec in self._factor_recs:
            self._new_factors.add(self._factor(rec))

    def estimate(self, key: NodeKey) -> F64 | None:
        """``T_map_camera`` (4, 4) of a keyframe, or None if its session floats or it is unknown."""
        node = self._nodes.get(key)
        if node is None or node.index < 0:
            return None
        return self._est[node.index].copy()

    def estimates(self, keys: Sequence[NodeKey]) -> list[F64 | None]:
        """:meth:`estimate` of each key, in order."""
        return [self.estimate(k) for k in keys]

    def T_map_odom(self, session: SessionKey) -> F64 | None:
        """The session's odom frame in the map frame (4, 4), from its latest keyframe; None if
        the session floats or is unknown."""
        sess = self._sessions.get(session)
        if sess is None or not sess.anchored:
            return None
        return self._T_map_odom_now(session)

    def anchored(self, session: SessionKey) -> bool:
        """True when the session's keyframes are in the map frame."""
        sess = self._sessions.get(session)
        return sess is not None and sess.anchored

    def sessions(self) -> list[SessionKey]:
        """All sessions, in the order of their first keyframe."""
        return list(self._sessions)

    def __len__(self) -> int:
        """Number of keyframes (anchored and floating)."""
        return len(self._order)

    # ------------------------------------------------------------ persistence

    def records(self) -> tuple[list[NodeRecord], list[EdgeRecord]]:
        """All keyframes (arrival order, current estimates) and edges (creation order)."""
        return [self._node_record(k) for k in self._order], list(self._edges)

    def new_records(self) -> tuple[list[NodeRecord], list[EdgeRecord]]:
        """Keyframes and edges added since the last call (or since :meth:`restore`), each once.

        A node record's ``T_map_camera`` is its estimate at the time of the call (None while
        its session floats); later loop closures do not re-emit it.
        """
        nodes = [self._node_record(k) for k in self._order[self._emitted_nodes:]]
        edges = self._edges[self._emitted_edges:]
        self._emitted_nodes = len(self._order)
        self._emitted_edges = len(self._edges)
        return nodes, edges

    @classmethod
    def restore(cls, config: GraphConfig, nodes: Sequence[NodeRecord],
                edges: Sequence[EdgeRecord]) -> PoseGraph:
        """Rebuild a graph from its records in one batch iSAM2 update.

        ``nodes`` in arrival order, ``edges`` in creation order (as :meth:`records` or the
        concatenation of :meth:`new_records` gives them). Edges keep their stored sigmas; loop
        edges get ``config``'s kernel. A session is anchored when a prior edge or a chain of
        loop edges ties it to one with a prior, as when the graph was built. Stored
        ``T_map_camera`` estimates are the initial values. A session keeps its stored
        estimates when iSAM2's solution from them agrees with every one within
        ``report_trans_m`` / ``report_rot_deg`` (a restart does not move the map by the
        original's residual non-convergence); otherwise (stale records) it takes the
        solution. Anchored keyframes without one
        (recorded while floating) start at their session's ``T_map_odom`` (from another of its
        keyframes, or solved through the edge that anchored it) @ ``T_odom_camera``.
        The restored graph reports nothing new: :meth:`new_records` starts empty and the
        next :meth:`update` reports only changes after this one.

        Raises:
            GraphError: records that do not form a graph (unknown keyframe in an edge, seq
                out of order, duplicate keyframe, odometry edge across sessions).
        """
        graph = cls(config)
        for node in nodes:
            key = graph._register(node.key, node.T_odom_camera, node.pose_source, node.prior_T_map_odom)
            if node.T_map_camera is not None:
                graph._hints[key] = node.T_map_camera
        stored_est = dict(graph._hints)
        stored = list(edges)
        for rec in stored:
            for k in (rec.a, rec.b):
                if k is not None and k not in graph._nodes:
                    raise GraphError(f"edge {rec.kind}: unknown keyframe {k!r:.80}")
        for rec in stored:
            if rec.kind == "odometry":
                b = _end_b(rec)
                if rec.a[:2] != b[:2]:
                    raise GraphError(f"odometry edge across sessions: {rec.a!r:.80} -> {b!r:.80}")
                graph._sessions[(rec.a[0], rec.a[1])].held.append(rec)
        for rec in stored:
            if rec.kind == "prior":
                skey: SessionKey = (rec.a[0], rec.a[1])
                if graph._sessions[skey].anchored:
                    graph._add_factor(rec)
                    continue
                T_map_a = graph._hints.get(rec.a, rec.T_a_b)
                graph._anchor(skey, T_map_a @ inverse(graph._nodes[rec.a].T_odom_camera), rec)
        graph._resolve_pending()
        for rec in stored:
            if rec.kind == "loop":
                graph._place_loop(rec)
        for rec in stored:
            if rec.kind == "bundle":  # within an anchored session, added after its anchoring
                b = _end_b(rec)
                if not graph._sessions[(rec.a[0], rec.a[1])].anchored:
                    raise GraphError(f"bundle edge on a floating session: {rec.a!r:.80}")
                graph._add_factor(rec)
                graph._bundled.add((rec.a, b))
        graph._edges = stored
        graph._hints = {}
        graph.update()
        # A session whose stored estimates iSAM2's solution confirms (every one within the
        # report thresholds) keeps them: a restart must not move the map by the original's
        # residual non-convergence. Otherwise (stale records, taken before a later loop
        # closure) the session takes the solution.
        for sess in graph._sessions.values():
            kept = [(graph._nodes[k].index, stored_est[k]) for k in sess.nodes if k in stored_est]
            if sess.anchored and not any(graph._moved(graph._est[i], T) for i, T in kept):
                for i, T in kept:
                    graph._est[i] = T
        graph._reported = {s: graph._T_map_odom_now(s)
                           for s, sess in graph._sessions.items() if sess.anchored}
        graph._emitted_nodes = len(graph._order)
        graph._emitted_edges = len(graph._edges)
        return graph

    # -------------------------------------------------------------- internals

    def _register(self, key: NodeKey, T_odom_camera: ArrayLike, pose_source: PoseSource,
                  prior_T_map_odom: ArrayLike | None) -> NodeKey:
        """Check and store a keyframe (no edges, not in iSAM2)."""
        key = _check_node_key(key)
        if key in self._nodes:
            raise GraphError(f"keyframe {key!r:.80} is already in the graph")
        if pose_source not in POSE_SOURCES:
            raise GraphError(f"pose_source: unknown {pose_source!r:.40}; expected one of {POSE_SOURCES}")
        T = _pose(T_odom_camera, "T_odom_camera")
        prior = None if prior_T_map_odom is None else _pose(prior_T_map_odom, "prior_T_map_odom")
        skey: SessionKey = (key[0], key[1])
        sess = self._sessions.get(skey)
        if sess is None:
            sess = self._sessions[skey] = _Session()
        sess.nodes.append(key)
        self._nodes[key] = _Node(T, pose_source, prior)
        self._order.append(key)
        return key

    def _node_record(self, key: NodeKey) -> NodeRecord:
        node = self._nodes[key]
        est = None if node.index < 0 else self._est[node.index]
        return NodeRecord(key, node.T_odom_camera, node.pose_source, est, node.prior_T_map_odom)

    def _insert_node(self, key: NodeKey, T_map_camera: F64) -> None:
        """Give the keyframe a gtsam key and an initial value ``T_map_camera`` (4, 4)."""
        index = len(self._keys)
        if index == len(self._est):
            grown = np.zeros((2 * len(self._est), 4, 4))
            grown[:index] = self._est
            self._est = grown
        self._keys.append(key)
        self._nodes[key].index = index
        self._est[index] = T_map_camera
        self._new_values.insert(index, gtsam.Pose3(T_map_camera))
        self._grown.add((key[0], key[1]))

    def _factor(self, rec: EdgeRecord) -> gtsam.NonlinearFactor:
        noise: gtsam.noiseModel.Base = gtsam.noiseModel.Diagonal.Sigmas(rec.sigmas)
        if rec.robust:
            noise = gtsam.noiseModel.Robust.Create(self._kernel, noise)
        a = self._nodes[rec.a].index
        if rec.b is None:
            return gtsam.PriorFactorPose3(a, gtsam.Pose3(rec.T_a_b), noise)
        return gtsam.BetweenFactorPose3(a, self._nodes[rec.b].index, gtsam.Pose3(rec.T_a_b), noise)

    def _add_factor(self, rec: EdgeRecord) -> None:
        self._new_factors.add(self._factor(rec))
        self._factor_recs.append(rec)
        if rec.kind != "odometry":
            self._big_change = True

    def _anchor(self, skey: SessionKey, T_map_odom: F64, edge: EdgeRecord) -> None:
        """Put a floating session into iSAM2 at ``T_map_odom`` (4, 4), with the edge that anchors it."""
        sess = self._sessions[skey]
        sess.anchored = True
        for key in sess.nodes:
            hint = self._hints.pop(key, None)
            self._insert_node(key, T_map_odom @ self._nodes[key].T_odom_camera if hint is None else hint)
        for rec in sess.held:
            self._add_factor(rec)
        sess.held = []
        self._add_factor(edge)
        self._anchored_new.append(skey)
        self._big_change = True
        _log.debug("session %s anchored through a %s edge on %s", skey, edge.kind, edge.a)

    def _anchor_through(self, rec: EdgeRecord) -> None:
        """Anchor the floating end's session of a loop edge whose other end is anchored."""
        b = _end_b(rec)
        if self._sessions[(rec.a[0], rec.a[1])].anchored:
            T_map_b = self._est[self._nodes[rec.a].index] @ rec.T_a_b
            T_map_odom = T_map_b @ inverse(self._nodes[b].T_odom_camera)
            self._anchor((b[0], b[1]), T_map_odom, rec)
        else:
            T_map_a = self._est[self._nodes[b].index] @ inverse(rec.T_a_b)
            T_map_odom = T_map_a @ inverse(self._nodes[rec.a].T_odom_camera)
            self._anchor((rec.a[0], rec.a[1]), T_map_odom, rec)

    def _place_loop(self, rec: EdgeRecord) -> LoopResult:
        b = _end_b(rec)
        sa = self._sessions[(rec.a[0], rec.a[1])]
        sb = self._sessions[(b[0], b[1])]
        if sa.anchored and sb.anchored:
            self._add_factor(rec)
            return "loop"
        if sa.anchored or sb.anchored:
            self._anchor_through(rec)
            self._resolve_pending()
            return "anchored"
        if sa is sb:
            sa.held.append(rec)
        else:
            self._pending.append(rec)
        return "floating"

    def _resolve_pending(self) -> None:
        """Place pending loop edges that now touch an anchored session, until none does."""
        while True:
            for i, rec in enumerate(self._pending):
                b = _end_b(rec)
                sa = self._sessions[(rec.a[0], rec.a[1])].anchored
                sb = self._sessions[(b[0], b[1])].anchored
                if sa or sb:
                    del self._pending[i]
                    if sa and sb:
                        self._add_factor(rec)
                    else:
                        self._anchor_through(rec)
                    break
            else:
                return

    def _tail(self, skey: SessionKey, n_prev: int) -> list[int]:
        """gtsam keys of the last ``refresh_tail`` keyframes of a session before its new ones."""
        nodes = self._sessions[skey].nodes
        end = len(nodes)
        while end > 0 and self._nodes[nodes[end - 1]].index >= n_prev:
            end -= 1
        return [self._nodes[k].index for k in nodes[max(0, end - self.config.refresh_tail):end]]

    def _T_map_odom_now(self, skey: SessionKey) -> F64:
        last = self._nodes[self._sessions[skey].nodes[-1]]
        return self._est[last.index] @ inverse(last.T_odom_camera)

    def _moved(self, T_old: F64, T_new: F64) -> bool:
        if np.linalg.norm(T_new[:3, 3] - T_old[:3, 3]) > self.config.report_trans_m:
            return True
        return math.degrees(rotation_angle(T_old[:3, :3].T @ T_new[:3, :3])) > self.config.report_rot_deg
