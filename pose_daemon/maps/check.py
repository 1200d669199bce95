"""``pose-daemon map check``'s library half: a map held against a recording's own frames.

The frames go through the map processor built from the whole config, as ``replay`` builds it
(camera, estimator, detector, [mount], [attitude]); each frame's markers are then judged on
what the frames themselves say, not on how the markers agree with each other (a map wrong
everywhere the same way agrees with itself):

1. Orientation. Every marker wholly in view gives the camera's pose on its own (both planar
   solutions), carried into the map frame under each of the 8 ways its printed square can
   sit against the map's (turned 0/90/180/270 deg about its normal, face out or mirrored).
   One camera saw them all, so in a frame with two markers or more the assignment whose poses
   coincide is the truth; each marker's share of frames per assignment is its vote.
2. Size and place. With those orientations, each marker is left out and the map pose solved
   from the others (with the frame's attitude as in the daemon); the marker's corners as the
   map has them are held against those seen: their spread gives its size ratio, their centre
   its offset.

A marker turned, mirrored, mis-sized (or in other units) or moved is one line saying so, exit
status 1; so is a check with too little to go on (no frame with two markers, frames that give
no map pose). Exit 0 only when every marker the frames show was checked and agrees.
"""

from __future__ import annotations

import math
import sys
from collections import Counter
from dataclasses import dataclass, field, replace
from typing import Dict, Iterable, List, Optional, TextIO, Tuple

import cv2
import numpy as np

from ..camera import Camera
from ..capture.base import Frame
from ..config import Config, load_config
from ..geometry import R_from_euler_rpy, R_from_rvec, euler_rpy_from_R_3x3, rot_x, rot_z
from ..marker_map import MarkerMap
from .survey import _camera_of, _frames, _open, load_map_file

#: Frames a marker must be checked in for a verdict.
MIN_CHECKED = 3
#: An orientation other than the map's is reported when it wins this share of a marker's votes.
VOTE_SHARE = 0.6
#: Two single-marker camera poses agree within this: centre distance over the distance to the
#: marker, plus the rotation between them in radians.
AGREE = 0.15
#: A size ratio beyond this (either way) is a mis-sized marker.
SIZE_TOLERANCE = 0.08
#: A marker whose median centre offset exceeds this (pixels) and MOVED_FACTOR times the
#: others' is misplaced (or every marker, when the others are off too).
MOVED_PX = 2.0
MOVED_FACTOR = 3.0
#: A check where fewer of the frames with markers than this share give a map pose says so.
MIN_POSE_SHARE = 0.5
#: Size ratios that are a unit mix-up: (map size / printed size, what it is).
UNIT_RATIOS = (
    (100.0, "centimetres"),
    (1000.0, "millimetres"),
    (1.0 / 0.0254, "inches"),
    (1.0 / 0.3048, "feet"),
    (0.0254, "metres read as inches"),
    (0.01, "metres read as centimetres"),
)

# The 8 ways a printed square can sit against the map's: H, with the true marker frame = the
# map's marker frame @ H. Index 0 is the map as written.
_ORIENTATIONS: List[Tuple[str, np.ndarray]] = []
for _mirror in (False, True):
    for _k in range(4):
        _H = rot_z(math.radians(90.0 * _k))
        if _mirror:
            _H = _H @ rot_x(math.pi)
        _ORIENTATIONS.append((f"{'mirrored ' if _mirror else ''}{90 * _k}", _H))


def orientation_text(index: int) -> str:
    """What orientation ``index`` (of _ORIENTATIONS) says about the map's marker."""
    k, mirrored = index % 4, index >= 4
    turn = {
        0: "",
        1: "turned 90 deg clockwise about its normal (seen from its face)",
        2: "turned 180 deg about its normal",
        3: "turned 90 deg counter-clockwise about its normal (seen from its face)",
    }[k]
    if mirrored:
        return "mirrored (the map has its back where its face is)" + (f" and {turn}" if turn else "")
    return turn


