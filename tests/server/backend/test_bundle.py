"""Bundle adjustment over keyframe features: it removes drift that the initial poses carry."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from wardmap.server.backend.bundle import BundleConfig, BundleFrame, _level_noise, _pairs, bundle_adjust
from wardmap.server.backend.verify import KeyframeFeatures
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import GeometryError
from wardmap.shared.se3 import inverse, make_transform, rotation_angle, so3_exp
from wardmap.shared.wire import POINT_ID_SPAN

CAM = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)


def _scene(rng: np.random.Generator, n_frames: int = 24) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Cameras walking along x looking at a textured wall 2-4 m ahead (z), and the wall's
    points (M, 3) with a unique ORB-like descriptor each (M, 32)."""
    truth = [make_transform(so3_exp([0.0, 0.02 * np.sin(i / 3), 0.0]), [0.12 * i, 0.0, 0.0])
             for i in range(n_frames)]
    m = 4000
    pts = np.stack([rng.uniform(-2.5, 0.12 * n_frames + 2.5, m), rng.uniform(-1.2, 1.2, m),
                    rng.uniform(2.0, 4.0, m)], 1)
    desc = rng.integers(0, 256, size=(m, 32), dtype=np.uint8)
    return truth, pts, desc


def _features(rng: np.random.Generator, T: np.ndarray, pts: np.ndarray, desc: np.ndarray, *,
              ids: bool = False, scramble: bool = False) -> KeyframeFeatures:
    """The frame's view of the wall; ``ids``: each keypoint's map point id is its wall point's
    index; ``scramble``: descriptors drawn afresh in every view (no descriptor match exists)."""
    Ti = inverse(T)
    pc = pts @ Ti[:3, :3].T + Ti[:3, 3]
    uv = np.stack([CAM.fx * pc[:, 0] / pc[:, 2] + CAM.cx, CAM.fy * pc[:, 1] / pc[:, 2] + CAM.cy], 1)
    seen = (pc[:, 2] > 0.3) & CAM.in_image(uv, margin=2.0)
    idx = np.nonzero(seen)[0][:500]
    uv_noisy = uv[idx] + rng.normal(0.0, 0.5, size=(len(idx), 2))
    z = pc[idx, 2] + rng.normal(0.0, 0.002, size=len(idx))
    z[rng.random(len(idx)) < 0.2] = 0.0  # some keypoints without depth
    d = desc[idx].copy()
    flips = rng.integers(0, 256, size=(len(idx), 3))  # a few bits differ between views
    for row, bits in zip(d, flips, strict=True):
        for b in bits:
            row[b // 8] ^= np.uint8(1 << (b % 8))
    if scramble:
        d = rng.integers(0, 256, size=d.shape, dtype=np.uint8)
    return KeyframeFeatures(uv_noisy.astype(np.float32), z.astype(np.float32), d, CAM,
                            point_id=idx.astype(np.int64) if ids else None)


def _errors(poses: list[np.ndarray], truth: list[np.ndarray]) -> tuple[float, float]:
    """Worst translation (m) and rotation (deg) error relative to the first frame."""
    t, r = 0.0, 0.0
    for P, G in zip(poses, truth, strict=True):
        D = inverse(inverse(truth[0]) @ G) @ (inverse(poses[0]) @ P)
        t = max(t, float(np.linalg.norm(D[:3, 3])))
        r = max(r, float(np.degrees(rotation_angle(D[:3, :3]))))
    return t, r


def test_bundle_adjustment_removes_drift() -> None:
    rng = np.random.default_rng(7)
    truth, pts, desc = _scene(rng)
    # initial poses with a drift that grows along the path (1 mm and 0.03 deg per frame)
    drift = make_transform(so3_exp([0.0, np.radians(0.025), np.radians(0.015)]), [0.001, 0.0005, 0.0])
    init, acc = [], np.eye(4)
    for G in truth:
        init.append(G @ acc)
        acc = acc @ drift
    frames = [BundleFrame(i, T, _features(rng, G, pts, desc), chain="s")
              for i, (T, G) in enumerate(zip(init, truth, strict=True))]
    before = _errors(init, truth)
    res = bundle_adjust(frames, BundleConfig())
    after = _errors([res.poses[i] for i in range(len(frames))], truth)
    assert before[0] > 0.02 and before[1] > 0.6
    assert after[0] < 0.01, (before, after)
    assert after[1] < 0.15, (before, after)
    assert np.array_equal(res.poses[0], init[0])  # the gauge is held
    assert res.landmarks > 500 and res.observations > 3000
    assert res.error_after < res.error_before


def test_level_prior_holds_tilt_and_height_only() -> None:
    """A ground robot's camera pitched 30 deg down in a z-up map: the prior does not resist a
    move along the floor or a turn about the vertical, and costs one sigma for 2 cm up or
    0.5 deg of tilt about either horizontal axis."""
    pitch_down = so3_exp([-np.pi / 2 - np.radians(30.0), 0.0, 0.0])  # camera z forward and 30 deg down
    T0 = make_transform(so3_exp([0.0, 0.0, 0.7]) @ pitch_down, [2.0, 1.0, 1.1])
    rng = np.random.default_rng(2)
    truth, pts, desc = _scene(rng, n_frames=1)
    frame = BundleFrame(0, T0, _features(rng, truth[0], pts, desc), up=np.array([0.0, 0.0, 1.0]))
    factor = gtsam.PriorFactorPose3(0, gtsam.Pose3(T0), _level_noise(frame, (0.5, 0.02)))

    def cost(T: np.ndarray) -> float:
        values = gtsam.Values()
        values.insert(0, gtsam.Pose3(T))
        return float(factor.error(values))

    slide_and_turn = make_transform(so3_exp([0.0, 0.0, np.radians(5.0)]), [0.3, -0.2, 0.0]) @ T0
    assert cost(slide_and_turn) < 1e-3
    assert cost(make_transform(np.eye(3), [0.0, 0.0, 0.02]) @ T0) == pytest.approx(0.5, rel=0.02)
    for axis in ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]):
        tilt = make_transform(so3_exp(np.radians(0.5) * np.array(axis)), [0.0, 0.0, 0.0])
        T = tilt @ T0
        T[:3, 3] = T0[:3, 3]  # about the camera's own centre
        assert cost(T) == pytest.approx(0.5, rel=0.02)


