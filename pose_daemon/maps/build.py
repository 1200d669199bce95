"""Surveying a marker map from a walk-through: every marker's pose in one map frame.

1. Observations: per frame, the corners of every marker found ({id: (4, 2) pixels}; the
   caller detects them, maps/survey.py with detect/multi.MapDetector); a marker with a
   corner outside the frame (extrapolated by the detector, not measured) is left out.
2. Pairwise relative poses: each marker's own pose in each frame (OpenCV's IPPE for squares,
   both planar solutions kept), T_a_b for every two markers seen in one frame (up to four
   candidates), and across frames the candidate most frames agree on (maps/pairs.py).
3. A graph over markers: a maximum spanning tree (edge weight: frames that agree) from the
   anchor puts every connected marker in the map frame; each frame's camera pose starts from
   the marker pose that fits all its markers best, then all cameras are refined at once with
   the markers held (a damped Gauss-Newton per camera, vectorised over the cameras)
   (maps/tree.py; the refinement in maps/joint.py).
4. One joint robust least squares of all marker poses (the anchor held at its pose: the map
   frame) and all camera poses over every corner observation: Levenberg-Marquardt, Huber loss
   in pixels (iteratively reweighted), the Jacobian analytic, each step's normal equations
   solved exactly with every camera's 6 x 6 block eliminated (a Schur complement: a dense
   system in the marker parameters only, filled by the markers seen together; maps/joint.py).
   With ``plane`` the markers are solved in the anchor's plane first (position x, y and a turn
   about z each, from the tree's map laid flat: a chain of markers bends out of the plane in a
   free solve that is slow to straighten), then freed as the yardstick: the plane is kept when the
   residuals allow it (no marker's residual grows by much), else the free solve goes on to
   convergence.
5. Observations that stay far off under the free solve are left out and both solves repeated.
6. Uncertainty: the marker block of s^2 (J^T W J)^-1 (the camera blocks eliminated likewise),
   s^2 the residual variance.

This module runs the stages in order and keeps what the report needs (``MapBuild``). scipy
(its sparse matrices sum the joint solve's blocks) is an off-vehicle extra
(``pose-daemon[map]``), imported only by maps/joint.py and checked here by ``require_scipy``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..camera import Camera
from ..errors import UserError
from ..geometry import euler_rpy_from_R, rot_z
from ..marker_map import MapMarker, MarkerMap
from .joint import SOLVE_ITERATIONS, Problem, Solved, levenberg_marquardt, marker_covariance
from .pairs import local_corners, relative_poses, single_poses
from .tree import camera_start, spanning_tree

__all__ = [
    "MISSING_SCIPY",
    "require_scipy",
    "PlacedMarker",
    "MapBuild",
    "build_map",
]

MISSING_SCIPY = "map build needs scipy: pip install 'pose-daemon[map]'"

#: A marker must be seen in at least this many frames to be placed.
MIN_VIEWS = 5
#: Evaluations of the free solve that only checks whether the plane holds.
FREE_CHECK_ITERATIONS = 15
#: An observation (one marker in one frame) whose RMS corner residual after the first solve is
#: over this (pixels) and several times the median is left out.
OUTLIER_PX = 3.0
#: The plane is kept when no marker's RMS residual grows by more than this factor + this many
#: pixels, and the whole solve's by no more than PLANE_TOTAL.
PLANE_MARKER_FACTOR, PLANE_MARKER_PX, PLANE_TOTAL = 1.3, 0.05, 1.1


def require_scipy() -> Any:
    """scipy (with scipy.sparse), or a UserError naming the missing extra."""
    try:
        import scipy.sparse
    except ImportError as exc:
        raise UserError(MISSING_SCIPY) from exc
    return scipy


@dataclass(frozen=True)
class PlacedMarker:
    """One surveyed marker: its pose in the map frame, the frames that saw it (in the solve),
    its RMS corner residual and its standard deviations from the solve (position: the root of
    the trace, metres; rotation: likewise, degrees)."""

    id: int
    size_m: float
    position_m: Tuple[float, float, float]
    R_map_marker: np.ndarray
    views: int
    rms_px: float
    position_std_m: float
    rotation_std_deg: float

    @property
    def rotation_deg(self) -> Tuple[float, float, float]:
        r, p, y = euler_rpy_from_R(self.R_map_marker)
        return (math.degrees(float(r)), math.degrees(float(p)), math.degrees(float(y)))

    def map_marker(self) -> MapMarker:
        return MapMarker(self.id, self.size_m, self.position_m, self.rotation_deg)


@dataclass
class MapBuild:
    """What ``build_map`` found: the map, and the figures its report gives."""

    marker_map: MarkerMap
    anchor: int
    placed: List[PlacedMarker]
    #: id -> why it was not placed
    unplaced: Dict[int, str]
    rms_px: float
    frames_total: int
    frames_used: int
    #: reason -> frame labels left out for it
    frames_left_out: Dict[str, List[str]]
    #: "kept", or why the markers were left free of the plane
    plane: str
    #: camera centre in the map frame (n, 3) of every frame in the solve, in frame order
    camera_path_m: np.ndarray
    #: seconds per stage: "pairs", "graph", "solve", "covariance"
    stage_s: Dict[str, float] = field(default_factory=dict)
    observations_used: int = 0
    #: per solve in order: (in one plane, steps, residual evaluations)
    solves: List[Tuple[bool, int, int]] = field(default_factory=list)


def build_map(
    observations: Sequence[Dict[int, np.ndarray]],
    camera: Camera,
    dictionary: str,
    sizes: Dict[int, float],
    *,
    default_size_m: float,
    anchor: Optional[int] = None,
    placement: str = "floor",
    plane: bool = True,
    labels: Optional[Sequence[str]] = None,
    max_frames: int = 600,
    min_views: int = MIN_VIEWS,
) -> MapBuild:
    """Every marker's pose in the anchor's frame from per-frame corners (see the module).

    ``observations``: one {id: (4, 2) pixels TL, TR, BR, BL} per frame, in frame order;
    ``sizes``: the markers whose size is not ``default_size_m``; ``anchor``: the marker whose
    frame is the map frame (default: the lowest id that can be placed); ``labels``: one name
    per frame for the report; ``max_frames``: frames in the joint solve at most (evenly
    spaced over those that see two or more placed markers). UserError when nothing can be
    placed or the anchor cannot be.
    """
    require_scipy()

    stage: Dict[str, float] = {}
    t0 = time.perf_counter()
    n_frames = len(observations)
    labels = list(labels) if labels is not None else [f"frame {i}" for i in range(n_frames)]
    obs = [{int(i): np.asarray(c, dtype=np.float64).reshape(4, 2) for i, c in o.items()} for o in observations]
    # A marker partly out of the frame: the detector extrapolates the corners it cannot see
    # (detect/multi), which are no measurement; such an observation is left out whole.
    frame_max = np.array([camera.width - 1.0, camera.height - 1.0])
    obs = [{i: c for i, c in o.items() if bool(np.all((c >= 0.0) & (c <= frame_max)))} for o in obs]

    def size_of(i: int) -> float:
        return float(sizes.get(i, default_size_m))

    all_sizes = {i: size_of(i) for o in obs for i in o}
    views: Dict[int, int] = {}
    for o in obs:
        for i in o:
            views[i] = views.get(i, 0) + 1
    if not views:
        raise UserError("no marker of the dictionary was found in any frame")
    unplaced: Dict[int, str] = {}
    for i, n in sorted(views.items()):
        if n < min_views:
            unplaced[i] = f"seen in {n} frame{'s' if n != 1 else ''} (needs {min_views})"
    candidates = sorted(i for i in views if i not in unplaced)
    if anchor is not None:
        if anchor not in views:
            raise UserError(f"anchor marker {anchor} was not seen in any frame (seen: {_id_list(sorted(views))})")
        if anchor in unplaced:
            raise UserError(f"anchor marker {anchor} was {unplaced[anchor]}: choose another --anchor")
    if not candidates:
        raise UserError(f"no marker was seen in {min_views} frames or more: " + _reasons(unplaced))
    # Frames with one candidate marker join nothing: no single poses for them.
    singles = [
        single_poses({i: c for i, c in o.items() if i in candidates}, camera, all_sizes)
        if sum(1 for i in o if i in candidates) >= 2
        else {}
        for o in obs
    ]
    relative = relative_poses(singles, plane)
    stage["pairs"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    # The anchor: as asked, else the lowest id whose tree reaches the most markers.
    if anchor is None:
        best_tree: Optional[Dict[int, Tuple[np.ndarray, np.ndarray]]] = None
        for i in candidates:
            tree = spanning_tree(i, relative, candidates)
            if best_tree is None or len(tree) > len(best_tree):
                best_tree, anchor = tree, i
            if len(tree) == len(candidates):
                break
        assert best_tree is not None and anchor is not None
        tree = best_tree
    else:
        tree = spanning_tree(anchor, relative, candidates)
    for i in candidates:
        if i not in tree:
            partners = sorted({b if a == i else a for (a, b), v in relative.items() if i in (a, b)})
            if any(p in tree for p in partners):
                unplaced[i] = "seen with placed markers, but too few frames agree on where it is"
            else:
                unplaced[i] = "never seen in one frame together with a placed marker"
    if len(tree) < 1:
        raise UserError("no marker could be placed")
    marker_ids = sorted(tree)
    index = {m: k for k, m in enumerate(marker_ids)}
    R0 = np.array([tree[m][0] for m in marker_ids])
    p0 = np.array([tree[m][1] for m in marker_ids])

    # Frames: those that see two or more placed markers, evenly thinned to max_frames.
    left_out: Dict[str, List[str]] = {}
    eligible = []
    for f, o in enumerate(obs):
        n = sum(1 for i in o if i in tree)
        if n >= 2:
            eligible.append(f)
        else:
            why = "no placed marker in view" if n == 0 else "only one placed marker in view"
            left_out.setdefault(why, []).append(labels[f])
    if len(eligible) > max_frames:
        pick = set(np.linspace(0, len(eligible) - 1, max_frames).round().astype(int).tolist())
        thinned = [f for k, f in enumerate(eligible) if k not in pick]
        eligible = [f for k, f in enumerate(eligible) if k in pick]
        left_out[f"thinned to {max_frames} frames for the solve"] = [labels[f] for f in thinned]
    if not eligible and len(marker_ids) > 1:
        raise UserError("no frame sees two placed markers: nothing joins them")
    cams = []
    Rc0_list, tc0_list = [], []
    markers_T = {m: tree[m] for m in marker_ids}
    for f in eligible:
        start = camera_start(camera, obs[f], singles[f], markers_T, all_sizes)
        if start is None:
            left_out.setdefault("no camera pose from its markers", []).append(labels[f])
            continue
        cams.append(f)
        Rc0_list.append(start[0])
        tc0_list.append(start[1])
    stage["graph"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    Rc0 = np.array(Rc0_list).reshape(-1, 3, 3)
    tc0 = np.array(tc0_list).reshape(-1, 3)
    obs_cam_l, obs_marker_l, obs_img_l, local_l, obs_frame_l = [], [], [], [], []
    for k, f in enumerate(cams):
        for i in sorted(obs[f]):
            if i in index:
                obs_cam_l.append(k)
                obs_marker_l.append(index[i])
                obs_img_l.append(obs[f][i])
                local_l.append(local_corners(all_sizes[i]))
                obs_frame_l.append(f)
    keep_obs = np.ones(len(obs_cam_l), dtype=bool)
    obs_cam = np.array(obs_cam_l, dtype=np.int64)
    obs_marker = np.array(obs_marker_l, dtype=np.int64)
    obs_img = np.array(obs_img_l).reshape(-1, 4, 2)
    local = np.array(local_l).reshape(-1, 4, 3)
    obs_frame = np.array(obs_frame_l, dtype=np.int64)
    anchor_index = index[anchor]
    solve_log: List[Tuple[bool, int, int]] = []
    # All observations, every marker free: the cameras' refinement on a start, the outliers.
    full = Problem(camera, obs_cam, obs_marker, obs_img, local, anchor_index, len(marker_ids), len(cams), False)
    Rc0, tc0 = full.refine_cameras(R0, p0, Rc0, tc0)

    def run(planar: bool, Rm0, pm0, Rcs, tcs, mask, max_iterations=SOLVE_ITERATIONS) -> Solved:
        """One solve from (markers, cameras) over the observations in ``mask``."""
        prob = Problem(
            camera,
            obs_cam[mask],
            obs_marker[mask],
            obs_img[mask],
            local[mask],
            anchor_index,
            len(marker_ids),
            len(cams),
            planar,
        )
        solved = levenberg_marquardt(prob, Rm0, pm0, Rcs, tcs, max_iterations)
        solve_log.append((planar, solved.iterations, solved.evaluations))
        return solved

    def marker_rms(state: Solved):
        prob_ = state.prob
        r = prob_.residuals(state.Rm, state.pm, state.Rc, state.tc)
        d2 = np.sum(r**2, axis=2).mean(axis=1)
        per = np.array(
            [
                math.sqrt(float(d2[prob_.obs_marker == m].mean())) if np.any(prob_.obs_marker == m) else 0.0
                for m in range(len(marker_ids))
            ]
        )
        return per, math.sqrt(float(d2.mean())) if len(d2) else 0.0

    def poses(state: Solved) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return state.Rm, state.pm, state.Rc, state.tc

    def both(start_planar, free_from_planar, mask):
        """(planar state or None, free state)."""
        planar_state = None
        if start_planar is not None:
            planar_state = run(True, *start_planar, mask)
            # Only the yardstick of the plane (continued below if the plane is not kept).
            free_state = run(False, *poses(planar_state), mask, FREE_CHECK_ITERATIONS)
        else:
            free_state = run(False, *free_from_planar, mask)
        return planar_state, free_state

    use_plane = plane and len(marker_ids) > 1
    planar_start = None
    if use_plane:
        # The plane first, from the tree's map laid flat (a chain of markers bends out of the
        # plane in a free solve that is slow to straighten), with camera starts on that map.
        yaw = np.arctan2(R0[:, 1, 0], R0[:, 0, 0])
        Rp0 = np.array([rot_z(float(v)) for v in yaw])
        pp0 = p0.copy()
        pp0[:, 2] = 0.0
        Rp0[anchor_index], pp0[anchor_index] = np.eye(3), 0.0
        flat = {m: (Rp0[k], pp0[k]) for k, m in enumerate(marker_ids)}
        Rcp, tcp = Rc0.copy(), tc0.copy()
        for k, f in enumerate(cams):
            start = camera_start(camera, obs[f], singles[f], flat, all_sizes)
            if start is not None:
                Rcp[k], tcp[k] = start[0], start[1]
        Rcp, tcp = full.refine_cameras(Rp0, pp0, Rcp, tcp)
        planar_start = (Rp0, pp0, Rcp, tcp)
    planar_state, free_state = both(planar_start, (R0, p0, Rc0, tc0), keep_obs)
    # Outliers by the free solve (the plane might not hold), then both again without them.
    Rm, pm, Rc, tc = poses(free_state)
    per_obs = np.sqrt(np.mean(np.sum(full.residuals(Rm, pm, Rc, tc) ** 2, axis=2), axis=1))
    limit = max(OUTLIER_PX, 5.0 * float(np.median(per_obs))) if len(per_obs) else OUTLIER_PX
    keep_obs = per_obs <= limit
    if (~keep_obs).any():
        for f in sorted(set(obs_frame[~keep_obs].tolist())):
            left_out.setdefault(
                f"a marker's corners off by more than {limit:.1f} px (that marker left out)", []
            ).append(labels[f])
        planar_state, free_state = both(
            poses(planar_state) if planar_state is not None else None, poses(free_state), keep_obs
        )
    free_per, free_rms = marker_rms(free_state)
    plane_note = "not asked"
    chosen = free_state
    if planar_state is not None:
        plane_per, plane_rms = marker_rms(planar_state)
        worst = int(np.argmax(plane_per - (PLANE_MARKER_FACTOR * free_per + PLANE_MARKER_PX)))
        fits = bool(np.all(plane_per <= PLANE_MARKER_FACTOR * free_per + PLANE_MARKER_PX)) and (
            plane_rms <= PLANE_TOTAL * free_rms + 0.02
        )
        if fits:
            plane_note = "kept"
            chosen = planar_state
        else:
            plane_note = (
                f"not kept: in one plane marker {marker_ids[worst]}'s residual grows from "
                f"{free_per[worst]:.2f} to {plane_per[worst]:.2f} px (RMS {free_rms:.2f} -> {plane_rms:.2f} px)"
            )
            Rm_f, pm_f, Rc_f, tc_f = poses(free_state)
            chosen = run(False, Rm_f, pm_f, Rc_f, tc_f, keep_obs)
    prob = chosen.prob
    Rm, pm, Rc, tc = poses(chosen)
    per_marker, rms = marker_rms(chosen)
    stage["solve"] = time.perf_counter() - t2

    t3 = time.perf_counter()
    n_res = 8 * len(prob.obs_cam)
    stds = np.zeros((len(marker_ids), 2))
    if prob.n_marker_params and n_res:
        dof = max(n_res - prob.n_params, 1)
        s2 = max(2.0 * float(chosen.cost) / dof, 1e-12)
        cov = marker_covariance(chosen, s2)
        for m in range(len(marker_ids)):
            c = prob.marker_col[m]
            if c < 0:
                continue
            block = cov[c : c + prob.mp, c : c + prob.mp]
            if prob.planar:
                stds[m] = (
                    math.sqrt(max(block[0, 0] + block[1, 1], 0.0)),
                    math.degrees(math.sqrt(max(block[2, 2], 0.0))),
                )
            else:
                stds[m] = (
                    math.sqrt(max(float(np.trace(block[3:, 3:])), 0.0)),
                    math.degrees(math.sqrt(max(float(np.trace(block[:3, :3])), 0.0))),
                )
    stage["covariance"] = time.perf_counter() - t3

    views_used = np.bincount(prob.obs_marker, minlength=len(marker_ids))
    placed = [
        PlacedMarker(
            id=m,
            size_m=all_sizes[m],
            position_m=(float(pm[k][0]), float(pm[k][1]), float(pm[k][2])),
            R_map_marker=Rm[k],
            views=int(views_used[k]),
            rms_px=float(per_marker[k]),
            position_std_m=float(stds[k][0]),
            rotation_std_deg=float(stds[k][1]),
        )
        for k, m in enumerate(marker_ids)
    ]
    if not all(np.all(np.isfinite(p.R_map_marker)) and np.all(np.isfinite(p.position_m)) for p in placed):
        raise UserError("the map solve did not converge to finite marker poses")
    marker_map = MarkerMap(dictionary, tuple(p.map_marker() for p in placed), placement)
    path = np.array([-Rc[k].T @ tc[k] for k in range(len(cams))]).reshape(-1, 3)
    return MapBuild(
        marker_map=marker_map,
        anchor=int(anchor),
        placed=placed,
        unplaced=dict(sorted(unplaced.items())),
        rms_px=float(rms),
        frames_total=n_frames,
        frames_used=len(cams),
        frames_left_out=left_out,
        plane=plane_note,
        camera_path_m=path,
        stage_s=stage,
        observations_used=int(len(prob.obs_cam)),
        solves=solve_log,
    )


def _id_list(ids: Sequence[int]) -> str:
    return ", ".join(str(i) for i in ids[:20]) + (" ..." if len(ids) > 20 else "")


def _reasons(unplaced: Dict[int, str]) -> str:
    return "; ".join(f"{i}: {why}" for i, why in list(unplaced.items())[:10])
