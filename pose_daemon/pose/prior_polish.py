"""The chosen pose re-fitted with priors: its corners and direction terms (the attitude's down,
a known heading) in one least-squares cost, the poorly seen part of the pose moving most."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import cv2
import numpy as np

from ..camera import Camera, Marker
from ..geometry import paper_angles_deg_from_R_cam_marker
from .types import Pose


@dataclass(frozen=True)
class HeadingTerm:
    """A prior term on the vehicle's heading for ``polish_toward``: the body's x axis in the
    local frame (``R_local_marker R^T forward_cam``, ``forward_cam`` the body's x axis in the
    camera frame) turned about the vertical to ``yaw_rad``, weighed ``weight_px`` per radian."""

    R_local_marker: np.ndarray
    forward_cam: np.ndarray
    yaw_rad: float
    weight_px: float


def polish_toward_down(
    pose: Pose,
    corners_px: np.ndarray,
    camera: Camera,
    marker: Marker,
    down_m: np.ndarray,
    down_cam: np.ndarray,
    weight_px: float,
    iterations: int = 3,
) -> Tuple[Pose, float]:
    """``pose`` re-fitted to its corners with a prior term pulling the down direction it
    implies (``R @ down_m``, ``down_m`` = down in the marker frame) towards ``down_cam``.

    Minimises sum |reprojection|^2 + weight_px^2 |R down_m - down_cam|^2 (Gauss-Newton on
    rvec, tvec; OpenCV's projection Jacobian through the distortion). ``weight_px`` = corner
    noise / the down direction's accuracy (radians): the two terms in the same units.
    Like PhotonVision's constrained solver and Limelight's MegaTag2, only the poorly seen
    part of the pose (the marker's tilt) moves. Returns the pose (its reprojection RMS
    recomputed) and the final cost in px^2."""
    return polish_toward(pose, corners_px, camera, marker, [(down_m, down_cam, weight_px)], iterations)


def polish_toward(
    pose: Pose,
    corners_px: np.ndarray,
    camera: Camera,
    marker: Marker,
    terms: Sequence[Tuple[np.ndarray, np.ndarray, float]],
    iterations: int = 3,
    heading: Optional[HeadingTerm] = None,
) -> Tuple[Pose, float]:
    """``polish_toward_down`` with any number of direction terms (dir in the marker frame,
    wanted dir in the camera frame, weight px): down, and the heading once it is known;
    ``heading`` adds a term on the vehicle's heading itself (``HeadingTerm``)."""
    obj = marker.object_points.astype(np.float64)
    uv = np.asarray(corners_px, dtype=np.float64).reshape(-1)
    rvec = np.asarray(pose.rvec, dtype=np.float64).reshape(3).copy()
    tvec = np.asarray(pose.tvec, dtype=np.float64).reshape(3).copy()
    terms = [(np.asarray(d_m, dtype=np.float64), np.asarray(d_c, dtype=np.float64), float(w)) for d_m, d_c, w in terms]

    def residual(rv: np.ndarray, tv: np.ndarray):
        img, J = cv2.projectPoints(obj, rv, tv, camera.K, camera.dist_coeffs)
        R, dR = cv2.Rodrigues(rv)
        rs, Js = [img.reshape(-1) - uv], [J[:, :6]]
        for d_m, d_c, w in terms:
            rs.append(w * (R @ d_m - d_c))
            J_dir = np.zeros((3, 6))
            # dR is (3, 9): d R.flat / d rvec_k, row-major R.
            J_dir[:, :3] = w * (dR.reshape(3, 3, 3) @ d_m).T
            Js.append(J_dir)
        if heading is not None:
            # yaw = atan2(v_y, v_x) of v = R_local_marker R^T forward_cam (the body's x axis in
            # the local frame); d v / d rvec_k = R_local_marker dR_k^T forward_cam.
            v = heading.R_local_marker @ (R.T @ heading.forward_cam)
            dv = heading.R_local_marker @ np.einsum("kij,i->jk", dR.reshape(3, 3, 3), heading.forward_cam)
            h2 = max(float(v[0] ** 2 + v[1] ** 2), 1e-12)
            turn = math.remainder(math.atan2(v[1], v[0]) - heading.yaw_rad, math.tau)
            rs.append(np.array([heading.weight_px * turn]))
            J_head = np.zeros((1, 6))
            J_head[0, :3] = heading.weight_px * (v[0] * dv[1] - v[1] * dv[0]) / h2
            Js.append(J_head)
        return np.concatenate(rs), np.vstack(Js)

    r, J = residual(rvec, tvec)
    cost = float(r @ r)
    lam = 1e-4
    eye = np.eye(6)
    for _ in range(iterations):
        H = J.T @ J
        g = J.T @ r
        ok, step = cv2.solve(H + lam * (eye * np.diag(H) + 1e-12 * eye), -g.reshape(6, 1))
        if not ok:
            break
        step = step.reshape(6)
        rv_new, tv_new = rvec + step[:3], tvec + step[3:]
        if tv_new[2] <= 0:
            lam *= 10.0
            continue
        r_new, J_new = residual(rv_new, tv_new)
        cost_new = float(r_new @ r_new)
        if cost_new < cost:
            converged = cost - cost_new < 1e-6 * cost + 1e-9
            rvec, tvec, r, J, cost = rv_new, tv_new, r_new, J_new, cost_new
            lam = max(lam / 10.0, 1e-9)
            if converged:
                break
        else:
            lam *= 10.0
    R = cv2.Rodrigues(rvec)[0]
    rms = float(np.sqrt(np.mean(np.sum(r[:8].reshape(4, 2) ** 2, axis=1))))
    a, b, c = paper_angles_deg_from_R_cam_marker(R)
    polished = dataclasses.replace(
        pose, rvec=rvec, tvec=tvec, R=R, alpha_deg=a, beta_deg=b, gamma_deg=c, reprojection_error_px=rms
    )
    return polished, cost
