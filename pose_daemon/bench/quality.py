"""``pose-daemon bench quality``: does the quality sent to the autopilot follow the pose's real error?

Rendered hovers of a down-looking camera over a floor square (640x480, fx = 600, 0.2 m
marker), level, within +-5 deg and within +-15 deg of tilt, at 0.5, 1, 2 and 3 m, each frame
through the daemon's own detector, estimator, gate and continuity choice (FrameProcessor), its
quality as the outputs send it (``result_uncertainty``: the corner noise the processor
measured, the choice). Each pose is judged against the renderer's truth: "correct" (vehicle
position within 2 cm and attitude within 2 deg), "wrong" (attitude off by more than 10 deg, or
the other planar solution taken where the two are more than 5 deg apart and the other is the
nearer to the truth), or neither; "imprecise" counts poses more than 10 cm off. Each frame is
also estimated with one corner knocked 3 px off and put through the same gate and choice
(gate-worthy: wrong unless its pose is still correct; "withheld" when the gate or the choice
sends nothing for it) and, where the other planar solution is more than 10 deg off the truth,
as if that one had been taken by a coin flip (wrong). Printed per case: the quality
distribution (today's model and the old 100/(1+e^2)(1-ambiguity_ratio)), the fraction of
correct poses a minimum quality would drop and the wrong poses it would let through (a
withheld pose is never let through).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from typing import Dict, List, Optional, Sequence

import numpy as np

from ..camera import Camera, Marker
from ..capture.base import Frame
from ..geometry import R_from_euler_rpy, VehicleFrames, VehiclePose, rotation_angle_deg_3x3, rvec_from_R
from ..outputs.quality import pose_quality, resolved_by_prior, result_uncertainty, uncertainty
from ..pose.continuity import choose_by_continuity
from ..pose.estimator import estimate_pose
from ..pose.prior import choose_solution
from ..pose.types import EstimationError
from ..processing.marker import FrameProcessor
from ..render import Effects, render_frame

CAMERA = Camera(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=640, height=480)
MARKER = Marker(0.2, 0.2)
FRAMES = VehicleFrames.from_settings("down", placement="floor")
HEIGHTS_M = (0.5, 1.0, 2.0, 3.0)
TILTS_DEG = (0.0, 5.0, 15.0)
THRESHOLDS = (10, 30, 40)
# Gate-worthy frames: the same corners with one knocked this far off (a bad edge fit).
BAD_CORNER_PX = 3.0
CORRECT_M, CORRECT_DEG = 0.02, 2.0
# Wrong: the attitude off by more than 10 deg, or the other planar solution taken where the
# two are more than 5 deg apart (the alternative is the nearer one to the truth).
WRONG_DEG, FLIP_DEG = 10.0, 5.0
# Right solution, imprecise: the vehicle position off by more than this.
IMPRECISE_M = 0.10
MARGIN_PX = 4.0
# Frames each hover runs before the judged ones: the daemon's steady state, its corner noise
# measured (before that, its fit is judged against the least noise any camera has).
WARMUP_FRAMES = 30


def _old_quality(err_px: float, ratio: float) -> int:
    return int(min(100, max(1, round(100.0 / (1.0 + err_px**2) * (1.0 - min(max(ratio, 0.0), 1.0))))))


def _hover(rng: np.random.Generator, n: int, height_m: float, tilt_deg: float) -> List[VehiclePose]:
    """A hover: slow drift around the point above the marker, roll/pitch swinging within
    +-tilt_deg (exactly 0 for a level hover), heading swinging slowly."""
    out = []
    phases = rng.uniform(0, 2 * math.pi, 6)
    # A plain square's labels are defined up to quarter turns (the detector takes the first
    # sighting as upright): the heading stays within +-40 deg of the marker's.
    yaw0 = rng.uniform(-0.4, 0.4)
    drift_m = 0.15 * height_m * math.tan(math.radians(20.0))
    for k in range(n):
        s = np.sin(2 * math.pi * k / np.array([47.0, 61.0, 37.0, 29.0, 53.0, 71.0]) + phases)
        p = np.array([drift_m * s[0], drift_m * s[1], -height_m * (1.0 + 0.05 * s[2])])
        roll, pitch = math.radians(tilt_deg) * s[3], math.radians(tilt_deg) * s[4]
        out.append(VehiclePose(p, R_from_euler_rpy(roll, pitch, yaw0 + 0.3 * s[5])))
    return out


def _visible(R_cm: np.ndarray, t: np.ndarray) -> bool:
    pts = MARKER.object_points @ R_cm.T + t
    if np.any(pts[:, 2] <= 0.05):
        return False
    px = CAMERA.project(pts)
    return bool(np.all((px >= MARGIN_PX) & (px <= [CAMERA.width - 1 - MARGIN_PX, CAMERA.height - 1 - MARGIN_PX])))


def run_case(height_m: float, tilt_deg: float, n_frames: int, seed: int) -> Dict:
    rng = np.random.default_rng([seed, int(height_m * 10), int(tilt_deg)])
    proc = FrameProcessor(CAMERA, MARKER, frames=FRAMES)
    effects = Effects()
    rows: List[Dict] = []
    rendered = 0
    for k, vehicle in enumerate(_hover(rng, n_frames + WARMUP_FRAMES, height_m, tilt_deg)):
        R_cm, t = FRAMES.camera_pose(vehicle)
        if not _visible(R_cm, t):
            proc.reset()
            continue
        rendered += k >= WARMUP_FRAMES
        image, _ = render_frame(CAMERA, MARKER, rvec_from_R(R_cm), t, effects=effects, rng=rng)
        # The track as it stood before this frame: its bad-corner twin is judged against it.
        track_before = copy.deepcopy(proc.track)
        result = proc.process(Frame(seq=k, t_capture_s=k / 30.0, image=image))
        pose = result.pose
        if pose is None or k < WARMUP_FRAMES:
            continue
        est = FRAMES.vehicle_pose(pose.R, pose.tvec)
        pos_err = float(np.linalg.norm(est.p_local_body_m - vehicle.p_local_body_m))
        rot_err = rotation_angle_deg_3x3(est.R_local_body, vehicle.R_local_body)
        alt = pose.alternative
        flipped = (
            alt is not None
            and rotation_angle_deg_3x3(pose.R, alt.R) > FLIP_DEG
            and (rotation_angle_deg_3x3(alt.R, R_cm) < rotation_angle_deg_3x3(pose.R, R_cm))
        )
        sigma_px = result.corner_sigma_px
        rows.append(
            {
                "q": pose_quality(pose, u=result_uncertainty(result, FRAMES, CAMERA.fx, MARKER.width)),
                "q_old": _old_quality(pose.reprojection_error_px, pose.ambiguity_ratio),
                "correct": pos_err < CORRECT_M and rot_err < CORRECT_DEG,
                "wrong": rot_err > WRONG_DEG or flipped,
                "imprecise": pos_err > IMPRECISE_M,
                "kind": "sent",
                "pos_err_m": pos_err,
                "rot_err_deg": rot_err,
                "pose": pose,
                "sigma_px": sigma_px,
            }
        )
        # The same corners with one knocked BAD_CORNER_PX off: gate-worthy, judged wrong when
        # its pose is not correct.
        if result.corners is not None:
            bad = np.array(result.corners, dtype=np.float64)
            a = rng.uniform(0, 2 * math.pi)
            bad[rng.integers(4)] += BAD_CORNER_PX * np.array([math.cos(a), math.sin(a)])
            try:
                estimated = estimate_pose(bad, CAMERA, MARKER)
            except EstimationError:
                estimated = None
            if estimated is not None:
                # The same gate and choice as the frame itself (the track as it stands).
                side_px = float(np.mean(np.linalg.norm(bad - np.roll(bad, 1, axis=0), axis=1)))
                choice = choose_solution(
                    estimated,
                    FRAMES,
                    attitude=None,
                    settings=proc.prior,
                    side_px=side_px,
                    by_continuity=lambda p: choose_by_continuity(p, proc.track.normal_ref),
                    corners_px=bad,
                    camera=CAMERA,
                    marker=MARKER,
                    corner_sigma_px=sigma_px,
                )
                bp = choice.pose if choice.pose is not None else estimated
                be = FRAMES.vehicle_pose(bp.R, bp.tvec)
                b_pos = float(np.linalg.norm(be.p_local_body_m - vehicle.p_local_body_m))
                b_rot = rotation_angle_deg_3x3(be.R_local_body, vehicle.R_local_body)
                ok = b_pos < CORRECT_M and b_rot < CORRECT_DEG
                sent = choice.pose is not None
                u = uncertainty(
                    bp,
                    CAMERA.fx,
                    MARKER.width,
                    corner_sigma_px=sigma_px,
                    flip_resolved=resolved_by_prior(choice.resolved_by),
                )
                # As the outputs judge the frame: with the noise not measured yet, pending; its
                # rotation against the track's prediction.
                u = dataclasses.replace(
                    u,
                    pending=result.corner_noise_pending,
                    innovation=track_before.innovation(bp.R, result.t_capture_s) if sent else None,
                )
                rows.append(
                    {
                        # Withheld: nothing is sent, below any minimum quality.
                        "q": pose_quality(bp, u=u) if sent else 0,
                        "q_old": _old_quality(bp.reprojection_error_px, bp.ambiguity_ratio) if sent else 0,
                        "correct": False,
                        "wrong": not ok,
                        "withheld": not sent,
                        "imprecise": b_pos > IMPRECISE_M,
                        "kind": "bad corner",
                        "pos_err_m": b_pos,
                        "rot_err_deg": b_rot,
                        "pose": bp,
                        "sigma_px": sigma_px,
                        "gate": True,
                    }
                )
        # The same frame had the estimator taken the other solution by a coin flip: a wrong
        # pose whenever that solution is more than 10 deg off the truth.
        if alt is not None and rotation_angle_deg_3x3(alt.R, R_cm) > WRONG_DEG:
            flip = dataclasses.replace(
                alt, alternative=dataclasses.replace(pose, alternative=None), ambiguity_ratio=1.0
            )
            rows.append(
                {
                    "q": pose_quality(
                        flip,
                        u=dataclasses.replace(
                            uncertainty(flip, CAMERA.fx, MARKER.width, corner_sigma_px=sigma_px),
                            pending=result.corner_noise_pending,
                        ),
                    ),
                    "q_old": _old_quality(flip.reprojection_error_px, 1.0),
                    "correct": False,
                    "wrong": True,
                    "imprecise": True,
                    "kind": "coin flip",
                    "pose": flip,
                    "sigma_px": sigma_px,
                    "coin_flip": True,
                }
            )
    return {"height_m": height_m, "tilt_deg": tilt_deg, "rendered": rendered, "rows": rows}


def _summary(rows: Sequence[Dict], key: str, thresholds: Sequence[int]) -> Dict:
    q = np.array([r[key] for r in rows], dtype=float)
    correct = np.array([r["correct"] for r in rows], dtype=bool)
    wrong = np.array([r["wrong"] for r in rows], dtype=bool)
    imprecise = np.array([r["imprecise"] for r in rows], dtype=bool)
    out: Dict = {
        "poses": int(len(rows)),
        "correct": int(correct.sum()),
        "wrong": int(wrong.sum()),
        "withheld": int(sum(1 for r in rows if r.get("withheld"))),
        "imprecise": int(imprecise.sum()),
    }
    sent_q = q[[not r.get("withheld") for r in rows]] if len(rows) else q
    if len(sent_q):
        out.update(q_p5=float(np.percentile(sent_q, 5)), q_median=float(np.median(sent_q)), q_min=float(sent_q.min()))
    if correct.any():
        out["q_correct_p1"] = float(np.percentile(q[correct], 1))
        out["q_correct_median"] = float(np.median(q[correct]))
    if imprecise.any():
        out["q_imprecise_median"] = float(np.median(q[imprecise]))
    for th in thresholds:
        kept = q >= th
        out[f"drop_correct_{th}"] = float((~kept & correct).sum() / correct.sum()) if correct.any() else None
        out[f"pass_wrong_{th}"] = int((kept & wrong).sum())
    return out


def run_bench(
    n_frames: int = 60,
    seed: int = 0,
    heights_m: Sequence[float] = HEIGHTS_M,
    tilts_deg: Sequence[float] = TILTS_DEG,
    thresholds: Sequence[int] = THRESHOLDS,
) -> Dict:
    """The report: per case (height x tilt) and over all, for the new and the old quality."""
    cases = [run_case(h, tilt, n_frames, seed) for tilt in tilts_deg for h in heights_m]
    rows_all = [r for c in cases for r in c["rows"]]
    report: Dict = {"frames_per_case": n_frames, "seed": seed, "thresholds": list(thresholds), "cases": []}
    for c in cases:
        report["cases"].append(
            {
                "height_m": c["height_m"],
                "tilt_deg": c["tilt_deg"],
                "rendered": c["rendered"],
                "new": _summary(c["rows"], "q", thresholds),
                "old": _summary(c["rows"], "q_old", thresholds),
            }
        )
    report["all"] = {"new": _summary(rows_all, "q", thresholds), "old": _summary(rows_all, "q_old", thresholds)}
    return report


def _pct(v: Optional[float]) -> str:
    return "-" if v is None else f"{100.0 * v:.1f} %"


def print_report(report: Dict) -> None:
    ths = report["thresholds"]
    print(f"quality against truth, {report['frames_per_case']} hover frames per case, seed {report['seed']}")
    head = (
        "tilt",
        "height",
        "poses",
        "correct",
        "wrong",
        "wrong withheld",
        ">10 cm",
        "quality p5/median",
        "old p5/median",
        "q >10 cm median",
        *[f"drop correct @{t}" for t in ths],
        *[f"wrong passed @{t}" for t in ths],
    )
    print(" | ".join(head))
    lines = [(f"+-{c['tilt_deg']:g} deg", f"{c['height_m']:g} m", c["new"]) for c in report["cases"]]
    lines.append(("all", "", report["all"]["new"]))
    olds = [c["old"] for c in report["cases"]] + [report["all"]["old"]]
    for (tilt, h, s), o in zip(lines, olds):
        qs = f"{s.get('q_p5', 0):.0f}/{s.get('q_median', 0):.0f}" if s["poses"] else "-"
        qo = f"{o.get('q_p5', 0):.0f}/{o.get('q_median', 0):.0f}" if o["poses"] else "-"
        qi = f"{s['q_imprecise_median']:.0f}" if "q_imprecise_median" in s else "-"
        cells = [
            tilt,
            h,
            str(s["poses"]),
            str(s["correct"]),
            str(s["wrong"]),
            str(s["withheld"]),
            str(s["imprecise"]),
            qs,
            qo,
            qi,
            *[_pct(s[f"drop_correct_{t}"]) for t in ths],
            *[str(s[f"pass_wrong_{t}"]) for t in ths],
        ]
        print(" | ".join(cells))
    a_new, a_old = report["all"]["new"], report["all"]["old"]
    for t in ths:
        print(
            f"min quality {t}: drops {_pct(a_new[f'drop_correct_{t}'])} of correct poses and lets "
            f"{a_new[f'pass_wrong_{t}']} of {a_new['wrong']} wrong through (old model: "
            f"{_pct(a_old[f'drop_correct_{t}'])}, {a_old[f'pass_wrong_{t}']})"
        )
