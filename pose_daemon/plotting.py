"""Shared figure helpers: matplotlib imported only when a plot is asked for, always headless (Agg).

matplotlib is an optional extra (``pose-daemon[plot]``): nothing else in the package needs it,
so commands check for it (``require_matplotlib``) and the output path (``check_plot_path`` /
``check_plot_dir``) before any long computation, and fail with a one-line UserError.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Tuple, Union

from .errors import UserError

MISSING_MESSAGE = "plots need matplotlib: pip install 'pose-daemon[plot]'"

# Formats the Agg canvas writes; the file name's suffix picks one.
PLOT_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg")

PathLike = Union[str, "os.PathLike[str]"]


def require_matplotlib() -> Any:
    """Import matplotlib for headless use and return the module; UserError when it is missing.

    Figures are built with ``matplotlib.figure.Figure`` and an Agg canvas, never through
    pyplot's global state, so plotting works without a display and from any thread.
    """
    try:
        import matplotlib
        from matplotlib.backends import backend_agg  # noqa: F401  (fails early if broken)
    except ImportError as exc:
        raise UserError(MISSING_MESSAGE) from exc
    return matplotlib


def new_figure(
    nrows: int = 1, ncols: int = 1, *, size_in: Tuple[float, float] = (6.4, 4.8), dpi: float = 100.0, **subplot_kw: Any
) -> Tuple[Any, Any]:
    """A new figure on an Agg canvas and its axes (one Axes, or an array for a grid)."""
    require_matplotlib()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    # "constrained" keeps the labels of neighbouring panels apart (matplotlib >= 3.5).
    fig = Figure(figsize=size_in, dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=True, subplot_kw=subplot_kw or None)
    return fig, axes


def check_plot_path(path: PathLike) -> Path:
    """Validate a figure file name before the work that fills it: known suffix, existing folder."""
    p = Path(path)
    if p.suffix.lower() not in PLOT_SUFFIXES:
        raise UserError(f"plot file {str(p)!r} must end in one of {', '.join(PLOT_SUFFIXES)}")
    if p.is_dir():
        raise UserError(f"plot file {str(p)!r} is a directory")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise UserError(f"cannot write plot {str(p)!r}: directory {str(parent)!r} does not exist")
    if not os.access(parent, os.W_OK):
        raise UserError(f"cannot write plot {str(p)!r}: directory {str(parent)!r} is not writable")
    return p


def check_plot_dir(path: PathLike) -> Path:
    """Validate (and create if needed) a folder that will receive several figures."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise UserError(f"plot directory {str(p)!r} exists and is not a directory")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create plot directory {str(p)!r}: {exc.strerror or exc}") from exc
    if not os.access(p, os.W_OK):
        raise UserError(f"plot directory {str(p)!r} is not writable")
    return p


def save_figure(fig: Any, path: PathLike) -> Path:
    """Write ``fig`` to ``path`` (format from the suffix) and release it; UserError on failure."""
    p = check_plot_path(path)
    try:
        fig.savefig(str(p), bbox_inches="tight")
    except OSError as exc:
        raise UserError(f"cannot write plot {str(p)!r}: {exc.strerror or exc}") from exc
    finally:
        fig.clear()
    return p
