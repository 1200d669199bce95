"""Section IV-C, eqs 18-22: a unicycle robot steered home by the pose estimated from its camera.

World frame (units: cm): origin at the window's centre, X to the window's right as the
robot sees it, Y down, Z from the robot's start towards the window (whose face looks down
-Z at the robot). These are the axes of the paper's "unrotated camera" (geometry.py), so
a robot with heading theta = 0 looks straight at the window. The robot moves as
X' = -v sin(theta), Z' = v cos(theta), theta' = w (eqs 18-20); its camera looks along its
heading, ``camera_below`` under the window's centre.

Each control step (one camera frame) the window's corners are projected with the project's
camera model at the robot's true pose, optionally disturbed by Gaussian pixel noise, and
``estimate_pose`` turns them into the feedback (x*, z*, theta*) of the controller
v = kv * distance to the goal (21), w = kw * (bearing of the goal - theta*) (22). The
controls are held over the step and the motion integrated exactly (arcs). A frame where a
corner falls outside the image (or behind the camera) gives no estimate; until the next
one the feedback is dead-reckoned from the last estimate with the commanded v and w.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Tuple

import numpy as np

from .. import geometry
from ..camera import Camera, Marker
from ..pose.estimator import estimate_pose
from ..pose.types import EstimationError, Pose

# A wide-angle Raspberry Pi camera (Camera Module 3 Wide: 102 deg horizontal field of view)
# at 640x480, lens distortion already calibrated out. The wide lens matters: the robot
# reaches the goal heading about 26 deg away from the window, which is 20 cm across at
# 50 cm, so a 62 deg camera (Camera Module 2, f = 530 px) loses it for most of the run.
DEFAULT_CAMERA = Camera(fx=260.0, fy=260.0, cx=319.5, cy=239.5, width=640, height=480)


@dataclass(frozen=True)
class UnicycleSetup:
    """Everything the paper leaves open, with the values this reproduction uses."""

    kv: float = 0.5  # 1/s: eq 21
    kw: float = 3.0  # 1/s: eq 22
    dt_s: float = 1.0 / 30.0  # one control step per camera frame at 30 fps
    duration_s: float = 10.0
    start: Tuple[float, float, float] = (20.0, -100.0, 0.0)  # x, z (cm), theta (deg)
    goal: Tuple[float, float] = (0.0, -50.0)  # x_f, z_f (cm)
    # The bearing in eq 22 is undefined at the goal: with noisy feedback, the robot would
    # spin in place there. It stops (v = w = 0, for good) once the feedback puts it within
    # goal_radius of the goal; 0 keeps the paper's controller exactly as printed.
    goal_radius: float = 1.0  # cm
    window_side: float = 20.0  # cm
    camera_below: float = 10.0  # cm the camera sits under the window's centre
    camera: Camera = DEFAULT_CAMERA
    method: str = "paper"
    iterations: int = 5
    refine: bool = False
    noise_px: float = 0.0
    seed: int = 0

    def to_json_dict(self) -> dict:
        c = self.camera
        return {
            "kv": self.kv,
            "kw": self.kw,
            "dt_s": self.dt_s,
            "duration_s": self.duration_s,
            "start": {"x": self.start[0], "z": self.start[1], "theta_deg": self.start[2]},
            "goal": {"x": self.goal[0], "z": self.goal[1]},
            "goal_radius": self.goal_radius,
            "window_side": self.window_side,
            "camera_below": self.camera_below,
            "camera": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width, "height": c.height},
            "method": self.method,
            "iterations": self.iterations,
            "refine": self.refine,
            "noise_px": self.noise_px,
            "seed": self.seed,
        }


@dataclass
class UnicycleRun:
    """One simulated run; arrays have one entry per control step (time t_s)."""

    feedback: str  # "true" or "estimated"
    t_s: np.ndarray
    x: np.ndarray
    z: np.ndarray
    theta_deg: np.ndarray
    x_est: np.ndarray = field(default_factory=lambda: np.empty(0))
    z_est: np.ndarray = field(default_factory=lambda: np.empty(0))
    theta_est_deg: np.ndarray = field(default_factory=lambda: np.empty(0))
    t_arrived_s: Optional[float] = None  # when the feedback first put it within goal_radius
    out_of_view: int = 0  # frames where a corner fell outside the image (no estimate)
    failures: int = 0  # frames the estimator rejected (the last estimate was kept)


def goal_bearing_rad(x: float, z: float, goal: Tuple[float, float]) -> float:
    """The heading that points from (x, z) at the goal.

    With X' = -v sin(theta) the printed eq 22, atan((x_f - x*) / (z_f - z*)), steers away
    from the goal (a sign slip: from (20, -100) to (0, -50) it asks for -21.8 deg, which
    moves towards +X); the heading that reaches it is atan2(x* - x_f, z_f - z*), which the
    paper's Figs. 7-8 show (heading rising to about +30 deg while X falls to 0).
    """
    return math.atan2(x - goal[0], goal[1] - z)


def camera_pose(x: float, z: float, theta_rad: float, setup: UnicycleSetup) -> Tuple[np.ndarray, np.ndarray]:
    """(R_cam_marker, tvec) of the robot's camera: X_cam = R X_marker + tvec."""
    # The world has the unrotated camera's axes, so the camera turned by theta about the
    # vertical is R_world_cam = Ry(theta) (its optical axis (-sin, 0, cos) is the heading).
    R_cam_world = np.swapaxes(geometry.rot_y(theta_rad), -1, -2)
    R_cam_marker = geometry.R_cam_marker_from_R_cam_unrot(R_cam_world)
    camera_in_world = np.array([x, setup.camera_below, z])
    tvec = R_cam_world @ (-camera_in_world)
    return R_cam_marker, tvec


