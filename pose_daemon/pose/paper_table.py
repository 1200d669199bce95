"""The paper's e_beta -> beta and e_alpha -> alpha cubics, with coefficients depending on depth.

Built by simulation as the paper describes (its Fig. 1): a square on the optical axis, seen by
a camera turned by a pure yaw (pitch), gives e_beta (e_alpha) for each angle; a cubic
a e^3 + b e^2 + c e + d is fitted at each depth. Depth is the dimensionless
z_rel = z / sqrt(W*H) (z a length, from eq. 1; equivalently z / (f sqrt(W*H)) with z in image
units): image angles do not depend on f, so one table holds for every camera and marker size.
A W x H rectangle looks yaw up at z / H and pitch at z / W (see loop.py).
``scripts/make_paper_table.py`` writes the shipped table ``pose_daemon/data/paper_table.json``
with ``pose_daemon.paper.table_build.build_table``; this module only looks it up.
"""

from __future__ import annotations

import bisect
import json
import math
from importlib import resources
from typing import Any, Dict, Optional, Union, overload

import numpy as np

TABLE_FILE = "paper_table.json"
# Corrections are clamped to this: beyond it the marker is seen edge-on.
STEP_LIMIT_RAD = math.radians(80.0)


class PaperTable:
    """Looks up the cubic for a depth (linear interpolation in log z_rel) and evaluates it."""

    def __init__(self, data: Dict[str, object]) -> None:
        z_rel = np.asarray(data["z_rel"], dtype=np.float64)
        self._log_z = np.log(z_rel)
        self._norm: Dict[str, np.ndarray] = {}
        self._u_max: Dict[str, np.ndarray] = {}
        for name in ("beta", "alpha"):
            c = np.asarray(data[name], dtype=np.float64)  # (n, 4): a, b, c, d
            # Coefficients of the cubic in u = e * z_rel: nearly constant in depth, so they
            # interpolate well and extend beyond the grid (weak perspective: e ~ 1 / z_rel).
            powers = np.stack([z_rel**-3, z_rel**-2, z_rel**-1, np.ones_like(z_rel)], -1)
            self._norm[name] = c * powers
            # Limit of |u| = |e| z_rel that the fit covered, per depth.
            self._u_max[name] = np.asarray(data[name + "_e_max"], dtype=np.float64) * z_rel
        self._log_z_list = self._log_z.tolist()
        self._norm_list = {k: v.tolist() for k, v in self._norm.items()}
        self._u_max_list = {k: v.tolist() for k, v in self._u_max.items()}

    def _evaluate(self, name: str, e: Union[float, np.ndarray], z_rel: Any) -> Union[float, np.ndarray]:
        if isinstance(e, float):
            return self._evaluate_float(name, e, float(z_rel))
        table = self._norm[name]
        lz = np.log(np.clip(z_rel, 1e-6, None))
        u_max = np.interp(lz, self._log_z, self._u_max[name])
        u = np.clip(np.asarray(e) * z_rel, -u_max, u_max)
        out = np.zeros(np.broadcast(u, lz).shape)
        for k in range(4):
            coeff = np.interp(lz, self._log_z, table[:, k])
            out = out * u + coeff
        return np.clip(out, -STEP_LIMIT_RAD, STEP_LIMIT_RAD)

    def _evaluate_float(self, name: str, e: float, z_rel: float) -> float:
        # The per-frame path: plain floats, no numpy call overhead.
        lz = math.log(max(z_rel, 1e-6))
        grid = self._log_z_list
        rows = self._norm_list[name]
        k = bisect.bisect_right(grid, lz)
        u_max = self._u_max_list[name]
        if k <= 0:
            coeffs, um = rows[0], u_max[0]
        elif k >= len(grid):
            coeffs, um = rows[-1], u_max[-1]
        else:
            w = (lz - grid[k - 1]) / (grid[k] - grid[k - 1])
            lo, hi = rows[k - 1], rows[k]
            coeffs = [lo[j] + w * (hi[j] - lo[j]) for j in range(4)]
            um = u_max[k - 1] + w * (u_max[k] - u_max[k - 1])
        u = min(max(e * z_rel, -um), um)
        out = ((coeffs[0] * u + coeffs[1]) * u + coeffs[2]) * u + coeffs[3]
        return min(max(out, -STEP_LIMIT_RAD), STEP_LIMIT_RAD)

    # Plain floats in, a float out (the per-frame path); arrays in, an array out.
    @overload
    def yaw(self, e_beta_rad: float, z_rel: float) -> float: ...
    @overload
    def yaw(self, e_beta_rad: np.ndarray, z_rel: Union[float, np.ndarray]) -> np.ndarray: ...

    def yaw(self, e_beta_rad: Any, z_rel: Any) -> Any:
        """beta (radians) from e_beta (radians) at depth z_rel = z / sqrt(W*H)."""
        return self._evaluate("beta", e_beta_rad, z_rel)

    @overload
    def pitch(self, e_alpha_rad: float, z_rel: float) -> float: ...
    @overload
    def pitch(self, e_alpha_rad: np.ndarray, z_rel: Union[float, np.ndarray]) -> np.ndarray: ...

    def pitch(self, e_alpha_rad: Any, z_rel: Any) -> Any:
        """alpha (radians) from e_alpha (radians) at depth z_rel."""
        return self._evaluate("alpha", e_alpha_rad, z_rel)


_TABLE: Optional[PaperTable] = None


def load_table() -> PaperTable:
    """The shipped table, read once."""
    global _TABLE
    if _TABLE is None:
        text = resources.files("pose_daemon").joinpath("data").joinpath(TABLE_FILE).read_text("utf-8")
        _TABLE = PaperTable(json.loads(text))
    return _TABLE
