"""Small markers (issue 35): every 6x6 ArUco marker OpenCV's detector decodes at 16 px and up is
found too, on the same frames."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pose_daemon import Camera, Marker, MarkerDetector
from pose_daemon.detect import aruco_compat
from pose_daemon.detect.square import side_lengths
from pose_daemon.render import Effects, facing_pose, inside_image, render_frame

CAMERA = Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
DICTIONARY = "DICT_6X6_250"
MARKER = Marker(0.2, 0.2, type="aruco", dictionary=DICTIONARY, id=7)
#: What a webcam gives: sRGB-encoded, sharpened, JPEG; read as the default linear response.
WEBCAM = dict(noise_gray=2.0, gamma="srgb", jpeg_quality=90, sharpen=0.8)


def _opencv_finds(image: np.ndarray) -> bool:
    finder = aruco_compat.ArucoMarkerFinder(
        aruco_compat.get_dictionary(DICTIONARY), aruco_compat.make_parameters(corner_refine="subpix")
    )
    _, ids = finder.detect(image)
    return MARKER.id in [int(i) for i in ids]


def _found(image: np.ndarray, truth: np.ndarray) -> bool:
    corners = MarkerDetector(MARKER).detect(image)
    return corners is not None and float(np.abs(corners - truth).max()) < 1.5


#: A 6x6 marker 18 x 25 px, 40-65 deg off its face, whose rough outline (the threshold's, up
#: to a pixel inside the edge: half a 2 px cell) read as another code: (rvec, tvec,
#: background, blur px, lighting gradient, noise seed).
MISREAD = [
    ([-2.4974, 0.1275, 0.1484], [0.9614, 0.5461, 4.0975], "texture", 0.622, 0.236, 71),
]


@pytest.mark.parametrize("rvec, tvec, background, blur, gradient, seed", MISREAD)
def test_a_small_marker_whose_rough_outline_misreads_is_found_as_opencv_finds_it(
    rvec, tvec, background: str, blur: float, gradient: float, seed: int
) -> None:
    effects = Effects(background=background, blur_px=blur, lighting_gradient=gradient, **WEBCAM)
    image, truth = render_frame(CAMERA, MARKER, rvec, tvec, effects=effects, rng=np.random.default_rng(seed))
    assert side_lengths(truth).min() >= 16.0
    assert _opencv_finds(image)
    assert _found(image, truth)


@pytest.mark.parametrize("seed", [0, 1])
def test_every_small_marker_opencv_decodes_is_found(seed: int) -> None:
    """16-24 px markers anywhere in the frame, 0-60 deg off their face, webcam-like frames:
    whatever OpenCV decodes (and usually more) is found."""
    rng = np.random.default_rng([35, seed])
    decoded = found = 0
    for i in range(12):
        while True:
            side_px = rng.uniform(16.0, 24.0)
            centre = (CAMERA.cx + rng.uniform(-0.45, 0.45) * CAMERA.width, CAMERA.cy + rng.uniform(-0.4, 0.4) * 480)
            rvec, tvec = facing_pose(
                CAMERA,
                centre,
                CAMERA.fx * MARKER.width / side_px,
                rng.uniform(0, 2 * math.pi),
                rng.uniform(0.0, 60.0),
                rng.uniform(-math.pi, math.pi),
            )
            if not inside_image(CAMERA, MARKER, rvec, tvec):
                continue
            effects = Effects(
                background="texture" if i % 2 else "plain",
                blur_px=float(rng.uniform(0.5, 1.0)),
                lighting_gradient=float(rng.uniform(0.0, 0.5)),
                **WEBCAM,
            )
            image, truth = render_frame(CAMERA, MARKER, rvec, tvec, effects=effects, rng=np.random.default_rng(i))
            if side_lengths(truth).min() >= 16.0:
                break
        if _opencv_finds(image):
            decoded += 1
            assert _found(image, truth), f"frame {i}: OpenCV decodes the marker, the detector misses it"
        found += _found(image, truth)
    assert decoded >= 2 and found >= decoded