@dataclass
class MarkerVerdict:
    """What the frames say about one map marker."""

    id: int
    votes: Counter = field(default_factory=Counter)  # orientation index -> frames
    size_ratios: List[float] = field(default_factory=list)  # printed / map
    offsets_px: List[float] = field(default_factory=list)
    offsets_m: List[float] = field(default_factory=list)
    seen: int = 0  # frames it was wholly in view
    orientation: int = 0
    problems: List[str] = field(default_factory=list)

    @property
    def placed(self) -> bool:
        """Its size and place were measured in enough frames."""
        return len(self.offsets_px) >= MIN_CHECKED

    @property
    def checked(self) -> bool:
        """Its orientation too (a marker far off in size gives no votes: no verdict is one)."""
        return self.placed and (sum(self.votes.values()) >= MIN_CHECKED or bool(self.problems))


@dataclass
class CheckResult:
    verdicts: Dict[int, MarkerVerdict]
    frames: int
    frames_with_markers: int
    frames_with_pose: int
    frames_with_two: int
    pose_errors: Counter


def _inside(camera: Camera, corners: np.ndarray) -> bool:
    return bool(np.all((corners >= -0.5) & (corners <= [camera.width - 0.5, camera.height - 0.5])))


def _camera_candidates(
    camera: Camera, marker_map: MarkerMap, marker_id: int, corners: np.ndarray
) -> List[Tuple[int, np.ndarray, np.ndarray]]:
    """(orientation index, R_map_cam, camera centre in the map) for each orientation and each
    planar solution of the marker's own pose."""
    h = marker_map.marker(marker_id).size_m / 2.0
    obj = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            obj, corners.reshape(4, 2).astype(np.float64), camera._K, camera._dist, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
    except cv2.error:
        return []
    R_mm, p = marker_map.T_map_marker(marker_id)
    out = []
    for k in range(int(n)):
        R_cm = R_from_rvec(np.asarray(rvecs[k], dtype=np.float64).reshape(3))
        t = np.asarray(tvecs[k], dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(R_cm)) and np.all(np.isfinite(t))):
            continue
        R_marker_cam, c_marker = R_cm.T, -R_cm.T @ t
        for j, (_, H) in enumerate(_ORIENTATIONS):
            R_map_cam = R_mm @ H @ R_marker_cam
            out.append((j, R_map_cam, R_mm @ H @ c_marker + p))
    return out


def _consensus(
    candidates: Dict[int, List[Tuple[int, np.ndarray, np.ndarray]]], marker_map: MarkerMap
) -> Dict[int, int]:
    """The orientation of each marker under which the camera poses its markers give coincide
    (markers no assignment fits are left out)."""
    ids = [i for i in candidates if candidates[i]]
    if len(ids) < 2:
        return {}
    owner = np.concatenate([[k] * len(candidates[i]) for k, i in enumerate(ids)])
    orient = np.array([c[0] for i in ids for c in candidates[i]])
    Rs = np.array([c[1] for i in ids for c in candidates[i]])
    cs = np.array([c[2] for i in ids for c in candidates[i]])
    centres = np.array([marker_map.marker(ids[k]).position_m for k in owner])
    reach = np.maximum(np.linalg.norm(cs - centres, axis=1), 0.1)
    d_pos = np.linalg.norm(cs[:, None, :] - cs[None, :, :], axis=2) / reach[:, None]
    cos = (np.einsum("aji,bji->ab", Rs, Rs) - 1.0) / 2.0
    dist = d_pos + np.arccos(np.clip(cos, -1.0, 1.0))
    n = len(ids)
    # Per reference candidate, each marker's closest candidate (its own marker: the reference).
    best_of = np.full((dist.shape[0], n), np.inf)
    arg_of = np.zeros((dist.shape[0], n), dtype=int)
    for k in range(n):
        cols = np.flatnonzero(owner == k)
        sub = dist[:, cols]
        arg_of[:, k] = cols[np.argmin(sub, axis=1)]
        best_of[:, k] = sub.min(axis=1)
    for a in range(dist.shape[0]):
        best_of[a, owner[a]], arg_of[a, owner[a]] = 0.0, a
    total = np.minimum(best_of, 1.0).sum(axis=1)
    ref = int(np.argmin(total))
    return {ids[k]: int(orient[arg_of[ref, k]]) for k in range(n) if best_of[ref, k] <= AGREE}


