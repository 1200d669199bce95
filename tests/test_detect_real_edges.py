"""A LifeCam-like render (issue 35): the real frames' size bias and its cure, on the renderer.

scripts/real_edge_bias.py measured on a LifeCam HD-3000's chessboard frames a size bias of
-3.0 % read as linear, +2.0 % read as sRGB, and 0.0 % read at the camera's own exponent 1.6
(docs/accuracy.md, real camera edges). The renderer makes the same kind of frame (response
exponent 1.6, in-camera sharpening, JPEG 85, a defocus of 2 px): read at the exponent the
camera has, the edge fit is unbiased within the issue's 0.3 %; read as sRGB, the marker comes
out too large, as on the real frames."""

from __future__ import annotations

import dataclasses

import numpy as np

from pose_daemon import Camera, Marker, MarkerDetector
from pose_daemon.detect.square import side_lengths
from pose_daemon.render import Effects, random_pose, render_frame

CAMERA = Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
SQUARE = Marker(0.2, 0.2)
LIFECAM = Effects(blur_px=2.0, noise_gray=2.0, gamma=1.6, sharpen=0.6, jpeg_quality=85)
SIZE_BIAS_BOUND_PCT = 0.3


def _size_bias_pct(gamma, effects: Effects = LIFECAM, gamma_shoulder: float = 0.0) -> float:
    """The mean size bias (detected / true perimeter - 1, %) over eight LifeCam-like frames."""
    rng = np.random.default_rng(3)
    bias = []
    for i in range(8):
        rvec, tvec = random_pose(rng, CAMERA, SQUARE, distance_m=(0.5, 2.0), max_tilt_deg=40.0)
        image, truth = render_frame(CAMERA, SQUARE, rvec, tvec, effects=effects, rng=np.random.default_rng(i))
        corners = MarkerDetector(SQUARE, gamma=gamma, gamma_shoulder=gamma_shoulder).detect(image)
        assert corners is not None, f"frame {i}: not found"
        bias.append(100.0 * (side_lengths(corners).sum() / side_lengths(truth).sum() - 1.0))
    return float(np.mean(bias))


def test_a_lifecam_like_frame_read_at_its_own_exponent_is_unbiased_and_as_srgb_too_large() -> None:
    assert abs(_size_bias_pct(1.6)) <= SIZE_BIAS_BOUND_PCT
    assert _size_bias_pct("srgb") > 0.5


def test_a_response_with_a_shoulder_read_at_its_two_parameters_is_unbiased_at_any_exposure() -> None:
    # The LifeCam's own frames: its exponent rises towards white (about 1.3 at a white level of
    # 100, 2 at 230; docs/accuracy.md), so one exponent suits one exposure. Rendered so (1.5 at
    # mid grey, rising by 1.6 from black to white), a dim and a bright frame read at the
    # camera's two parameters are both unbiased; read at one exponent they differ by over 1 %.
    dim, bright = (
        dataclasses.replace(LIFECAM, gamma=1.5, gamma_shoulder=1.6, white=white, black=black)
        for white, black in ((105.0, 5.0), (225.0, 15.0))
    )
    for effects in (dim, bright):
        assert abs(_size_bias_pct(1.5, effects, gamma_shoulder=1.6)) <= SIZE_BIAS_BOUND_PCT
    for gamma in (1.3, 1.5, 1.9):
        assert _size_bias_pct(gamma, dim) - _size_bias_pct(gamma, bright) > 0.8