def test_level_prior_lets_the_adjustment_remove_drift_along_the_floor() -> None:
    """Up is -y in the wall scene; a drift in heading and along the path is still removed."""
    rng = np.random.default_rng(11)
    truth, pts, desc = _scene(rng)
    drift = make_transform(so3_exp([0.0, np.radians(0.03), 0.0]), [0.0015, 0.0, 0.0005])
    init, acc = [], np.eye(4)
    for G in truth:
        init.append(G @ acc)
        acc = acc @ drift
    up = np.array([0.0, -1.0, 0.0])
    frames = [BundleFrame(i, T, _features(rng, G, pts, desc), chain="s", up=up)
              for i, (T, G) in enumerate(zip(init, truth, strict=True))]
    before = _errors(init, truth)
    res = bundle_adjust(frames, BundleConfig())
    after = _errors([res.poses[i] for i in range(len(frames))], truth)
    assert before[0] > 0.03 and before[1] > 0.6
    assert after[0] < 0.01 and after[1] < 0.15, (before, after)


def test_wrong_depths_are_dropped_not_followed() -> None:
    """30 % of two frames' depths 40 % short (a keypoint on a depth edge reads the foreground):
    the robust kernel and the second solve drop them and the poses stay as without them
    (followed, they cost 8 cm)."""
    rng = np.random.default_rng(3)
    truth, pts, desc = _scene(rng, n_frames=12)
    frames, bad = [], 0
    for i, G in enumerate(truth):
        f = _features(rng, G, pts, desc)
        if i in (5, 6):
            d = np.array(f.depth_m)
            wrong = (rng.random(len(d)) < 0.3) & (d > 0)
            d[wrong] *= 0.6
            bad += int(wrong.sum())
            f = KeyframeFeatures(f.uv, d.astype(np.float32), f.descriptors, CAM)
        frames.append(BundleFrame(i, G, f, chain="s"))
    res = bundle_adjust(frames, BundleConfig())
    t, r = _errors([res.poses[i] for i in range(len(frames))], truth)
    assert t < 0.004 and r < 0.1, (t, r)
    assert res.dropped >= 0.9 * bad