def _turned(marker_map: MarkerMap, orientation: Dict[int, int]) -> MarkerMap:
    """The map with each marker set the way the frames show it."""
    markers = []
    for m in marker_map.markers:
        j = orientation.get(m.id, 0)
        if j:
            R = R_from_euler_rpy(*np.radians(m.rotation_deg)) @ _ORIENTATIONS[j][1]
            roll, pitch, yaw = euler_rpy_from_R_3x3(R)
            m = replace(m, rotation_deg=(math.degrees(roll), math.degrees(pitch), math.degrees(yaw)))
        markers.append(m)
    return MarkerMap(marker_map.dictionary, tuple(markers), marker_map.placement)


def _unit_hint(ratio_map_over_printed: float) -> str:
    for r, name in UNIT_RATIOS:
        if abs(math.log(ratio_map_over_printed / r)) < 0.03:
            return f": {name}, not metres?" if "read as" not in name else f": {name}?"
    return ""


def _resized(marker_map: MarkerMap, sizes: Dict[int, float]) -> MarkerMap:
    markers = tuple(replace(m, size_m=sizes[m.id]) if m.id in sizes else m for m in marker_map.markers)
    return MarkerMap(marker_map.dictionary, markers, marker_map.placement)


def _measure(
    verdicts: Dict[int, MarkerVerdict],
    kept: List[Tuple[Dict[int, np.ndarray], object]],
    camera: Camera,
    turned: MarkerMap,
    reference: MarkerMap,
    moved: set,
) -> None:
    """Each marker's size ratio and offset in every kept frame, under the pose the other
    markers (not those in ``moved``) give in ``reference``; its corners as ``turned`` has them."""
    from ..pose.map_solve import solve_map_pose
    from ..pose.types import EstimationError

    for v in verdicts.values():
        v.size_ratios, v.offsets_px, v.offsets_m = [], [], []
    for found, prior in kept:
        for i, corners in found.items():
            others = {j: c for j, c in found.items() if j != i and j not in moved}
            if not others:
                continue
            try:
                pose = solve_map_pose(others, camera, reference, prior=prior)  # type: ignore[arg-type]
            except EstimationError:
                continue
            # The corners seen, cast onto the marker's plane as the map (turned) has it: their
            # size and centre in the marker's own frame, metres.
            R_mm, p = turned.T_map_marker(i)
            normal = pose.R @ R_mm[:, 2]
            origin = pose.R @ p + pose.tvec
            rays = np.hstack([camera.undistort_normalized(corners), np.ones((4, 1))])
            along = rays @ normal
            if not np.all(np.abs(along) > 1e-9):
                continue
            lam = float(origin @ normal) / along
            if not np.all(lam > 0.0):
                continue
            local = ((rays * lam[:, None] - pose.tvec) @ pose.R - p) @ R_mm  # (4, 3) in the marker frame
            side = float(np.mean(np.linalg.norm(local - np.roll(local, 1, axis=0), axis=1)))
            off_m = float(np.linalg.norm(local.mean(axis=0)[:2]))
            depth = float(origin[2])
            if not (side > 0.0 and depth > 1e-3):
                continue
            v = verdicts[i]
            v.size_ratios.append(side / turned.marker(i).size_m)
            v.offsets_m.append(off_m)
            v.offsets_px.append(off_m * camera.fx / depth)


