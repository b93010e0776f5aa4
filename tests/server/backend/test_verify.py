"""Geometric verification of loop candidates: matching, EPnP in RANSAC, refinement, checks."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from wardmap.server.backend.verify import (
    REASONS,
    KeyframeFeatures,
    Verified,
    VerifyConfig,
    verify_pair,
)
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import ConfigError, GeometryError
from wardmap.shared.se3 import inverse, make_transform, rotation_angle, so3_exp, transform_points
from wardmap.shared.wire import Keypoints

CAM = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
T_CAND_QUERY = make_transform(so3_exp([0.03, np.radians(12.0), -0.02]), [0.35, -0.05, 0.2])
"""The query camera 35 cm right, 20 cm forward and turned 12 deg about y in the candidate frame."""


def _pose_error(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) of ``inv(T_true) @ T``."""
    D = inverse(T_true) @ T
    return float(np.linalg.norm(D[:3, 3])), float(np.degrees(rotation_angle(D[:3, :3])))


def _flip_bits(rng: np.random.Generator, desc: np.ndarray, bits: int) -> np.ndarray:
    """Copy of ``desc`` (N, 32) with ``bits`` random bits of each row flipped."""
    out = np.unpackbits(desc, axis=1)
    for row in out:
        idx = rng.choice(256, bits, replace=False)
        row[idx] ^= 1
    return np.packbits(out, axis=1)


def _pair(
    rng: np.random.Generator,
    *,
    inliers: int = 150,
    outliers: int = 150,
    camera: PinholeCamera = CAM,
    region: tuple[float, float, float, float] | None = None,
    noise_px: float = 0.5,
) -> tuple[KeyframeFeatures, KeyframeFeatures]:
    """Two keyframes seeing one random 3D scene from candidate and query poses.

    ``inliers`` points are seen by both cameras (projections with ``noise_px`` noise, the
    query's descriptors the candidate's with 8 of 256 bits flipped); ``outliers`` candidate
    points have their query keypoint at a random pixel (wrong matches). With ``region``
    ``(u0, v0, u1, v1)`` the true points lie only in that box of the candidate image.
    """
    T_query_cand = inverse(T_CAND_QUERY)
    pts: list[np.ndarray] = []
    while sum(len(p) for p in pts) < inliers:
        if region is None:
            uv = rng.uniform([0, 0], [camera.width, camera.height], (400, 2))
        else:
            uv = rng.uniform(region[:2], region[2:], (400, 2))
        P = camera.unproject(uv, rng.uniform(1.2, 4.5, 400))
        uv_q, front = camera.project(transform_points(T_query_cand, P))
        ok = front & camera.in_image(uv_q, margin=2)
        pts.append(P[ok])
    P_in = np.concatenate(pts)[:inliers]
    uv_c = camera.project(P_in)[0]
    uv_q = camera.project(transform_points(T_query_cand, P_in))[0]
    depth_q = transform_points(T_query_cand, P_in)[:, 2]
    P_out = camera.unproject(
        rng.uniform([0, 0], [camera.width, camera.height], (outliers, 2)), rng.uniform(1.2, 4.5, outliers)
    )
    uv_c = np.concatenate([uv_c, camera.project(P_out)[0]])
    uv_q = np.concatenate([uv_q, rng.uniform([0, 0], [camera.width, camera.height], (outliers, 2))])
    depth_c = np.concatenate([P_in[:, 2], P_out[:, 2]])
    depth_q = np.concatenate([depth_q, rng.uniform(1.2, 4.5, outliers)])
    desc_c = rng.integers(0, 256, (inliers + outliers, 32), dtype=np.uint8)
    desc_q = _flip_bits(rng, desc_c, 8)
    n = inliers + outliers
    cand = KeyframeFeatures(
        (uv_c + rng.normal(0, noise_px, (n, 2))).astype(np.float32),
        depth_c.astype(np.float32),
        desc_c,
        camera,
    )
    order = rng.permutation(n)  # the matcher must not rely on keypoint order
    query = KeyframeFeatures(
        (uv_q + rng.normal(0, noise_px, (n, 2))).astype(np.float32)[order],
        depth_q.astype(np.float32)[order],
        desc_q[order],
        camera,
    )
    return query, cand


