"""Per-frame processing: a bad frame costs that frame only."""

from __future__ import annotations

import numpy as np

from pose_daemon.capture.base import Frame
from pose_daemon.processing import FrameProcessor
from pose_daemon.render import Effects, render_marker


def test_wrong_size_and_empty_frames_become_frame_errors_and_processing_goes_on(camera, marker):
    processor = FrameProcessor(camera, marker)
    rendered = render_marker(
        camera, marker, np.array([np.pi, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), effects=Effects.clean()
    )
    bad = [np.zeros((240, 320), np.uint8), np.zeros((0, 0), np.uint8), np.zeros((480, 640), np.float64)]
    for seq, image in enumerate(bad):
        result = processor.process(Frame(image=image, t_capture_s=float(seq), seq=seq))
        assert not result.ok and result.error.startswith("bad frame: "), result.error
        assert "detect" in result.stage_s
    good = processor.process(Frame(image=rendered.image, t_capture_s=9.0, seq=9))
    assert good.ok
    assert np.abs(good.corners - rendered.corners_px).max() < 0.1
    assert np.abs(good.pose.tvec - [0.0, 0.0, 1.0]).max() < 1e-3
