"""The paper's figures redrawn from our runs: Fig. 4 (sweep) and Figs. 7-9 (unicycle)."""

from __future__ import annotations

from pathlib import Path
from typing import List

import numpy as np

from ..plotting import check_plot_dir, new_figure, save_figure
from .sweep import SweepResult
from .unicycle import UnicycleResult

UNICYCLE_FILES = ("fig7_trajectory.png", "fig8_heading.png", "fig9_heading_error.png")


PAPER_E_IMAGE = 1.4023e-6  # the value Fig. 4 of the paper shows for every orientation
PAPER_MAX_HEADING_ERROR_DEG = 0.043  # Fig. 9


def plot_sweep(result: SweepResult, path: str) -> Path:
    """Fig. 4: e_image of every orientation against its index, their distribution, and
    (when traced) the largest and mean e_image after each iteration."""
    by_iteration = result.by_iteration
    traced = by_iteration is not None
    fig, axes = new_figure(1, 3 if traced else 2, size_in=(16.0 if traced else 11.0, 4.4))
    ax, hist = axes[0], axes[1]
    e = result.e_image
    finite = np.isfinite(e) & (e > 0)
    # A floor keeps exact zeros on a log axis.
    shown = np.where(np.isfinite(e), np.maximum(e, 1e-17), np.nan)
    ax.plot(np.arange(e.size) / 1000.0, shown, ",", color="tab:blue", rasterized=True)
    ax.axhline(PAPER_E_IMAGE, color="tab:red", linestyle="--", label="paper (Fig. 4)")
    ax.set_yscale("log")
    ax.set_xlabel("orientation index / 1000 (alpha slowest, gamma fastest)")
    ax.set_ylabel("e_image (px, eq 17)")
    ax.set_title(f"e_image per orientation: {result.method}, {result.iterations} iterations")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(loc="center right")
    if finite.any():
        hist.hist(np.log10(e[finite]), bins=80, color="tab:blue")
    hist.axvline(np.log10(PAPER_E_IMAGE), color="tab:red", linestyle="--", label=f"paper: {PAPER_E_IMAGE:g}")
    hist.legend(loc="upper left")
    hist.set_xlabel("log10 e_image (px)")
    hist.set_ylabel("orientations")
    hist.set_title(f"{result.count:,} orientations, max {np.nanmax(e):.2e} px")
    if by_iteration is not None:
        conv = axes[2]
        its = np.arange(1, by_iteration.shape[0] + 1)
        conv.semilogy(its, by_iteration[:, 0], "o-", label="max")
        conv.semilogy(its, by_iteration[:, 1] / max(result.count, 1), "s--", label="mean")
        conv.axhline(PAPER_E_IMAGE, color="tab:red", linestyle="--", label="paper")
        conv.set_xlabel("iteration")
        conv.set_ylabel("e_image after the iteration (px)")
        conv.set_title("convergence over all orientations")
        conv.grid(True, which="major", alpha=0.3)
        conv.legend(loc="upper right")
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
    error = est.theta_est_deg - est.theta_deg
    ax.plot(est.t_s, error, "-", color="tab:red")
    ax.text(
        0.98,
        0.95,
        f"max |error| {np.max(np.abs(error)):.2e} deg\npaper: {PAPER_MAX_HEADING_ERROR_DEG} deg",
        transform=ax.transAxes,
        ha="right",
        va="top",
        bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "0.8"},
    )
    ax.set_xlabel("time (s)")
    ax.set_ylabel("heading error (deg)")
    ax.set_title(f"Fig. 9: error in the estimated heading ({s.method}{noise})")
    ax.grid(True, alpha=0.3)
    paths.append(save_figure(fig, out / UNICYCLE_FILES[2]))
    return paths