def test_true_revisit_is_accepted_with_the_pose() -> None:
    """150 true matches and 150 wrong ones: accepted, T_cand_query within 1 cm and 0.5 deg,
    inliers are the true matches."""
    query, cand = _pair(np.random.default_rng(1))
    res = verify_pair(query, cand, VerifyConfig())
    assert isinstance(res, Verified), res
    t_err, r_err = _pose_error(res.T_cand_query, T_CAND_QUERY)
    assert t_err < 0.01 and r_err < 0.5
    assert 140 <= res.inliers <= 155 and res.matches == 300
    assert res.rms_px < 1.5  # 0.5 px noise in both images: about 1 px
    assert res.T_cand_query.dtype == np.float64 and res.T_cand_query.shape == (4, 4)


def test_pose_direction_maps_query_points_into_the_candidate_frame() -> None:
    """T_cand_query @ (a point in the query camera frame) = the point in the candidate frame."""
    query, cand = _pair(np.random.default_rng(2), outliers=0, noise_px=0.0)
    res = verify_pair(query, cand)
    assert isinstance(res, Verified)
    has = query.depth_m > 0
    p_query = query.camera.unproject(query.uv[has], query.depth_m[has])
    p_cand = transform_points(res.T_cand_query, p_query)
    uv, _ = cand.camera.project(p_cand)
    # each query point lands on some candidate keypoint (same scene point)
    d = np.linalg.norm(uv[:, None, :] - cand.uv[None, :, :], axis=2).min(axis=1)
    assert np.median(d) < 0.05


def test_distorted_cameras() -> None:
    """With lens distortion on both keyframes the pose is as accurate."""
    cam = PinholeCamera(640, 480, 517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633))
    query, cand = _pair(np.random.default_rng(3), camera=cam)
    res = verify_pair(query, cand)
    assert isinstance(res, Verified), res
    t_err, r_err = _pose_error(res.T_cand_query, T_CAND_QUERY)
    assert t_err < 0.01 and r_err < 0.5


def test_deterministic() -> None:
    """The same pair verifies to the same pose twice."""
    query, cand = _pair(np.random.default_rng(4))
    a, b = verify_pair(query, cand), verify_pair(query, cand)
    assert isinstance(a, Verified) and isinstance(b, Verified)
    np.testing.assert_array_equal(a.T_cand_query, b.T_cand_query)
    assert (a.inliers, a.matches, a.rms_px) == (b.inliers, b.matches, b.rms_px)


def test_other_scene_is_rejected() -> None:
    """A candidate of another place (unrelated descriptors) has no matches."""
    rng = np.random.default_rng(5)
    query, cand = _pair(rng)
    other = replace(cand, descriptors=rng.integers(0, 256, cand.descriptors.shape, dtype=np.uint8))
    assert verify_pair(query, other) == "few matches"


def test_same_look_other_geometry_is_rejected() -> None:
    """Matching descriptors on scrambled geometry (a planted false candidate: the look of the
    place, its 3D points shuffled) finds no consistent pose."""
    rng = np.random.default_rng(6)
    query, cand = _pair(rng)
    perm = rng.permutation(len(cand))
    scrambled = replace(cand, uv=cand.uv[perm], depth_m=cand.depth_m[perm])
    res = verify_pair(query, scrambled)
    assert res in ("pnp failed", "few inliers")
    assert res in REASONS


def test_too_few_points_are_rejected() -> None:
    """Fewer than min_matches keypoints, or candidate keypoints with depth, reject at once."""
    rng = np.random.default_rng(7)
    query, cand = _pair(rng, inliers=40, outliers=0)
    cfg = VerifyConfig()
    assert verify_pair(query, replace(cand, depth_m=np.zeros(len(cand), np.float32)), cfg) == "few points"
    far = np.full(len(cand), 9.0, np.float32)  # beyond depth_range_m
    assert verify_pair(query, replace(cand, depth_m=far), cfg) == "few points"
    few = KeyframeFeatures(query.uv[:10], query.depth_m[:10], query.descriptors[:10], CAM)
    assert verify_pair(few, cand, cfg) == "few points"
    assert verify_pair(query, cand, replace(cfg, min_inliers=45, min_matches=20)) == "few inliers"