def test_frames_of_other_chains_only_pair_as_revisits() -> None:
    rng = np.random.default_rng(5)
    truth, pts, desc = _scene(rng, n_frames=8)
    frames = [BundleFrame(i, G, _features(rng, G, pts, desc), chain=i // 4) for i, G in enumerate(truth)]
    # the sequence window never crosses chains; close cameras of another chain pair as revisits
    assert all(j // 4 == i // 4 for j, i in _pairs(frames, BundleConfig(revisit_radius_m=0.01)))
    assert any(j // 4 != i // 4 for j, i in _pairs(frames, BundleConfig(revisit_radius_m=1.0)))
    res = bundle_adjust(frames, BundleConfig(revisit_radius_m=0.01))
    # no revisits, windows within a chain: two problems (the second held by the weak priors)
    assert res.landmarks > 0
    t, r = _errors([res.poses[i] for i in range(8)], truth)
    assert t < 0.02 and r < 0.3


def _drifting(truth: list[np.ndarray]) -> list[np.ndarray]:
    drift = make_transform(so3_exp([0.0, np.radians(0.025), np.radians(0.015)]), [0.001, 0.0005, 0.0])
    init, acc = [], np.eye(4)
    for G in truth:
        init.append(G @ acc)
        acc = acc @ drift
    return init


def test_exact_tracks_join_keypoints_by_map_point_id() -> None:
    """Descriptors that never match between views but the tracker's map point ids: the tracks
    come from the ids and the drift goes; with exact tracks off nothing is matched and the
    initial poses stay (only the weak priors act)."""
    rng = np.random.default_rng(7)
    truth, pts, desc = _scene(rng)
    init = _drifting(truth)
    frames = [BundleFrame(i, T, _features(rng, G, pts, desc, ids=True, scramble=True), chain="s")
              for i, (T, G) in enumerate(zip(init, truth, strict=True))]
    before = _errors(init, truth)
    res = bundle_adjust(frames, BundleConfig())
    after = _errors([res.poses[i] for i in range(len(frames))], truth)
    assert res.landmarks > 500 and res.observations > 3000
    assert after[0] < 0.01 and after[1] < 0.15, (before, after)
    off = bundle_adjust(frames, BundleConfig(tracks="descriptors"))
    assert off.landmarks == 0
    assert _errors([off.poses[i] for i in range(len(frames))], truth)[0] > 0.8 * before[0]


def test_map_point_ids_join_only_within_their_chain() -> None:
    """Two sessions reuse the same id numbers for different points: ids never join across
    chains (that takes a descriptor match of a revisit, none here)."""
    rng = np.random.default_rng(9)
    truth, pts, desc = _scene(rng, n_frames=8)
    frames = []
    for i, G in enumerate(truth):
        f = _features(rng, G, pts, desc, ids=True, scramble=True)
        if i >= 4:  # the second session numbers its points differently
            f = KeyframeFeatures(f.uv, f.depth_m, f.descriptors, CAM, point_id=np.asarray(f.point_id) + 7)
        frames.append(BundleFrame(i, G, f, chain=i // 4))
    res = bundle_adjust(frames, BundleConfig(revisit_radius_m=1.0))
    one_chain = sum(bundle_adjust(part, BundleConfig()).landmarks for part in (frames[:4], frames[4:]))
    assert res.landmarks == one_chain


def test_map_point_ids_join_only_frames_within_the_id_span() -> None:
    """Ids travel modulo 2**31: the same id in frames POINT_ID_SPAN or more apart in seq is
    another point and joins nothing."""
    rng = np.random.default_rng(9)
    truth, pts, desc = _scene(rng, n_frames=4)
    feats = [_features(rng, G, pts, desc, ids=True, scramble=True) for G in truth]
    near = [BundleFrame(i, G, f, chain="s", seq=i) for i, (G, f) in enumerate(zip(truth, feats, strict=True))]
    far = [BundleFrame(i, G, f, chain="s", seq=i * POINT_ID_SPAN)
           for i, (G, f) in enumerate(zip(truth, feats, strict=True))]
    assert bundle_adjust(near, BundleConfig()).landmarks > 100
    assert bundle_adjust(far, BundleConfig()).landmarks == 0


def test_bad_input_is_refused() -> None:
    rng = np.random.default_rng(1)
    truth, pts, desc = _scene(rng, n_frames=2)
    f = _features(rng, truth[0], pts, desc)
    with pytest.raises(GeometryError, match="at least two"):
        bundle_adjust([BundleFrame(0, truth[0], f)])
    other = KeyframeFeatures(f.uv, f.depth_m, f.descriptors,
                             PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0))
    with pytest.raises(GeometryError, match="different cameras"):
        bundle_adjust([BundleFrame(0, truth[0], f), BundleFrame(1, truth[1], other)])
    with pytest.raises(GeometryError, match="window"):
        BundleConfig(window=0)
    with pytest.raises(GeometryError, match="tracks"):
        BundleConfig(tracks="nearest")  # type: ignore[arg-type]
