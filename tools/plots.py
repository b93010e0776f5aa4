"""Figures of offline evaluations, written as PNG (matplotlib, evo's own plotting library).

:func:`plot_ate`: the trajectory against its ground truth seen from above, and the
translation error over time (``wardmap eval ate --plot FILE.png``); :func:`plot_ate_compared`:
the same for several estimates of one trajectory (``bench/backend.py --plot``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wardmap.shared.errors import WardmapError
from wardmap.shared.metrics import AteResult, AteSeries

__all__ = ["PlotError", "plot_ate", "plot_ate_compared", "top_down_axes"]

_AXES = "xyz"


class PlotError(WardmapError):
    """A figure cannot be written."""


def top_down_axes(positions: np.ndarray) -> tuple[int, int]:
    """The two world axes (indices, ascending) along which ``positions`` (N, 3) spread most:
    the floor plane of a trajectory whatever its world's up axis."""
    spread = np.ptp(np.asarray(positions, np.float64), axis=0)
    a, b = sorted(np.argsort(spread)[-2:].tolist())
    return int(a), int(b)


def plot_ate(result: AteResult, series: AteSeries, out: str | Path, *, title: str = "") -> None:
    """Write a PNG: left, the reference and the aligned estimate on their floor plane
    (metres); right, the translation error of each pose over time, its RMSE in the legend.

    Raises:
        PlotError: ``out`` cannot be written.
    """
    plot_ate_compared([("estimate", result, series)], out, title=title or f"ATE over {result.n} poses")


def plot_ate_compared(runs: list[tuple[str, AteResult, AteSeries]], out: str | Path, *,
                      title: str = "") -> None:
    """Write a PNG like :func:`plot_ate` with several estimates of one trajectory, each aligned on
    its own (``(label, result, series)``; the first one's reference is drawn as ground truth).

    Raises:
        PlotError: no run, or ``out`` cannot be written.
    """
    if not runs:
        raise PlotError("plot_ate_compared: nothing to plot")
    import matplotlib

    matplotlib.use("Agg")  # files only: no display, no GUI toolkit
    import matplotlib.pyplot as plt

    ref = runs[0][2].positions_ref
    i, j = top_down_axes(ref)
    fig, (top, err) = plt.subplots(1, 2, figsize=(11, 4.5), gridspec_kw={"width_ratios": [1, 1.3]})
    try:
        top.plot(ref[:, i], ref[:, j], "--", color="0.4", label="ground truth")
        for label, result, series in runs:
            line = top.plot(series.positions_est[:, i], series.positions_est[:, j], "-", lw=1, label=label)[0]
            t = series.stamps - series.stamps[0]
            err.plot(t, series.errors_m, color=line.get_color(), lw=1,
                     label=f"{label}: RMSE {result.rmse:.3f} m")
        top.set_xlabel(f"{_AXES[i]} (m)")
        top.set_ylabel(f"{_AXES[j]} (m)")
        top.set_aspect("equal", adjustable="datalim")
        top.legend(loc="best")
        err.set_xlabel("time (s)")
        err.set_ylabel("translation error (m)")
        err.set_ylim(bottom=0)
        err.legend(loc="best")
        fig.suptitle(title)
        fig.tight_layout()
        fig.savefig(out, dpi=100)
    except OSError as exc:
        raise PlotError(f"cannot write {out}: {exc.strerror or exc}") from exc
    finally:
        plt.close(fig)