def test_few_matches_rejected() -> None:
    """Only 15 shared features among 200 keypoints: too few matches for PnP."""
    rng = np.random.default_rng(8)
    query, cand = _pair(rng, inliers=200, outliers=0)
    desc = cand.descriptors.copy()
    desc[15:] = rng.integers(0, 256, desc[15:].shape, dtype=np.uint8)
    assert verify_pair(query, replace(cand, descriptors=desc)) == "few matches"


def test_low_inlier_ratio_rejected() -> None:
    """Half of the matches wrong is accepted by default, refused when 60 % must be inliers."""
    query, cand = _pair(np.random.default_rng(9))
    assert verify_pair(query, cand, VerifyConfig(min_inlier_ratio=0.6)) == "low inlier ratio"


def test_clustered_inliers_rejected() -> None:
    """A small textured object seen twice (all true matches in one 90 x 70 px box, inside one
    cell of the 4 x 4 grid) is not a place, however many features agree."""
    query, cand = _pair(np.random.default_rng(10), inliers=80, outliers=20, region=(170, 130, 260, 200))
    assert verify_pair(query, cand) == "clustered inliers"
    relaxed = verify_pair(query, cand, VerifyConfig(min_spread_cells=1))
    assert isinstance(relaxed, Verified)


def test_query_depth_must_agree() -> None:
    """Query depths 40 % too far disagree with the candidate's 3D points; no query depth at
    all skips the check."""
    query, cand = _pair(np.random.default_rng(11))
    assert verify_pair(replace(query, depth_m=query.depth_m * 1.4), cand) == "depth mismatch"
    blind = verify_pair(replace(query, depth_m=np.zeros(len(query), np.float32)), cand)
    assert isinstance(blind, Verified)


def test_without_mutual_check() -> None:
    """The one-way matcher (ambiguous candidate keypoints dropped) also verifies."""
    query, cand = _pair(np.random.default_rng(12))
    res = verify_pair(query, cand, VerifyConfig(mutual=False))
    assert isinstance(res, Verified)
    assert _pose_error(res.T_cand_query, T_CAND_QUERY)[0] < 0.01


def _plane_views(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float]:
    """A random texture on the plane z = 2 m of the candidate camera (fronto-parallel, so the
    candidate image is the texture) and the query view rendered through the plane homography."""
    noise = rng.uniform(0, 255, (120, 160)).astype(np.float32)
    tex = np.asarray(cv2.resize(noise, (640, 480), interpolation=cv2.INTER_CUBIC), np.float32)
    tex += rng.normal(0, 30, tex.shape).astype(np.float32)
    tex = np.asarray(cv2.GaussianBlur(tex, (0, 0), 1.0), np.float32)
    cand_img = np.clip(tex, 0, 255).astype(np.uint8)
    d = 2.0
    T_qc = inverse(T_CAND_QUERY)
    n = np.array([0.0, 0.0, 1.0])
    H = CAM.K @ (T_qc[:3, :3] + np.outer(T_qc[:3, 3], n) / d) @ np.linalg.inv(CAM.K)
    query_img = cv2.warpPerspective(cand_img, H, (640, 480), flags=cv2.INTER_LINEAR)
    return cand_img, query_img, d


