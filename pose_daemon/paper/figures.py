"""The paper's figures redrawn from our runs: Fig. 4 (sweep) and Figs. 7-9 (unicycle)."""

from __future__ import annotations

from pathlib import Path
from typing import List

import numpy as np

from ..plotting import check_plot_dir, new_figure, save_figure
from .sweep import SweepResult
from .unicycle import UnicycleResult

UNICYCLE_FILES = ("fig7_trajectory.png", "fig8_heading.png", "fig9_heading_error.png")


def plot_sweep(result: SweepResult, path: str) -> Path:
    """Fig. 4: e_image of every orientation against its index, and their distribution."""
    fig, (ax, hist) = new_figure(1, 2, size_in=(11.0, 4.2))
    e = result.e_image
    finite = np.isfinite(e) & (e > 0)
    # A floor keeps exact zeros (possible with "iterative") on a log axis.
    floor = 1e-17
    shown = np.where(np.isfinite(e), np.maximum(e, floor), np.nan)
    idx = np.arange(e.size)
    ax.plot(idx, shown, ",", color="tab:blue", rasterized=True)
    ax.set_yscale("log")
    ax.set_xlabel("orientation index (alpha slowest, gamma fastest)")
    ax.set_ylabel("e_image (px, eq 17)")
    ax.set_title(f"Error norm for each orientation: {result.method}, "
                 f"{result.iterations} iterations")
    ax.grid(True, which="major", alpha=0.3)
    if finite.any():
        logs = np.log10(e[finite])
        hist.hist(logs, bins=80, color="tab:blue")
        hist.axvline(np.log10(1.4023e-6), color="tab:red", linestyle="--",
                     label="paper: 1.4023e-6")
        hist.legend(loc="upper left")
    hist.set_xlabel("log10 e_image (px)")
    hist.set_ylabel("orientations")
    hist.set_title(f"{result.count:,} orientations, max {np.nanmax(e):.2e} px")
    return save_figure(fig, path)


def plot_unicycle(result: UnicycleResult, directory: str) -> List[Path]:
    """Figs. 7-9 in ``directory``: trajectories, heading, heading error."""
    out = check_plot_dir(directory)
    true_run, est = result.true_run, result.estimated_run
    s = result.setup
    noise = f", pixel noise {s.noise_px:g} px" if s.noise_px > 0 else ""
    paths = []

    fig, ax = new_figure(size_in=(6.4, 5.2))
    ax.plot(true_run.x, true_run.z, "-", color="tab:blue", label="true pose as feedback")
    ax.plot(est.x, est.z, "--", color="tab:orange", label="estimated pose as feedback")
    ax.plot([s.start[0]], [s.start[1]], "o", color="black", label="start")
    ax.plot([s.goal[0]], [s.goal[1]], "*", color="tab:green", markersize=12, label="goal")
    ax.set_xlabel("X (cm)")
    ax.set_ylabel("Z (cm)")
    ax.set_title(f"Fig. 7: robot trajectory ({s.method}{noise})")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower left")
    paths.append(save_figure(fig, out / UNICYCLE_FILES[0]))

    fig, ax = new_figure()
    ax.plot(est.t_s, est.theta_deg, "-", color="tab:blue", label="actual heading")
    ax.plot(est.t_s, est.theta_est_deg, "--", color="tab:orange", label="estimated heading")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("robot heading (deg)")
    ax.set_title(f"Fig. 8: robot heading ({s.method}{noise})")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower right")
    paths.append(save_figure(fig, out / UNICYCLE_FILES[1]))

    fig, ax = new_figure()
    ax.plot(est.t_s, est.theta_est_deg - est.theta_deg, "-", color="tab:red")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("heading error (deg)")
    ax.set_title(f"Fig. 9: error in the estimated heading ({s.method}{noise})")
    ax.grid(True, alpha=0.3)
    paths.append(save_figure(fig, out / UNICYCLE_FILES[2]))
    return paths
