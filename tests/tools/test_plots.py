"""``tools/plots.py`` and ``wardmap eval ate --plot``: a PNG of a trajectory against its
ground truth and the error over time."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from procs import one_line_error, wardmap

from wardmap.shared import se3
from wardmap.shared.metrics import ate_series
from wardmap.tools.plots import PlotError, plot_ate, plot_ate_compared, top_down_axes


def _square_walk(n: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """Camera poses along a 4 m x 2 m rectangle at 1.2 m height (world z up), 10 Hz."""
    t = np.linspace(0.0, 1.0, n, endpoint=False)
    x = np.interp(t, [0, 0.33, 0.5, 0.83, 1.0], [0, 4, 4, 0, 0])
    y = np.interp(t, [0, 0.33, 0.5, 0.83, 1.0], [0, 0, 2, 2, 0])
    poses = [se3.make_transform(np.eye(3), [a, b, 1.2]) for a, b in zip(x, y, strict=True)]
    return np.arange(n) * 0.1, np.array(poses)


def test_top_down_axes_are_the_floor() -> None:
    """For a walk on the x-y floor the plane is (x, y); for a TUM-like y-down world (x, z)."""
    _, T = _square_walk()
    assert top_down_axes(T[:, :3, 3]) == (0, 1)
    assert top_down_axes(T[:, :3, 3][:, [0, 2, 1]]) == (0, 2)


def test_plot_is_a_png(tmp_path: Path) -> None:
    """A noisy estimate of the walk: the figure is a PNG of the size asked (1100 x 450 px);
    an unwritable path is a PlotError."""
    stamps, T = _square_walk()
    rng = np.random.default_rng(0)
    est = np.array([t @ se3.make_transform(np.eye(3), rng.normal(0, 0.03, 3)) for t in T])
    result, series = ate_series(stamps, est, stamps, T)
    out = tmp_path / "ate.png"
    plot_ate(result, series, out)
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    assert (width, height) == (1100, 450)
    with pytest.raises(PlotError, match="cannot write"):
        plot_ate(result, series, tmp_path / "no" / "such" / "dir.png")


def test_compared_plot_draws_each_estimate(tmp_path: Path) -> None:
    """Two estimates of one walk in one PNG (1100 x 450 px); nothing to plot is a PlotError."""
    stamps, T = _square_walk()
    rng = np.random.default_rng(1)
    runs = []
    for label, noise in (("coarse", 0.05), ("fine", 0.01)):
        est = np.array([t @ se3.make_transform(np.eye(3), rng.normal(0, noise, 3)) for t in T])
        runs.append((label, *ate_series(stamps, est, stamps, T)))
    out = tmp_path / "compared.png"
    plot_ate_compared(runs, out, title="two estimates")
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert (int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")) == (1100, 450)
    with pytest.raises(PlotError, match="nothing to plot"):
        plot_ate_compared([], out)


def test_eval_ate_plot_from_the_command_line(tmp_path: Path) -> None:
    """``wardmap eval ate EST --reference GT --plot FILE.png`` prints the JSON and writes the
    PNG; a plot path in a missing folder is one line and exit 1."""
    stamps, T = _square_walk()
    lines = [f"{s:.6f} " + " ".join(f"{v:.9g}" for v in se3.transform_to_tum(t))
             for s, t in zip(stamps, T, strict=True)]
    (tmp_path / "gt.txt").write_text("\n".join(lines) + "\n")
    p = wardmap("eval", "ate", str(tmp_path / "gt.txt"), "--reference", str(tmp_path / "gt.txt"),
                "--plot", str(tmp_path / "ate.png"))
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "ate.png").read_bytes()[:4] == b"\x89PNG"
    one_line_error(wardmap("eval", "ate", str(tmp_path / "gt.txt"), "--reference", str(tmp_path / "gt.txt"),
                           "--plot", str(tmp_path / "no" / "ate.png")), "cannot write", "eval")