def test_rendered_plane_with_orb() -> None:
    """Real ORB features of two rendered views of a textured wall: accepted and the query's
    depth (ray-plane intersection) agrees. One plane seen head-on couples rotation and
    translation, and ORB positions at coarse octaves are rough: pose within 3 cm and 1 deg."""
    rng = np.random.default_rng(13)
    cand_img, query_img, d = _plane_views(rng)
    orb = cv2.ORB.create(nfeatures=1000)
    kc, dc = orb.detectAndCompute(cand_img, None)
    kq, dq = orb.detectAndCompute(query_img, None)
    uv_c = np.array([k.pt for k in kc], np.float32)
    uv_q = np.array([k.pt for k in kq], np.float32)
    # Plane in the query frame: n_q . X_q = d_q with n_q = R_cq^T n_c, d_q = d - n_c . t_cq.
    n_q = T_CAND_QUERY[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    d_q = d - T_CAND_QUERY[2, 3]
    rays = np.column_stack(
        [(uv_q[:, 0] - CAM.cx) / CAM.fx, (uv_q[:, 1] - CAM.cy) / CAM.fy, np.ones(len(uv_q))]
    )
    depth_q = (d_q / (rays @ n_q)).astype(np.float32)
    cand = KeyframeFeatures(uv_c, np.full(len(uv_c), d, np.float32), dc, CAM)
    query = KeyframeFeatures(uv_q, depth_q, dq, CAM)
    res = verify_pair(query, cand)
    assert isinstance(res, Verified), res
    t_err, r_err = _pose_error(res.T_cand_query, T_CAND_QUERY)
    assert t_err < 0.03 and r_err < 1.0
    assert res.inliers > 100


def test_from_keypoints() -> None:
    """Wire keypoints become features with the same arrays, read-only."""
    rng = np.random.default_rng(14)
    n = 50
    kp = Keypoints(
        uv=rng.uniform(0, 400, (n, 2)).astype(np.float32),
        octave=np.zeros(n, np.int8),
        angle_deg=np.zeros(n, np.float32),
        depth_m=rng.uniform(0, 3, n).astype(np.float32),
        descriptors=rng.integers(0, 256, (n, 32), dtype=np.uint8),
    )
    f = KeyframeFeatures.from_keypoints(kp, CAM)
    assert len(f) == n and f.camera is CAM
    np.testing.assert_array_equal(f.uv, kp.uv)
    np.testing.assert_array_equal(f.depth_m, kp.depth_m)
    np.testing.assert_array_equal(f.descriptors, kp.descriptors)
    assert not f.uv.flags.writeable and not f.descriptors.flags.writeable


def test_features_reject_bad_arrays() -> None:
    """Wrong shapes, dtypes, non-finite pixels and negative depth raise GeometryError."""
    uv = np.zeros((5, 2), np.float32)
    depth = np.ones(5, np.float32)
    desc = np.zeros((5, 32), np.uint8)
    with pytest.raises(GeometryError, match="uv"):
        KeyframeFeatures(np.zeros((5, 3), np.float32), depth, desc, CAM)
    with pytest.raises(GeometryError, match="depth"):
        KeyframeFeatures(uv, np.ones(4, np.float32), desc, CAM)
    with pytest.raises(GeometryError, match="descriptors"):
        KeyframeFeatures(uv, depth, np.zeros((5, 32), np.int16), CAM)
    with pytest.raises(GeometryError, match="uv"):
        KeyframeFeatures(np.full((5, 2), np.nan, np.float32), depth, desc, CAM)
    with pytest.raises(GeometryError, match="depth"):
        KeyframeFeatures(uv, -depth, desc, CAM)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("ratio", 0.0),
        ("max_hamming", 300),
        ("min_matches", 3),
        ("depth_range_m", (2.0, 1.0)),
        ("reprojection_px", 0.0),
        ("ransac_iterations", 0),
        ("ransac_confidence", 1.0),
        ("min_inliers", 5),
        ("min_inlier_ratio", 1.5),
        ("spread_grid", (0, 4)),
        ("min_spread_cells", 17),
        ("depth_tolerance", 0.0),
        ("min_depth_agreement", -0.1),
    ],
)
def test_config_rejects_bad_values(field: str, value: object) -> None:
    """Out-of-range settings raise ConfigError naming the field."""
    with pytest.raises(ConfigError, match=field):
        VerifyConfig(**{field: value})
