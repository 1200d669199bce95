"""``pose-daemon replay PATH [--config FILE] [--out FILE] [--annotate DIR]``: the pipeline over
a recording, a folder of images or a video, as fast as it goes; one JSON object per frame."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from ..config import load_config_or_default
from ..errors import EndOfStream, SourceError, UserError
from ..geometry import R_from_rvec, rotation_angle_deg


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("replay", help="run detection and pose over a recording, image folder or video",
                            description=__doc__.splitlines()[0])
    parser.add_argument("path", metavar="PATH", help="recording folder, folder of images or video file")
    parser.add_argument("--config", metavar="FILE",
                        help="TOML config: camera and marker when the recording has none, estimator, detector")
    parser.add_argument("--out", metavar="FILE", help="write the JSON lines here (default: stdout)")
    parser.add_argument("--annotate", metavar="DIR", help="also write each frame with corners, axes and pose")
    parser.set_defaults(func=run)


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
            self.corner_px.append(float(np.sqrt((d ** 2).sum(axis=1).mean())))
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
        for name, values in (("corner_rms_px", self.corner_px), ("rotation_deg", self.rotation_deg),
                             ("translation_m", self.translation_m)):
            out[f"{name}_median"] = float(np.median(values)) if values else None
            out[f"{name}_p95"] = float(np.percentile(values, 95)) if values else None
        return out

    def report(self) -> str:
        s = self.summary()

        def f(v: Optional[float], scale: float = 1.0, fmt: str = "{:.3f}") -> str:
            return "-" if v is None else fmt.format(v * scale)

        rate = s["detection_rate"]
        return "\n".join([
            f"accuracy against the recorded truth ({self.frames} frames)",
            f"  detection rate        {f(rate, 100, '{:.1f}')} % ({self.detected}/{self.frames})",
            "                        median      p95",
            f"  corner error px       {f(s['corner_rms_px_median']):>8} {f(s['corner_rms_px_p95']):>8}",
            f"  rotation error deg    {f(s['rotation_deg_median']):>8} {f(s['rotation_deg_p95']):>8}",
            f"  translation error mm  {f(s['translation_m_median'], 1e3, '{:.1f}'):>8} "
            f"{f(s['translation_m_p95'], 1e3, '{:.1f}'):>8}",
        ])


def run(args: argparse.Namespace) -> int:
    from ..capture import recording
    from ..capture.replay import ReplaySource
    from ..detect import MarkerDetector
    from ..processing import FrameProcessor

    source = ReplaySource(args.path, realtime=False)
    try:
        source.open()
    except SourceError as exc:
        raise UserError(str(exc)) from None
    cfg = load_config_or_default(args.config)
    try:
        rec_camera = recording.camera_from_meta(source.meta)
        rec_marker = recording.marker_from_meta(source.meta)
    except SourceError as exc:
        source.close()
        raise UserError(f"{args.path}: {exc}") from None
    camera = rec_camera or cfg.camera.model()
    marker = rec_marker or cfg.marker.model()
    if args.config:
        # The recording's own camera and marker are what its frames were taken with; say so
        # when --config names others, so that new intrinsics are not thought to be in use.
        ignored = [name for name, rec, conf, to_dict in (
            ("[camera]", rec_camera, cfg.camera.model(), recording.camera_to_dict),
            ("[marker]", rec_marker, cfg.marker.model(), recording.marker_to_dict))
            if rec is not None and to_dict(rec) != to_dict(conf)]
        if ignored:
            print(f"pose-daemon: note: {args.path} has its own {' and '.join(ignored)}, used instead of "
                  f"those of {args.config}", file=sys.stderr)
    detector = MarkerDetector(marker, max_misses=cfg.detector.max_misses,
                              min_side_px=cfg.detector.min_side_px, camera=camera)
    from ..geometry import VehicleFrames
    from ..pose.prior import PriorSettings

    processor = FrameProcessor(camera, marker, method=cfg.estimator.method,
                               iterations=cfg.estimator.iterations, refine=cfg.estimator.refine,
                               detector=detector, prior=PriorSettings.from_config(cfg),
                               frames=VehicleFrames.from_config(cfg.mount, cfg.marker.placement))
    annotate_dir: Optional[Path] = None
    if args.annotate:
        annotate_dir = Path(args.annotate)
        try:
            annotate_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            source.close()
            raise UserError(f"cannot create --annotate folder {annotate_dir}: {exc}") from None
    try:
        out = open(args.out, "w") if args.out else sys.stdout
    except OSError as exc:
        source.close()
        raise UserError(f"cannot write --out {args.out}: {exc.strerror or exc}") from None
    accuracy = Accuracy()
    count = 0
    try:
        while True:
            try:
                frame = source.read()
            except EndOfStream:
                break
            except SourceError as exc:  # a video that cannot decode on: the rest is lost
                print(f"pose-daemon: {exc}; stopping", file=sys.stderr)
                break
            result = processor.process(frame)
            # Replay has no live clock: latency is the processing time of the frame.
            result.latency_s = sum(result.stage_s.values())
            out.write(json.dumps(result.to_json_dict()) + "\n")
            accuracy.add(result, frame.metadata)
            count += 1
            if annotate_dir is not None:
                import cv2

                from ..draw import annotate

                image = annotate(frame.image, result, camera, marker, frame.metadata.get("true_corners"))
                cv2.imwrite(str(annotate_dir / f"{frame.seq:06d}.png"), image)
    finally:
        if out is not sys.stdout:
            out.close()
        else:
            out.flush()
        source.close()
    if source.skipped:
        print(f"pose-daemon: skipped {len(source.skipped)} unreadable frame(s): "
              + ", ".join(Path(f).name for f, _ in source.skipped[:10]), file=sys.stderr)
    if accuracy.frames:
        print(accuracy.report(), file=sys.stderr)
    if count == 0:
        raise UserError(f"{args.path}: no frame could be read")
    return 0
