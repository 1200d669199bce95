"""The view-angle sweep of ``pose-daemon bench detector --sweep view``: how often a pose is sent,
and how good it is, from face-on to 80 deg off the marker's face, beside the anchor.

Per bin of 10 deg, per background (plain, textured) and per marker type, the same poses (0.2 m
marker at 0.5-3 m, anywhere in the 640x480 frame, any in-plane rotation): the daemon's
processor (detect, estimate, the gate and the choice of solution: what would be sent) on the
frame alone (a first sighting, a whole-frame search) and as the last frame of a turn towards
it from 40 deg or less at 30 fps (tracked: a plain square's first sighting past
``[gate] max_view_deg`` is withheld, a tracked one is followed); the anchor, OpenCV's ArUco
detector with sub-pixel corners (``CORNER_REFINE_SUBPIX``, its cornerSubPix) and
``solvePnP(SOLVEPNP_IPPE_SQUARE)``, on the ArUco frames. Marker-free frames (plain, textured
and bench ambiguity's sheet of rectangles, in a row) count false poses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np

from ...camera import Camera, Marker
from ...capture.base import Frame
from ...geometry import R_from_rvec, rot_z, rotation_angle_deg_3x3
from ...render import Effects, facing_pose, inside_image, render_empty, render_frame, render_plane
from .common import DICTIONARY, MARKER_ID, MARKER_SIZE_M, fmt, opencv_anchor

#: The bins' lower edges, degrees off the marker's face; each bin is VIEW_BIN_DEG wide.
VIEW_BINS = tuple(range(0, 80, 10))
VIEW_BIN_DEG = 10.0
BACKGROUNDS = ("plain", "texture")
#: A tracked sequence starts at this view angle (or the target's, if less) ...
TRACK_START_DEG = 40.0
#: ... and turns by at most this per frame (at 30 fps: 150 deg/s), at least two frames before.
TRACK_STEP_DEG = 5.0
FPS = 30.0
#: A pose sent further off than this (a plain square: over its quarter turns) is a wrong one.
WRONG_DEG = 5.0
DETECTORS = ("search", "tracked", "anchor")


@dataclass
class BinTally:
    """One detector's results in one bin: frames, poses sent, their errors."""

    frames: int = 0
    sent: int = 0
    wrong: int = 0
    rot_deg: List[float] = field(default_factory=list)
    trans_mm: List[float] = field(default_factory=list)

    def add(self, R: Optional[np.ndarray], tvec, R_true: np.ndarray, t_true: np.ndarray, square: bool) -> None:
        self.frames += 1
        if R is None:
            return
        self.sent += 1
        turns = range(4) if square else range(1)
        err = min(rotation_angle_deg_3x3(R @ rot_z(k * math.pi / 2), R_true) for k in turns)
        if err > WRONG_DEG:
            self.wrong += 1
            return
        self.rot_deg.append(float(err))
        self.trans_mm.append(1e3 * float(np.linalg.norm(np.asarray(tvec, float).reshape(3) - t_true)))

    def summary(self) -> Dict[str, Optional[float]]:
        def q(values: List[float], p: float) -> Optional[float]:
            return float(np.percentile(values, p)) if values else None

        return {
            "frames": self.frames,
            "sent_rate": self.sent / self.frames if self.frames else None,
            "wrong": self.wrong,
            "rotation_err_median_deg": q(self.rot_deg, 50),
            "rotation_err_p95_deg": q(self.rot_deg, 95),
            "translation_err_median_mm": q(self.trans_mm, 50),
            "translation_err_p95_mm": q(self.trans_mm, 95),
        }


def _draw_view(rng: np.random.Generator, camera: Camera, marker: Marker, lo_deg: float) -> Tuple[list, float]:
    """A final pose in the bin [lo_deg, lo_deg + VIEW_BIN_DEG) and the turn towards it: the
    poses [(rvec, tvec), ...] from TRACK_START_DEG (or less) to the final one, all inside the
    image; and the final view angle."""
    for attempt in range(2000):
        spread = 1.0 if attempt < 1000 else 0.3
        centre = (
            camera.cx + spread * rng.uniform(-0.5, 0.5) * camera.width,
            camera.cy + spread * rng.uniform(-0.5, 0.5) * camera.height,
        )
        dist = float(rng.uniform(0.5, 3.0))
        axis, roll = float(rng.uniform(0, 2 * math.pi)), float(rng.uniform(-math.pi, math.pi))
        view = float(rng.uniform(lo_deg, lo_deg + VIEW_BIN_DEG))
        start = min(view, TRACK_START_DEG)
        n = max(2, math.ceil((view - start) / TRACK_STEP_DEG))
        views = [start + (view - start) * k / n for k in range(n)] if view > start else [view - 2.0, view - 1.0]
        poses = [facing_pose(camera, centre, dist, axis, v, roll) for v in views + [view]]
        if all(inside_image(camera, marker, r, t) for r, t in poses):
            return poses, view
    raise ValueError(f"no pose {lo_deg:g}-{lo_deg + VIEW_BIN_DEG:g} deg off the face fits the image")