def _judge(verdicts: Dict[int, MarkerVerdict], marker_map: MarkerMap, known_moved: set) -> Tuple[Dict[int, float], set]:
    """Each checked marker's problems from its measurements; (sizes the frames give to the
    mis-sized, the ids of the moved; ``known_moved``: those found moved in earlier rounds)."""
    sizes: Dict[int, float] = {}
    moved = set()
    medians = {i: float(np.median(v.offsets_px)) for i, v in verdicts.items() if v.placed}
    for i, v in verdicts.items():
        v.problems = []
        if not v.placed:
            continue
        if v.orientation:
            v.problems.append(
                f"tag {i} is {orientation_text(v.orientation)} against the frames "
                f"({v.votes[v.orientation]} of {sum(v.votes.values())} frames)"
            )
        ratio = float(np.median(v.size_ratios))
        size = marker_map.marker(i).size_m
        if abs(math.log(ratio)) > math.log1p(SIZE_TOLERANCE):
            sizes[i] = size * ratio
            v.problems.append(
                f"tag {i} is {size:g} m in the map but {size * ratio:.4g} m in the frames "
                f"(x{ratio:.3g}{_unit_hint(1.0 / ratio)})"
            )
        med = medians[i]
        others = [m for j, m in medians.items() if j != i]
        typical = float(np.median(others)) if others else 0.0
        if med > MOVED_PX and (med > MOVED_FACTOR * typical or typical > MOVED_PX):
            moved.add(i)
            v.problems.append(
                f"tag {i} is {float(np.median(v.offsets_m)):.3g} m from where the map has it "
                f"({med:.1f} px, median of {len(v.offsets_px)} frames)"
            )
    # One more misplaced marker counts as moved in a round, the worst: the others' offsets may
    # be its doing (it was among the markers their poses came from).
    fresh = moved - known_moved
    if len(fresh) > 1:
        worst = max(fresh, key=lambda i: medians[i])
        for i in fresh - {worst}:
            verdicts[i].problems = [p for p in verdicts[i].problems if "from where the map has it" not in p]
        moved = (moved & known_moved) | {worst}
    return sizes, moved


def check_frames(
    marker_map: MarkerMap, frames: Iterable[Frame], camera: Camera, cfg: Optional[Config] = None
) -> CheckResult:
    """Judge every marker of ``marker_map`` against ``frames`` (see the module's text), with
    the processor ``cfg`` (its [mount], [attitude], [estimator], [detector]) gives."""
    from ..processing.map import MapFrameProcessor

    proc = MapFrameProcessor.from_config(cfg if cfg is not None else Config(), camera=camera, marker_map=marker_map)
    verdicts = {i: MarkerVerdict(i) for i in marker_map.ids}
    kept: List[Tuple[Dict[int, np.ndarray], object]] = []
    n = with_markers = with_pose = with_two = 0
    errors: Counter = Counter()
    try:
        for frame in frames:
            n += 1
            result = proc.process(frame)
            found = {i: c for i, c in proc.last_found.items() if i in marker_map and _inside(camera, c)}
            if proc.last_found:
                with_markers += 1
                if result.ok:
                    with_pose += 1
                elif result.error:
                    errors[result.error.split(":")[0]] += 1
            for i in found:
                verdicts[i].seen += 1
            if len(found) < 2:
                continue
            with_two += 1
            kept.append((found, proc.gravity_prior(result.attitude)))
            cands = {i: _camera_candidates(camera, marker_map, i, c) for i, c in found.items()}
            for i, j in _consensus(cands, marker_map).items():
                verdicts[i].votes[j] += 1
    finally:
        proc.close()
    for v in verdicts.values():
        if v.votes:
            j, count = v.votes.most_common(1)[0]
            if j and count >= VOTE_SHARE * sum(v.votes.values()):
                v.orientation = j
    turned = _turned(marker_map, {i: v.orientation for i, v in verdicts.items()})
    # Size and place, leaving each marker out in turn; a marker found mis-sized takes its size
    # from the frames, and one found moved is left out, for the poses the others are judged by.
    sizes: Dict[int, float] = {}
    moved: set = set()
    for _ in range(6):
        reference = _resized(turned, sizes)
        _measure(verdicts, kept, camera, turned, reference, moved)
        new_sizes, new_moved = _judge(verdicts, marker_map, moved)
        if new_sizes.keys() == sizes.keys() and new_moved == moved:
            break
        sizes, moved = new_sizes, new_moved
    return CheckResult(verdicts, n, with_markers, with_pose, with_two, errors)


