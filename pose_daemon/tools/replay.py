"""``pose-daemon replay``: the pipeline's detection and pose over a recording, a folder of
images or a video, as fast as it goes, one JSON object per frame, and the accuracy against
the recorded truth when the recording has it."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

from ..capture import recording
from ..capture.replay import ReplaySource
from ..config import load_config_or_default
from ..errors import EndOfStream, SourceError, UserError
from ..geometry import VehicleFrames
from ..outputs.jsonl import json_line
from ..pipeline import Processor
from ..pose.prior import PriorSettings
from ..processing.marker import FrameProcessor
from ..result import FrameResult
from .accuracy import Accuracy


def _json_line(result: FrameResult) -> str:
    """The outputs' JSON line; a pose that is not finite is written as an error, never as NaN."""
    try:
        return json_line(result)
    except ValueError:
        result.pose = None
        result.error = "pose not finite"
        return json_line(result)


def replay(
    path: str, config: Optional[str] = None, out_path: Optional[str] = None, annotate: Optional[str] = None
) -> int:
    """Every frame of ``path`` through detection and pose estimation, one JSON line per frame
    to ``out_path`` (stdout without one or for "-"), annotated images into the folder ``annotate``; the
    camera and marker are the recording's own when it has them, else ``config``'s. Returns
    the exit status; UserError when nothing could be read."""

    source = ReplaySource(path, realtime=False)
    try:
        source.open()
    except SourceError as exc:
        raise UserError(str(exc)) from None
    cfg = load_config_or_default(config)
    try:
        rec_camera = recording.camera_from_meta(source.meta)
        rec_marker = recording.marker_from_meta(source.meta)
    except SourceError as exc:
        source.close()
        raise UserError(f"{path}: {exc}") from None
    camera = rec_camera or cfg.camera.model()
    marker = rec_marker or cfg.marker.model()
    if config:
        # The recording's own camera and marker are what its frames were taken with; say so
        # when --config names others, so that new intrinsics are not thought to be in use.
        ignored = []
        if rec_camera is not None and (
            recording.camera_to_dict(rec_camera) != recording.camera_to_dict(cfg.camera.model())
        ):
            ignored.append("[camera]")
        if rec_marker is not None and (
            recording.marker_to_dict(rec_marker) != recording.marker_to_dict(cfg.marker.model())
        ):
            ignored.append("[marker]")
        if ignored:
            print(
                f"pose-daemon: note: {path} has its own {' and '.join(ignored)}, used instead of those of {config}",
                file=sys.stderr,
            )
    processor: Processor
    if cfg.map is not None:  # a map names its own markers: the recording's [marker] is not used
        from ..processing.map import MapFrameProcessor

        # The recording's attitude (each frame's own) is the solve's prior term.
        processor = MapFrameProcessor.from_models(
            camera,
            cfg.map.model(),
            cfg.estimator,
            cfg.detector,
            prior=PriorSettings.from_config(cfg),
            frames=VehicleFrames.from_config(cfg.mount, cfg.placement),
        )
    else:
        processor = FrameProcessor.from_models(
            camera,
            marker,
            cfg.estimator,
            cfg.detector,
            prior=PriorSettings.from_config(cfg),
            frames=VehicleFrames.from_config(cfg.mount, cfg.placement),
        )
    annotate_dir: Optional[Path] = None
    if annotate:
        annotate_dir = Path(annotate)
        try:
            annotate_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            source.close()
            raise UserError(f"cannot create --annotate folder {annotate_dir}: {exc}") from None
    try:
        # "-" is stdout, as for [output.jsonl] path and the usual command-line tools.
        out = open(out_path, "w") if out_path and out_path != "-" else sys.stdout
    except OSError as exc:
        source.close()
        raise UserError(f"cannot write --out {out_path}: {exc.strerror or exc}") from None
    accuracy = Accuracy()
    count = 0
    lost = ""
    try:
        while True:
            try:
                frame = source.read()
            except EndOfStream as exc:
                lost = exc.lost
                break
            except SourceError as exc:  # a video that cannot decode on: the rest is lost
                print(f"pose-daemon: {exc}; stopping", file=sys.stderr)
                break
            result = processor.process(frame)
            # Replay has no live clock: latency is the processing time of the frame.
            result.latency_s = sum(result.stage_s.values())
            out.write(_json_line(result) + "\n")
            accuracy.add(result, frame.metadata)
            count += 1
            if annotate_dir is not None:
                import cv2

                from ..draw import annotate as draw_annotation

                image = draw_annotation(frame.image, result, camera, marker, frame.metadata.get("true_corners"))
                cv2.imwrite(str(annotate_dir / f"{frame.seq:06d}.png"), image)
    finally:
        if out is not sys.stdout:
            out.close()
        else:
            out.flush()
        source.close()
    if source.skipped:
        print(
            f"pose-daemon: skipped {len(source.skipped)} unreadable frame(s): "
            + ", ".join(Path(f).name for f, _ in source.skipped[:10]),
            file=sys.stderr,
        )
    if lost:
        print(f"pose-daemon: {lost}", file=sys.stderr)
    if accuracy.frames:
        print(accuracy.report(), file=sys.stderr)
    if count == 0:
        raise UserError(f"{path}: no frame could be read")
    return 0