def run_view_sweep(n_frames: int, seed: int, camera: Camera, n_empty: Optional[int] = None) -> dict:
    """The sweep on ``n_frames`` poses per bin and background (the same poses for both marker
    types), and ``n_empty`` marker-free frames per marker-free set (default ``n_frames``)."""
    from ...processing.marker import FrameProcessor

    markers = {
        "aruco": Marker(MARKER_SIZE_M, MARKER_SIZE_M, type="aruco", dictionary=DICTIONARY, id=MARKER_ID),
        "square": Marker(MARKER_SIZE_M, MARKER_SIZE_M),
    }
    anchor_finder = opencv_anchor()
    K, dist = camera.K, camera.dist_coeffs
    tallies: Dict[Tuple[str, str, str, int], BinTally] = {}

    class Both:
        """The tally of one background and that of both pooled, fed alike."""

        def __init__(self, *parts: BinTally) -> None:
            self.parts = parts

        def add(self, *args) -> None:
            for part in self.parts:
                part.add(*args)

    def tally(kind: str, who: str, background: str, lo: int) -> Both:
        return Both(
            tallies.setdefault((kind, who, background, lo), BinTally()),
            tallies.setdefault((kind, who, "both", lo), BinTally()),
        )

    for b_index, background in enumerate(BACKGROUNDS):
        for lo in VIEW_BINS:
            pose_rng = np.random.default_rng([seed, 30, b_index, lo])
            for i in range(n_frames):
                poses, _ = _draw_view(pose_rng, camera, markers["aruco"], float(lo))
                scene_rng = np.random.default_rng([seed, 31, b_index, lo, i])
                effects = Effects(
                    blur_px=0.8,
                    noise_gray=2.0,
                    background=background,
                    plain_gray=float(scene_rng.uniform(60.0, 200.0)),
                    lighting_gradient=float(scene_rng.uniform(0.0, 0.6)),
                )
                scene_seed = int(scene_rng.integers(2**31))
                rvec_t, tvec_t = poses[-1]
                R_true = R_from_rvec(np.asarray(rvec_t, float))
                for kind, marker in markers.items():
                    square = kind == "square"
                    frames = [
                        render_frame(camera, marker, r, t, effects=effects, rng=np.random.default_rng(scene_seed + k))[
                            0
                        ]
                        for k, (r, t) in enumerate(poses)
                    ]
                    # The frame alone: a first sighting.
                    alone = FrameProcessor(camera, marker).process(Frame(frames[-1], 0.0, 0))
                    pose = alone.pose
                    tally(kind, "search", background, lo).add(
                        None if pose is None else pose.R, None if pose is None else pose.tvec, R_true, tvec_t, square
                    )
                    # The last frame of the turn towards it.
                    proc = FrameProcessor(camera, marker)
                    for k, image in enumerate(frames):
                        result = proc.process(Frame(image, k / FPS, k))
                    pose = result.pose
                    tally(kind, "tracked", background, lo).add(
                        None if pose is None else pose.R, None if pose is None else pose.tvec, R_true, tvec_t, square
                    )
                    if kind == "aruco":
                        found, ids = anchor_finder.detect(frames[-1])
                        R_a, t_a = None, None
                        for c, marker_id in zip(found, ids):
                            if int(marker_id) == MARKER_ID:
                                ok, rvec_a, tvec_a = cv2.solvePnP(
                                    marker.object_points, c.astype(np.float64), K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE
                                )
                                if ok:
                                    R_a, t_a = R_from_rvec(np.asarray(rvec_a, float).reshape(3)), tvec_a
                                break
                        tally(kind, "anchor", background, lo).add(R_a, t_a, R_true, tvec_t, False)
    rows = [
        dict(marker=kind, detector=who, background=background, view_deg=lo, **t.summary())
        for (kind, who, background, lo), t in tallies.items()
    ]
    return {"rows": rows, "false_poses": _false_poses(camera, markers, seed, n_frames if n_empty is None else n_empty)}