def report(result: CheckResult, source: str, stream: TextIO) -> int:
    """Print the check's table and findings; the exit status (0 only when all is checked and well)."""
    v = result.verdicts
    print(
        f"{source}: {result.frames} frames, {result.frames_with_markers} with map markers, "
        f"{result.frames_with_pose} with a map pose, {result.frames_with_two} with two markers or more",
        file=stream,
    )
    print(f"  {'id':>4} {'seen':>5} {'votes':>6} {'size x':>7} {'offset px':>10} {'p90 px':>7}", file=stream)
    for i, m in v.items():
        if not m.seen:
            continue
        if not m.placed:
            print(f"  {i:>4} {m.seen:>5} {sum(m.votes.values()):>6} {'-':>7} {'-':>10} {'-':>7}", file=stream)
            continue
        print(
            f"  {i:>4} {m.seen:>5} {sum(m.votes.values()):>6} {float(np.median(m.size_ratios)):>7.3f} "
            f"{float(np.median(m.offsets_px)):>10.2f} {float(np.percentile(m.offsets_px, 90)):>7.2f}",
            file=stream,
        )
    problems = [p for m in v.values() for p in m.problems]
    for p in problems:
        print(p, file=stream)
    too_little = []
    if result.frames_with_two == 0:
        too_little.append(
            f"too little to check: no frame shows two map markers wholly in view together "
            f"({result.frames_with_markers} frames with markers)"
        )
    unchecked = [i for i, m in v.items() if m.seen and not m.checked]
    for i in unchecked:
        too_little.append(
            f"tag {i} not checked: seen wholly with another marker in {len(v[i].offsets_px)} frames, its "
            f"orientation settled in {sum(v[i].votes.values())} (needs {MIN_CHECKED} each)"
        )
    if result.frames_with_markers and result.frames_with_pose < MIN_POSE_SHARE * result.frames_with_markers:
        why = ", ".join(f"{k} {c}" for k, c in result.pose_errors.most_common(2))
        too_little.append(
            f"only {result.frames_with_pose} of {result.frames_with_markers} frames with markers give a map pose "
            f"({why}): check the config's [mount] and [attitude] (give it with --config)"
        )
    for line in too_little:
        print(line, file=stream)
    checked = [i for i, m in v.items() if m.checked]
    unseen = [i for i, m in v.items() if not m.seen]
    if problems or too_little or not checked:
        if not problems and not too_little:
            print("too little to check: no marker was checked", file=stream)
        return 1
    tail = f"; {len(unseen)} not in the frames (not checked)" if unseen else ""
    print(
        f"every checked marker agrees with the frames: {len(checked)} markers (orientation, size, place){tail}",
        file=stream,
    )
    return 0


def check(map_path: str, source_path: str, config: Optional[str] = None, stream: Optional[TextIO] = None) -> int:
    """``pose-daemon map check``: 0 when every marker the frames show agrees with them, 1 when
    one does not or too little could be checked."""
    stream = stream if stream is not None else sys.stdout
    marker_map = load_map_file(map_path)
    cfg = load_config(config) if config is not None else None
    source = _open(source_path)
    try:
        camera = _camera_of(source, source_path, cfg.camera.model() if cfg is not None else None)
        result = check_frames(marker_map, _frames(source), camera, cfg)
    finally:
        source.close()
    return report(result, source_path, stream)


__all__ = ["check", "check_frames", "report", "CheckResult", "MarkerVerdict", "orientation_text"]
