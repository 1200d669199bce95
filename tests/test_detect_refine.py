"""Edge fits and quadrilateral candidates on their own: accuracy, refusals, geometry helpers."""

from __future__ import annotations

import numpy as np
import pytest
from detect_helpers import SQUARE, facing_pose, render, rms

from pose_daemon.detect.quads import find_quads, inside_any
from pose_daemon.detect.refine import fit_edges, signed_area
from pose_daemon.render import Effects


@pytest.fixture(scope="module")
def frame():
    return render(SQUARE, *facing_pose(25, 0.8, 35), seed=800)


def test_fit_from_a_pixel_off_reaches_the_true_corners(frame) -> None:
    image, truth = frame
    start = truth + np.array([[0.9, -0.6], [-0.7, 0.8], [0.5, 0.9], [-0.8, -0.4]])
    fit = fit_edges(image, start, inner_px=3.0, outer_px=3.0)
    assert fit is not None
    assert rms(fit.corners, truth) < 0.05
    assert fit.residual_px < 0.1 and fit.valid_fraction > 0.9
    assert 150 < fit.contrast < 230  # white 220 and ink 25 under the lighting gradient


@pytest.mark.parametrize("inner, outer", [(1.5, 3.0), (3.0, 1.5), (2.0, 2.0)])
def test_short_or_lopsided_profiles_stay_unbiased(frame, inner: float, outer: float) -> None:
    # The half-way level is re-taken symmetrically about the edge, so profiles that do not
    # reach the dark or the light plateau do not shift the sides.
    image, truth = frame
    fit = fit_edges(image, truth + 0.4, inner_px=inner, outer_px=outer)
    assert fit is not None and rms(fit.corners, truth) < 0.06


def test_fit_refuses_what_is_not_a_dark_quadrilateral(frame) -> None:
    image, truth = frame
    flat = np.full_like(image, 128)
    assert fit_edges(flat, truth, inner_px=3.0, outer_px=3.0) is None
    # Corners that would have to move further than allowed.
    assert fit_edges(image, truth + 1.5, inner_px=3.0, outer_px=3.0, max_move_px=1.0) is None
    # Counter-clockwise corners describe a light region on a dark surround.
    assert fit_edges(image, truth[::-1].copy(), inner_px=3.0, outer_px=3.0) is None


def test_quads_are_clockwise_and_within_a_pixel(frame) -> None:
    image, truth = frame
    for downscale in (1, 2):
        quads = find_quads(image, min_side_px=10, block_px=25, offset_gray=10.0, downscale=downscale)
        near = [q for q in quads if np.abs(q.mean(axis=0) - truth.mean(axis=0)).max() < 3]
        assert near, f"no candidate at downscale {downscale}"
        q = near[0]
        assert signed_area(q) > 0
        err = min(np.abs(np.roll(q, -k, axis=0) - truth).max() for k in range(4))
        assert err < 1.5 * downscale


def test_quads_keep_elongated_and_tilted_outlines_and_drop_ragged_ones() -> None:
    """The compactness bound (quads.MIN_COMPACTNESS) before any polygon fit: a 6:1
    rectangle and a small square turned 30 deg stay candidates; a square whose rim is
    combed into teeth (texture, pile) has a four-point hull but is no candidate."""
    import cv2

    image = np.full((240, 320), 220, np.uint8)
    cv2.rectangle(image, (20, 20), (109, 34), 30, -1)  # 90 x 15: 6:1
    box = cv2.boxPoints(((200.0, 60.0), (14.0, 14.0), 30.0))
    cv2.fillConvexPoly(image, np.round(box * 16).astype(np.int32), 30, cv2.LINE_AA, shift=4)
    image[140:200, 200:260] = 30
    for k in range(0, 60, 3):  # light notches 1 px wide, 3 px deep, all round the rim
        image[140:143, 200 + k] = image[197:200, 200 + k] = 220
        image[140 + k, 200:203] = image[140 + k, 257:260] = 220
    quads = find_quads(image, min_side_px=10, block_px=25, offset_gray=10.0)
    centres = sorted((round(float(x)), round(float(y))) for x, y in (q.mean(axis=0) for q in quads))
    assert len(centres) == 2, centres
    assert abs(centres[0][0] - 65) <= 1 and abs(centres[0][1] - 27) <= 1
    assert abs(centres[1][0] - 200) <= 1 and abs(centres[1][1] - 60) <= 1


def test_no_quads_in_a_smooth_empty_scene() -> None:
    image, _ = render(
        SQUARE, *facing_pose(0, 50.0), seed=801, effects=Effects(background="plain", lighting_gradient=0.5)
    )
    assert find_quads(image, min_side_px=10, block_px=25) == []


def test_signed_area_and_containment() -> None:
    square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    assert signed_area(square) == pytest.approx(100.0)
    assert signed_area(square[::-1]) == pytest.approx(-100.0)
    assert inside_any(np.array([5.0, 5.0]), [square])
    assert not inside_any(np.array([11.0, 5.0]), [square])
    assert not inside_any(np.array([5.0, 5.0]), [])
