"""The paper's Fig. 1 simulation: builds the e_beta -> beta and e_alpha -> alpha cubics that
``pose/paper_table.py`` looks up (the shipped ``pose_daemon/data/paper_table.json``, written by
``scripts/make_paper_table.py``).

A square on the optical axis, seen by a camera turned by a pure yaw (pitch), gives e_beta
(e_alpha) for each angle; a cubic a e^3 + b e^2 + c e + d is fitted at each depth
z_rel = z / sqrt(W*H).
"""

from __future__ import annotations

from typing import Dict

import numpy as np

from .. import geometry
from ..pose.loop import e_alpha, e_beta, internal_angles, project_unrot

# Depth grid (z_rel) and angle range of the simulation.
Z_REL_MIN, Z_REL_MAX, Z_REL_COUNT = 1.0, 500.0, 80
ANGLE_MAX_DEG, ANGLE_COUNT = 60.0, 241


def build_table() -> Dict[str, object]:
    """Simulate and fit; returns the JSON-ready table (coefficients a, b, c, d per z_rel)."""
    z_rel = np.geomspace(Z_REL_MIN, Z_REL_MAX, Z_REL_COUNT)
    angles = np.radians(np.linspace(-ANGLE_MAX_DEG, ANGLE_MAX_DEG, ANGLE_COUNT))
    out: Dict[str, object] = {
        "description": "cubic angle = a e^3 + b e^2 + c e + d (radians) per z_rel = z / sqrt(W*H); "
        "simulated square on the optical axis, pure yaw (beta) or pitch (alpha)",
        "angle_max_deg": ANGLE_MAX_DEG,
        "z_rel": [float(v) for v in z_rel],
    }
    for name, rot, err in (("beta", geometry.rot_y, e_beta), ("alpha", geometry.rot_x, e_alpha)):
        coeffs, e_max = [], []
        for zr in z_rel:
            R = rot(angles)
            pos = np.broadcast_to(np.array([0.0, 0.0, zr]), angles.shape + (3,))
            img = project_unrot(R, pos, 1.0, 1.0, 1.0)
            e = err(internal_angles(img))
            # Fit in u = e * z_rel (well scaled at every depth), convert back to e.
            A, B, C, D = np.polyfit(e * zr, angles, 3)
            coeffs.append([float(A * zr**3), float(B * zr**2), float(C * zr), float(D)])
            e_max.append(float(np.abs(e).max()))
        out[name] = coeffs
        # The fit's range of |e|: a cubic must not be extrapolated beyond it.
        out[name + "_e_max"] = e_max
    return out
