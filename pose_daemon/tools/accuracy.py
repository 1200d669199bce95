"""Accuracy of per-frame results against the truth a recording carries (the renderer's):
detection rate and corner, rotation and translation errors, as figures and as a report."""

from __future__ import annotations

from typing import Dict, List, Optional

import numpy as np

from ..geometry import R_from_rvec, rotation_angle_deg


class Accuracy:
    """Errors of each frame against the recorded truth (marker pose in the camera frame)."""

    def __init__(self) -> None:
        self.frames = 0
        self.detected = 0
        self.corner_px: List[float] = []
        self.rotation_deg: List[float] = []
        self.translation_m: List[float] = []

    def add(self, result, metadata: Dict) -> None:
        if "true_rvec" not in metadata:
            return
        self.frames += 1
        if result.corners is None:
            return
        self.detected += 1
        if "true_corners" in metadata:
            d = np.asarray(result.corners, dtype=np.float64) - metadata["true_corners"]
            self.corner_px.append(float(np.sqrt((d**2).sum(axis=1).mean())))
        if result.pose is not None:
            R_true = R_from_rvec(np.asarray(metadata["true_rvec"], dtype=np.float64))
            self.rotation_deg.append(float(rotation_angle_deg(R_true, result.pose.R)))
            self.translation_m.append(float(np.linalg.norm(np.asarray(result.pose.tvec) - metadata["true_tvec"])))

    def summary(self) -> Dict[str, Optional[float]]:
        """detection_rate, and median / p95 of corner_rms_px, rotation_deg and translation_m."""
        out: Dict[str, Optional[float]] = {
            "frames": float(self.frames),
            "detection_rate": self.detected / self.frames if self.frames else None,
            "poses": float(len(self.rotation_deg)),
        }
        for name, values in (
            ("corner_rms_px", self.corner_px),
            ("rotation_deg", self.rotation_deg),
            ("translation_m", self.translation_m),
        ):
            out[f"{name}_median"] = float(np.median(values)) if values else None
            out[f"{name}_p95"] = float(np.percentile(values, 95)) if values else None
        return out

    def report(self) -> str:
        s = self.summary()

        def f(v: Optional[float], scale: float = 1.0, fmt: str = "{:.3f}") -> str:
            return "-" if v is None else fmt.format(v * scale)

        rate = s["detection_rate"]
        return "\n".join(
            [
                f"accuracy against the recorded truth ({self.frames} frames)",
                f"  detection rate        {f(rate, 100, '{:.1f}')} % ({self.detected}/{self.frames})",
                "                        median      p95",
                f"  corner error px       {f(s['corner_rms_px_median']):>8} {f(s['corner_rms_px_p95']):>8}",
                f"  rotation error deg    {f(s['rotation_deg_median']):>8} {f(s['rotation_deg_p95']):>8}",
                f"  translation error mm  {f(s['translation_m_median'], 1e3, '{:.1f}'):>8} "
                f"{f(s['translation_m_p95'], 1e3, '{:.1f}'):>8}",
            ]
        )