def _false_poses(camera: Camera, markers: Dict[str, Marker], seed: int, n_empty: int) -> List[dict]:
    """Poses sent on marker-free frames, in a row per set (a false track would be followed):
    plain and textured backgrounds, and bench ambiguity's sheet of rectangles turning past."""
    from ...geometry import R_from_euler_rpy, VehicleFrames, VehiclePose, rvec_from_R
    from ...processing.marker import FrameProcessor
    from ..ambiguity import clutter_texture

    anchor_finder = opencv_anchor()
    out = []
    wall = VehicleFrames.from_settings("forward", placement="wall")
    for set_index, name in enumerate(("plain", "texture", "rectangles sheet")):
        procs = {kind: FrameProcessor(camera, marker, frames=wall) for kind, marker in markers.items()}
        sent = {kind: 0 for kind in markers}
        anchor_sent = 0
        rng = np.random.default_rng([seed, 40, set_index])
        texture = clutter_texture(rng) if name == "rectangles sheet" else None
        for i in range(n_empty):
            effects = Effects(
                background="plain" if name == "plain" else "texture", plain_gray=float(rng.uniform(60, 200))
            )
            if texture is None:
                image = render_empty(camera, effects=effects, rng=rng)
            else:
                if i % 10 == 0:
                    texture = clutter_texture(rng)
                yaw = math.radians(-35.0 + 7.0 * (i % 10))
                R_cm, tvec = wall.camera_pose(VehiclePose(np.array([-1.0, 0.0, 0.0]), R_from_euler_rpy(0.0, 0.0, yaw)))
                image = render_plane(camera, texture, (0.8, 0.6), rvec_from_R(R_cm), tvec, effects=effects, rng=rng)
            for kind, proc in procs.items():
                sent[kind] += proc.process(Frame(image, i / FPS, i)).pose is not None
            _, ids = anchor_finder.detect(image)
            anchor_sent += bool(np.any(np.asarray(ids) == MARKER_ID))
        out.append(
            {"set": name, "frames": n_empty, **{f"{k}_sent": v for k, v in sent.items()}, "anchor_sent": anchor_sent}
        )
    return out


def print_view_sweep(result: dict, n_frames: int) -> None:
    """The sweep's table: per bin, both backgrounds pooled, each detector's share of frames
    with a pose sent and its errors (each background's rows are in ``result``); then the
    marker-free sets."""
    print()
    print(
        f"view-angle sweep: {n_frames} poses per 10 deg bin and background (plain, textured), 0.2 m marker"
        f" at 0.5-3 m, 640x480 fx=500, blur 0.8 px, noise 2; sent = share of frames with a pose sent"
        f" (wrong = sent > {WRONG_DEG:g} deg off, not in the errors); rotation deg / translation mm, median / p95"
    )
    header = f"{'view':<8}{'detector':<26}{'sent':>7}{'wrong':>6}{'rotation':>16}{'translation':>16}"
    print(header)
    print("-" * len(header))
    names = {
        ("aruco", "search"): "aruco, first sighting",
        ("aruco", "tracked"): "aruco, tracked",
        ("aruco", "anchor"): "aruco, OpenCV + IPPE",
        ("square", "search"): "square, first sighting",
        ("square", "tracked"): "square, tracked",
    }
    for lo in VIEW_BINS:
        for (kind, who), name in names.items():
            s = next(
                r
                for r in result["rows"]
                if (r["marker"], r["detector"], r["background"], r["view_deg"]) == (kind, who, "both", lo)
            )
            print(
                f"{f'{lo}-{lo + 10:g}':<8}{name:<26}{fmt(_pct(s['sent_rate']), '.0f', '%'):>7}{s['wrong']:>6}"
                f"{_pair(s['rotation_err_median_deg'], s['rotation_err_p95_deg'], '.3f', '.2f'):>16}"
                f"{_pair(s['translation_err_median_mm'], s['translation_err_p95_mm'], '.1f', '.1f'):>16}"
            )
    print()
    print("marker-free frames, in a row per set: poses sent (pose-daemon square, aruco; the anchor's aruco)")
    for f in result["false_poses"]:
        print(
            f"  {f['set']:<18}{f['frames']:>4} frames: square {f['square_sent']}, aruco {f['aruco_sent']},"
            f" anchor {f['anchor_sent']}"
        )


def _pct(rate: Optional[float]) -> Optional[float]:
    return None if rate is None else 100.0 * rate


def _pair(a: Optional[float], b: Optional[float], fa: str, fb: str) -> str:
    return "-" if a is None or b is None else f"{format(a, fa)} / {format(b, fb)}"
