"""Edges of gamma-encoded (real-camera) frames: located in linear light, no size bias with blur."""

from __future__ import annotations

import numpy as np
import pytest
from detect_helpers import ARUCO, CAM, SQUARE, aligned, render

from pose_daemon import Marker, MarkerDetector
from pose_daemon.detect.square import side_lengths
from pose_daemon.render import Effects, random_pose


def _errors(marker: Marker, gamma, detector_gamma, blurs=(0.8, 1.2, 1.5), per_blur: int = 4):
    """(size bias of each detection, corner errors (N, 2), misses) against the renderer's truth."""
    rng = np.random.default_rng(21)
    sizes, errors, misses = [], [], 0
    for blur in blurs:
        for i in range(per_blur):
            rvec, tvec = random_pose(rng, CAM, marker, distance_m=(0.4, 1.0), max_tilt_deg=45)
            image, truth = render(
                marker, rvec, tvec, seed=int(blur * 10) + i, effects=Effects(blur_px=blur, gamma=gamma)
            )
            corners = MarkerDetector(marker, gamma=detector_gamma).detect(image)
            if corners is None:
                misses += 1
                continue
            corners = aligned(corners, truth)
            sizes.append(float(side_lengths(corners).sum() / side_lengths(truth).sum() - 1.0))
            errors.append(corners - truth)
    return np.array(sizes), np.concatenate(errors), misses


@pytest.mark.parametrize("marker", [SQUARE, ARUCO], ids=["square", "aruco"])
@pytest.mark.parametrize("gamma", [2.2, "srgb"])
def test_gamma_encoded_blurred_frames_give_unbiased_corners(marker: Marker, gamma) -> None:
    sizes, err, misses = _errors(marker, gamma, gamma)
    assert misses == 0
    assert abs(float(sizes.mean())) <= 0.002  # |mean size bias| <= 0.2 %
    assert float(np.sqrt(np.mean(np.sum(err**2, axis=1)))) <= 0.1


def test_the_cause_half_way_levels_of_encoded_edges_shrink_the_marker() -> None:
    """Read as if linear, a gamma camera's blurred edge puts the marker well inside its truth."""
    sizes, _, _ = _errors(SQUARE, 2.2, 1.0, blurs=(1.5,), per_blur=3)
    assert len(sizes) and float(sizes.mean()) < -0.01


def test_linear_frames_are_unchanged_by_a_linear_response() -> None:
    rng = np.random.default_rng(3)
    rvec, tvec = random_pose(rng, CAM, ARUCO, distance_m=(0.5, 1.0))
    image, _ = render(ARUCO, rvec, tvec, seed=1)
    a = MarkerDetector(ARUCO).detect(image)
    b = MarkerDetector(ARUCO, gamma=1.0).detect(image)
    assert a is not None and np.array_equal(a, b)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), "cinema", True])
def test_bad_gamma_is_refused(bad) -> None:
    with pytest.raises(ValueError, match="gamma must be a number in"):
        MarkerDetector(SQUARE, gamma=bad)


def test_config_gamma_reaches_the_daemons_detector() -> None:
    from pose_daemon.config import parse_config
    from pose_daemon.errors import ConfigError
    from pose_daemon.processing.marker import FrameProcessor

    cfg = parse_config("[detector]\ngamma = 2.2\n")
    processor = FrameProcessor.from_config(cfg)
    assert processor.detector._finder.options.gamma == 2.2 and processor.detector._finder.lut is not None
    assert FrameProcessor.from_config(parse_config("")).detector._finder.lut is None
    with pytest.raises(ConfigError, match="gamma"):
        parse_config("[detector]\ngamma = 0.0\n")
