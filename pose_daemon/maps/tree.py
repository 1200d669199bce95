"""Map build, stage 3: a maximum spanning tree over the markers (an edge's weight: the frames
that agree on the two markers' relative pose) puts every marker it reaches in the anchor's frame,
and each frame's camera pose starts from the marker pose that fits all its markers best."""

from __future__ import annotations

import heapq
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..camera import Camera
from .pairs import local_corners

__all__ = ["MIN_PAIR_SUPPORT", "spanning_tree", "camera_start"]

#: Two markers are joined in the graph when at least this many frames agree on their relative pose.
MIN_PAIR_SUPPORT = 1


def spanning_tree(
    anchor: int, relative: Dict[Tuple[int, int], Tuple[np.ndarray, np.ndarray, int]], candidates: Sequence[int]
) -> Dict[int, Tuple[np.ndarray, np.ndarray]]:
    """T_map_marker of every marker the maximum spanning tree from ``anchor`` reaches."""
    edges: Dict[int, List[Tuple[int, np.ndarray, np.ndarray, int]]] = {i: [] for i in candidates}
    for (a, b), (R, t, n) in relative.items():
        if n < MIN_PAIR_SUPPORT or a not in edges or b not in edges:
            continue
        edges[a].append((b, R, t, n))  # X_a = R X_b + t
        edges[b].append((a, R.T, -R.T @ t, n))
    placed = {anchor: (np.eye(3), np.zeros(3))}
    heap: List[Tuple[int, int, int, int]] = []
    counter = 0
    for j, _, _, n in edges[anchor]:
        heapq.heappush(heap, (-n, counter, anchor, j))
        counter += 1
    while heap:
        _, _, a, b = heapq.heappop(heap)
        if b in placed:
            continue
        R_ab, t_ab = next((R, t) for j, R, t, _ in edges[a] if j == b)
        Ra, pa = placed[a]
        placed[b] = (Ra @ R_ab, Ra @ t_ab + pa)
        for j, _, _, n in edges[b]:
            if j not in placed:
                heapq.heappush(heap, (-n, counter, b, j))
                counter += 1
    return placed


def camera_start(
    camera: Camera,
    observed: Dict[int, np.ndarray],
    poses: Dict[int, List[Tuple[np.ndarray, np.ndarray, float]]],
    markers: Dict[int, Tuple[np.ndarray, np.ndarray]],
    sizes: Dict[int, float],
) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """(R_cam_map, t) of one frame from its placed markers (the marker's own pose that fits
    all of them best, under a capped cost), or None; refined with the others by
    ``Problem.refine_cameras``."""
    ids = [i for i in sorted(observed) if i in markers]
    if not ids:
        return None
    obj = np.vstack([local_corners(sizes[i]) @ markers[i][0].T + markers[i][1] for i in ids])
    img = np.vstack([observed[i] for i in ids])
    best = None
    for i in ids:
        Rm, pm = markers[i]
        for Rc, tc, _ in poses.get(i, []):
            R = Rc @ Rm.T
            t = tc - R @ pm
            pts = obj @ R.T + t
            if not np.all(pts[:, 2] > 1e-6):
                continue
            d2 = np.sum((camera.project(pts) - img) ** 2, axis=1)
            cost = float(np.minimum(d2, 36.0).sum())
            if best is None or cost < best[0]:
                best = (cost, R, t)
    if best is None:
        return None
    return best[1], best[2]
