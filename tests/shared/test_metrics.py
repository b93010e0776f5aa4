"""ATE through evo agrees with an independent Umeyama/Horn alignment on real trajectories."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from wardmap.shared import se3
from wardmap.shared.errors import DatasetError
from wardmap.shared.metrics import ate, rpe

TRAJ = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "tum_trajectories"


def _read(path: Path) -> tuple[np.ndarray, np.ndarray]:
    rows = [
        list(map(float, ln.split()))
        for ln in path.read_text().splitlines()
        if ln.strip() and not ln.startswith("#")
    ]
    a = np.array(rows)
    return a[:, 0], np.array([se3.transform_from_tum(r[1:]) for r in a])


def _horn_rmse(P: np.ndarray, G: np.ndarray) -> float:
    mp, mg = P.mean(0), G.mean(0)
    U, _, Vt = np.linalg.svd((P - mp).T @ (G - mg))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ D @ U.T
    return float(np.sqrt(np.mean(np.sum(((P - mp) @ R.T + mg - G) ** 2, axis=1))))


def test_identical_and_rigidly_moved_trajectories_have_zero_ate() -> None:
    """A trajectory against itself moved by a rigid transform: ATE 0 after SE3 alignment,
    non-zero without alignment."""
    rng = np.random.default_rng(0)
    T = np.array([se3.se3_exp(rng.normal(0, 0.5, 6)) for _ in range(50)])
    stamps = np.arange(50) * 0.1
    M = se3.se3_exp([1.0, -2.0, 0.5, 0.1, 0.2, -0.3])
    moved = np.array([M @ t for t in T])
    assert ate(stamps, moved, stamps, T).rmse < 1e-9
    assert ate(stamps, moved, stamps, T, align="none").rmse > 0.5


@pytest.mark.skipif(not TRAJ.is_dir(), reason="../shared/data/tum_trajectories absent")
def test_rgbdslam_on_fr1_xyz_matches_independent_alignment() -> None:
    """evo's ATE of RGBD-SLAM on fr1/xyz equals our own Horn alignment on the same pairs."""
    ts, Ts = _read(TRAJ / "freiburg1_xyz-rgbdslam.txt")
    tg, Tg = _read(TRAJ / "freiburg1_xyz-groundtruth.txt")
    res = ate(ts, Ts, tg, Tg)
    idx = np.searchsorted(tg, ts)
    idx = np.clip(idx, 1, len(tg) - 1)
    near = np.where(np.abs(tg[idx - 1] - ts) < np.abs(tg[idx] - ts), idx - 1, idx)
    ok = np.abs(tg[near] - ts) < 0.02
    own = _horn_rmse(Ts[ok, :3, 3], Tg[near[ok], :3, 3])
    assert res.n == int(ok.sum())
    assert res.rmse == pytest.approx(own, rel=1e-6)
    assert 0.005 < res.rmse < 0.1


def test_too_few_pairs_is_an_error() -> None:
    """Trajectories that do not overlap in time cannot be scored."""
    T = np.array([np.eye(4)] * 5)
    with pytest.raises(DatasetError):
        ate(np.arange(5.0), T, np.arange(5.0) + 100, T)


def test_ate_series_holds_the_errors_behind_the_statistics() -> None:
    """The series :func:`ate_series` returns with the result: one error per associated pose,
    whose RMSE and maximum are the result's, and aligned estimate positions that far from the
    reference's."""
    from wardmap.shared.metrics import ate_series

    rng = np.random.default_rng(1)
    T = np.array([se3.se3_exp(rng.normal(0, 0.5, 6)) for _ in range(40)])
    noisy = np.array([t @ se3.se3_exp(np.r_[rng.normal(0, 0.02, 3), 0, 0, 0]) for t in T])
    stamps = np.arange(40) * 0.1
    res, series = ate_series(stamps, noisy, stamps, T)
    assert series.errors_m.shape == (40,) and series.positions_est.shape == (40, 3)
    assert np.sqrt(np.mean(series.errors_m ** 2)) == pytest.approx(res.rmse)
    assert series.errors_m.max() == pytest.approx(res.max)
    assert np.allclose(np.linalg.norm(series.positions_est - series.positions_ref, axis=1), series.errors_m)
    assert np.allclose(series.stamps, stamps) and ate(stamps, noisy, stamps, T) == res


def test_rpe_is_the_frame_to_frame_error_and_ignores_a_rigid_offset() -> None:
    """Scenario: a straight reference moving 10 cm per frame; an estimate moved rigidly far
    away has zero RPE (no alignment needed), and one whose odd frames sit 1 cm ahead (jitter)
    has every step 1 cm off: RPE RMSE and max 1 cm."""
    n = 21
    stamps = np.arange(n) * 0.1
    T = np.stack([se3.make_transform(np.eye(3), [0.1 * i, 0.0, 0.0]) for i in range(n)])
    moved = np.stack([se3.se3_exp([5.0, -2.0, 1.0, 0.3, 0.2, -0.1]) @ t for t in T])
    assert rpe(stamps, moved, stamps, T).rmse < 1e-9
    jitter = T.copy()
    jitter[:, 0, 3] += 0.01 * (np.arange(n) % 2)
    r = rpe(stamps, jitter, stamps, T)
    assert r.n == n - 1
    assert r.rmse == pytest.approx(0.01, rel=1e-6) and r.max == pytest.approx(0.01, rel=1e-6)