def feedback_from_pose(pose: Pose) -> Tuple[float, float, float]:
    """(x*, z*, theta* rad) from an estimated Pose: the camera's place and heading in the world."""
    cp = np.asarray(pose.camera_position, dtype=np.float64)
    # marker frame (x right, y up, z towards the robot) -> world (X right, Y down, Z to the window)
    return float(cp[0]), float(-cp[2]), -math.radians(pose.beta_deg)


def _step(x: float, z: float, theta: float, v: float, w: float, dt: float) -> Tuple[float, float, float]:
    """Exact motion over dt with v, w held: an arc (a straight line when w = 0)."""
    h = 0.5 * w * dt
    sinc = math.sin(h) / h if abs(h) > 1e-12 else 1.0
    theta_mid = theta + h
    return (x - v * dt * math.sin(theta_mid) * sinc, z + v * dt * math.cos(theta_mid) * sinc, theta + w * dt)


def simulate(setup: UnicycleSetup, *, feedback: str = "estimated") -> UnicycleRun:
    """Run the closed loop for ``setup.duration_s`` with true or camera-estimated feedback."""
    if feedback not in ("true", "estimated"):
        raise ValueError(f"feedback must be 'true' or 'estimated', got {feedback!r}")
    marker = Marker(width=setup.window_side, height=setup.window_side)
    camera = setup.camera
    rng = np.random.default_rng(setup.seed)
    steps = int(round(setup.duration_s / setup.dt_s)) + 1
    t = np.arange(steps) * setup.dt_s
    xs, zs, ths = np.empty(steps), np.empty(steps), np.empty(steps)
    xe, ze, the = np.empty(steps), np.empty(steps), np.empty(steps)
    x, z, theta = setup.start[0], setup.start[1], math.radians(setup.start[2])
    last: Optional[Tuple[float, float, float]] = None
    out_of_view = failures = 0
    t_arrived: Optional[float] = None
    for k in range(steps):
        xs[k], zs[k], ths[k] = x, z, theta
        R, tvec = camera_pose(x, z, theta, setup)
        points_cam = marker.object_points @ R.T + tvec
        corners = camera.project(points_cam)
        if setup.noise_px > 0:
            corners = corners + rng.normal(0.0, setup.noise_px, corners.shape)
        if (
            np.any(points_cam[:, 2] <= 0.0)
            or np.any(corners < -0.5)
            or np.any(corners[:, 0] > camera.width - 0.5)
            or np.any(corners[:, 1] > camera.height - 0.5)
        ):
            # A real camera would not see the whole window: no detection this frame.
            out_of_view += 1
        else:
            try:
                pose = estimate_pose(
                    corners, camera, marker, method=setup.method, iterations=setup.iterations, refine=setup.refine
                )
                last = feedback_from_pose(pose)
            except EstimationError:
                failures += 1
        if last is None:
            # No estimate yet: nothing to compare, and a robot steered by its camera waits.
            xe[k] = ze[k] = the[k] = math.nan
            if feedback == "estimated":
                continue
        else:
            xe[k], ze[k], the[k] = last
        # last is None here only with true feedback (estimated feedback waited above).
        fx, fz, fth = (x, z, theta) if feedback == "true" or last is None else last
        distance = math.hypot(fx - setup.goal[0], fz - setup.goal[1])
        if t_arrived is None and distance < setup.goal_radius:
            t_arrived = float(t[k])
        if t_arrived is not None:
            continue
        v = setup.kv * distance
        w = setup.kw * (goal_bearing_rad(fx, fz, setup.goal) - fth)
        x, z, theta = _step(x, z, theta, v, w, setup.dt_s)
        if last is not None:
            # Dead reckoning: until the next camera fix the feedback follows the commanded
            # motion (a stale pose would make the robot circle with a constant turn rate).
            last = _step(*last, v, w, setup.dt_s)
    return UnicycleRun(feedback, t, xs, zs, np.degrees(ths), xe, ze, np.degrees(the), t_arrived, out_of_view, failures)


