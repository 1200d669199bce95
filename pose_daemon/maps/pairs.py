"""Map build, stage 2: each marker's own pose in each frame and, for every two markers seen in
one frame, their relative pose; across frames the relative pose most frames agree on.

OpenCV's IPPE for squares gives both planar solutions of each marker (a start for the joint
solve, where the daemon's own estimator would dominate the build time), so two markers in one
frame give up to four candidates; the candidate most frames agree on wins (maps/build.py).
"""

from __future__ import annotations

import math
from typing import Dict, List, Optional, Tuple

import numpy as np

from ..camera import Camera
from ..geometry import R_from_rvec

__all__ = ["AGREE_DEG", "AGREE_M", "AGREE_FRAC", "PAIR_FRAMES", "local_corners", "single_poses", "relative_poses"]

#: Relative poses from two frames agree within this rotation (deg) and this position
#: (metres, plus this fraction of the distance between the markers).
AGREE_DEG = 10.0
AGREE_M, AGREE_FRAC = 0.05, 0.10
#: Frames per marker pair used for the consensus (evenly spaced when there are more).
PAIR_FRAMES = 40


def _orthonormal(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R


def local_corners(size_m: float) -> np.ndarray:
    h = size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def single_poses(
    observed: Dict[int, np.ndarray], camera: Camera, sizes: Dict[int, float]
) -> Dict[int, List[Tuple[np.ndarray, np.ndarray, float]]]:
    """Both planar solutions of each marker's own pose: id -> [(R_cam_marker, t, rms px)].

    OpenCV's IPPE for squares (both solutions, through the lens): a start for the solve, where
    the daemon's own estimator (a few ms a call in Python) would dominate the build time.
    """
    import cv2

    out: Dict[int, List[Tuple[np.ndarray, np.ndarray, float]]] = {}
    for marker_id, corners in observed.items():
        obj = local_corners(sizes[marker_id])
        try:
            n, rvecs, tvecs, errs = cv2.solvePnPGeneric(
                obj, corners.reshape(4, 1, 2), camera._K, camera._dist, flags=cv2.SOLVEPNP_IPPE_SQUARE
            )
        except cv2.error:
            continue
        cands = []
        for k in range(int(n)):
            R = R_from_rvec(np.asarray(rvecs[k], dtype=np.float64).reshape(3))
            t = np.asarray(tvecs[k], dtype=np.float64).reshape(3)
            err = float(np.asarray(errs).ravel()[k]) if errs is not None else 0.0
            if np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and t[2] > 0:
                cands.append((R, t, err))
        if cands:
            out[marker_id] = cands
    return out


def pair_consensus(
    per_frame: List[List[Tuple[np.ndarray, np.ndarray, float]]], prefer_plane: bool
) -> Optional[Tuple[np.ndarray, np.ndarray, int]]:
    """The relative pose most frames agree on, averaged over them: (R_a_b, t_a_b, support).

    Two candidates agree within AGREE_DEG and AGREE_M + AGREE_FRAC x distance. With
    ``prefer_plane``, of the candidates nearly as well supported as the best (a pair seen only
    from one side keeps both planar solutions consistent), the least tilted one wins.
    """
    if len(per_frame) > PAIR_FRAMES:
        pick = np.linspace(0, len(per_frame) - 1, PAIR_FRAMES).round().astype(int)
        per_frame = [per_frame[i] for i in pick]
    frame_of = np.array([f for f, cands in enumerate(per_frame) for _ in cands], dtype=np.int64)
    if not len(frame_of):
        return None
    R = np.array([c[0] for cands in per_frame for c in cands])
    t = np.array([c[1] for cands in per_frame for c in cands])
    err = np.array([c[2] for cands in per_frame for c in cands])
    cos = np.clip((np.einsum("aij,bij->ab", R, R) - 1.0) / 2.0, -1.0, 1.0)
    dist = np.linalg.norm(t[:, None, :] - t[None, :, :], axis=2)
    tol = AGREE_M + AGREE_FRAC * np.linalg.norm(t, axis=1)
    agree = (cos >= math.cos(math.radians(AGREE_DEG))) & (dist <= tol[:, None])
    n_frames = len(per_frame)
    by_frame = np.zeros((len(R), n_frames), dtype=bool)
    for f in range(n_frames):
        by_frame[:, f] = agree[:, frame_of == f].any(axis=1)
    support = by_frame.sum(axis=1)
    tilt = np.degrees(np.arccos(np.clip(R[:, 2, 2], -1.0, 1.0)))
    if prefer_plane:
        near = support >= max(int(support.max()) - 1, int(math.ceil(0.8 * support.max())))
        score = np.where(near, -tilt, -np.inf)
        best = int(np.lexsort((-err, score))[-1])
    else:
        best = int(np.lexsort((-err, support))[-1])
    members = []
    for f in range(n_frames):
        idx = np.flatnonzero(agree[best] & (frame_of == f))
        if len(idx):
            members.append(int(idx[np.argmin(dist[best, idx])]))
    R_mean = _orthonormal(R[members].sum(axis=0))
    t_mean = t[members].mean(axis=0)
    return R_mean, t_mean, len(members)


def relative_poses(
    singles: List[Dict[int, List[Tuple[np.ndarray, np.ndarray, float]]]], prefer_plane: bool = False
) -> Dict[Tuple[int, int], Tuple[np.ndarray, np.ndarray, int]]:
    """(a, b) with a < b -> (R_a_b, t_a_b, frames that agree): X_a = R_a_b X_b + t_a_b."""
    pairs: Dict[Tuple[int, int], List[List[Tuple[np.ndarray, np.ndarray, float]]]] = {}
    for poses in singles:
        ids = sorted(poses)
        for i, a in enumerate(ids):
            for b in ids[i + 1 :]:
                cands = []
                for Ra, ta, ea in poses[a]:
                    for Rb, tb, eb in poses[b]:
                        cands.append((Ra.T @ Rb, Ra.T @ (tb - ta), ea + eb))
                pairs.setdefault((a, b), []).append(cands)
    out = {}
    for key, per_frame in pairs.items():
        found = pair_consensus(per_frame, prefer_plane)
        if found is not None:
            out[key] = found
    return out