@dataclass
class UnicycleResult:
    setup: UnicycleSetup
    true_run: UnicycleRun
    estimated_run: UnicycleRun

    def to_json_dict(self) -> dict:
        e = self.estimated_run
        # Frames before the first estimate (possible only under heavy noise) have none.
        seen = np.isfinite(e.theta_est_deg)
        heading_err = np.abs(e.theta_est_deg - e.theta_deg)[seen]
        deviation = np.hypot(e.x - self.true_run.x, e.z - self.true_run.z)

        def worst(err: np.ndarray) -> Optional[float]:
            return float(err.max()) if err.size else None

        return {
            "max_heading_error_deg": worst(heading_err),
            "max_x_error": worst(np.abs(e.x_est - e.x)[seen]),
            "max_z_error": worst(np.abs(e.z_est - e.z)[seen]),
            "rms_heading_error_deg": (float(np.sqrt(np.mean(heading_err**2))) if heading_err.size else None),
            "max_trajectory_deviation": float(deviation.max()),
            "t_arrived_s": e.t_arrived_s,
            "t_arrived_true_feedback_s": self.true_run.t_arrived_s,
            "final": {"x": float(e.x[-1]), "z": float(e.z[-1]), "theta_deg": float(e.theta_deg[-1])},
            "final_true_feedback": {
                "x": float(self.true_run.x[-1]),
                "z": float(self.true_run.z[-1]),
                "theta_deg": float(self.true_run.theta_deg[-1]),
            },
            "frames": int(e.t_s.size),
            "frames_out_of_view": e.out_of_view,
            "estimation_failures": e.failures,
            "length_unit": "cm",
            "setup": self.setup.to_json_dict(),
        }


def run_unicycle(setup: UnicycleSetup) -> UnicycleResult:
    return UnicycleResult(setup, simulate(setup, feedback="true"), simulate(setup, feedback="estimated"))


def _sci(value: Optional[float]) -> str:
    return "n/a (no estimate)" if value is None else f"{value:.3e}"


def _when(t_s: Optional[float]) -> str:
    return "never" if t_s is None else f"at {t_s:.2f} s"


def format_unicycle(result: UnicycleResult) -> str:
    d = result.to_json_dict()
    s = result.setup
    lines = [
        f"unicycle robot (eqs 18-22): start ({s.start[0]:g}, {s.start[1]:g}) cm, heading "
        f"{s.start[2]:g} deg, goal ({s.goal[0]:g}, {s.goal[1]:g}) cm, stop within "
        f"{s.goal_radius:g} cm",
        f"kv {s.kv:g}/s, kw {s.kw:g}/s, dt {s.dt_s:.4f} s, {s.duration_s:g} s; window "
        f"{s.window_side:g} cm, camera {s.camera.width}x{s.camera.height} f = {s.camera.fx:g} px, "
        f"{s.camera_below:g} cm below the window's centre",
        f"estimator {s.method}, {s.iterations} iterations, refine {'on' if s.refine else 'off'}, "
        f"pixel noise {s.noise_px:g} px (seed {s.seed})",
        "",
        f"{'max heading error':<30}{_sci(d['max_heading_error_deg'])} deg",
        f"{'rms heading error':<30}{_sci(d['rms_heading_error_deg'])} deg",
        f"{'max x error':<30}{_sci(d['max_x_error'])} cm",
        f"{'max z error':<30}{_sci(d['max_z_error'])} cm",
        f"{'max deviation from the':<30}",
        f"{'  true-feedback trajectory':<30}{d['max_trajectory_deviation']:.3e} cm",
        f"{'final (estimated feedback)':<30}x {d['final']['x']:.3f}, z {d['final']['z']:.3f} cm, "
        f"heading {d['final']['theta_deg']:.3f} deg",
        f"{'final (true feedback)':<30}x {d['final_true_feedback']['x']:.3f}, "
        f"z {d['final_true_feedback']['z']:.3f} cm, "
        f"heading {d['final_true_feedback']['theta_deg']:.3f} deg",
        f"{'arrived (within ' + format(s.goal_radius, 'g') + ' cm)':<30}"
        f"{_when(d['t_arrived_s'])} (true feedback: {_when(d['t_arrived_true_feedback_s'])})",
        f"{'frames (out of view, failed)':<30}{d['frames']} ({d['frames_out_of_view']}, {d['estimation_failures']})",
    ]
    return "\n".join(lines)
