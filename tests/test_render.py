"""Renderer truth: the reported corners are where an unbiased detector finds them."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from pose_daemon import Camera, Marker
from pose_daemon.detect.response import decode, encode
from pose_daemon.geometry import R_from_rvec
from pose_daemon.render import (
    Effects,
    random_pose,
    render_empty,
    render_marker,
    render_plane,
    trajectory,
)

CAM = Camera(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=640, height=480)
# A wide-angle lens with strong barrel distortion, like the Pi camera's wide modules.
CAM_DIST = Camera(
    fx=420.0, fy=420.0, cx=322.0, cy=236.0, dist=(-0.28, 0.09, 0.001, -0.0008, -0.012), width=640, height=480
)
ARUCO = Marker(0.2, 0.2, type="aruco", dictionary="DICT_4X4_50", id=7)
SQUARE = Marker(0.2, 0.2)
WHITE, BLACK = 220.0, 25.0


def _aruco_detect(image: np.ndarray, dictionary: str):
    aruco = cv2.aruco
    d = aruco.getPredefinedDictionary(getattr(aruco, dictionary))
    if hasattr(aruco, "ArucoDetector"):
        params = aruco.DetectorParameters()
    else:
        params = aruco.DetectorParameters_create()
    params.cornerRefinementMethod = aruco.CORNER_REFINE_SUBPIX
    params.cornerRefinementMinAccuracy = 0.001
    params.cornerRefinementMaxIterations = 100
    if hasattr(aruco, "ArucoDetector"):
        corners, ids, _ = aruco.ArucoDetector(d, params).detectMarkers(image)
    else:
        corners, ids, _ = aruco.detectMarkers(image, d, parameters=params)
    return corners, ids


@pytest.mark.parametrize("camera", [CAM, CAM_DIST], ids=["pinhole", "distorted"])
def test_aruco_detector_finds_the_rendered_corners_without_offset(camera: Camera) -> None:
    rng = np.random.default_rng(11)
    errors = []
    for _ in range(40):
        rvec, tvec = random_pose(rng, camera, ARUCO, (0.5, 1.6), 50)
        frame = render_marker(camera, ARUCO, rvec, tvec, effects=Effects.clean(), rng=rng)
        assert frame.visible
        corners, ids = _aruco_detect(frame.image, "DICT_4X4_50")
        if ids is None or 7 not in ids.ravel():
            continue
        found = corners[list(ids.ravel()).index(7)].reshape(4, 2)
        errors.append(found - frame.corners_px)  # same order: the marker's orientation is right
    e = np.array(errors).reshape(-1, 2)
    assert len(errors) >= 34
    # No systematic offset; per-corner scatter is the detector's own (cornerSubPix on
    # L-shaped corners), about 0.2 px on these frames.
    assert np.all(np.abs(e.mean(axis=0)) < 0.03), e.mean(axis=0)
    assert np.sqrt((e**2).sum(axis=1).mean()) < 0.3
    assert np.abs(e).max() < 0.8


@pytest.mark.parametrize("camera", [CAM, CAM_DIST], ids=["pinhole", "distorted"])
def test_chessboard_saddles_land_on_their_projections(camera: Camera) -> None:
    # Saddle points are what cornerSubPix finds without bias: a sharp check of the renderer's
    # geometry (pixel-centre convention, distortion, plane mapping) to a few hundredths of a px.
    squares, sq_px = (9, 7), 40
    board = np.kron(
        (np.indices(squares[::-1]).sum(axis=0) % 2) * (WHITE - BLACK) + BLACK, np.ones((sq_px, sq_px))
    ).astype(np.uint8)
    margin = sq_px
    texture = np.full((board.shape[0] + 2 * margin, board.shape[1] + 2 * margin), WHITE, np.uint8)
    texture[margin:-margin, margin:-margin] = board
    sq_m = 0.03
    size_m = (texture.shape[1] / sq_px * sq_m, texture.shape[0] / sq_px * sq_m)
    # Inner corners in the plane frame (x right, y up; texture row 0 at the top).
    xs = (np.arange(1, squares[0]) - squares[0] / 2) * sq_m
    ys = (squares[1] / 2 - np.arange(1, squares[1])) * sq_m
    grid = np.array([[x, y, 0.0] for y in ys for x in xs])
    rng = np.random.default_rng(5)
    all_err = []
    for _ in range(6):
        rvec, tvec = random_pose(rng, camera, Marker(size_m[0], size_m[1]), (0.55, 0.8), 35)
        image = render_plane(camera, texture, size_m, rvec, tvec, effects=Effects.clean(), rng=rng)
        truth = camera.project(grid @ R_from_rvec(rvec).T + tvec)
        refined = cv2.cornerSubPix(
            image,
            truth.astype(np.float32).reshape(-1, 1, 2).copy(),
            (5, 5),
            (-1, -1),
            (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4),
        )
        all_err.append(refined.reshape(-1, 2) - truth)
    e = np.concatenate(all_err)
    assert np.all(np.abs(e.mean(axis=0)) < 0.01), e.mean(axis=0)
    assert np.sqrt((e**2).sum(axis=1).mean()) < 0.08
    assert np.abs(e).max() < 0.25


def test_dark_area_equals_the_projected_area() -> None:
    # Anti-aliasing conserves area: the darkness summed over the frame is the area of the
    # projected dark square, so edges are neither pushed out nor pulled in.
    rng = np.random.default_rng(2)
    effects = Effects.clean(background="plain", plain_gray=WHITE)
    for _ in range(10):
        rvec, tvec = random_pose(rng, CAM, SQUARE, (0.6, 2.5), 60)
        frame = render_marker(CAM, SQUARE, rvec, tvec, effects=effects, rng=rng)
        darkness = ((WHITE - frame.image.astype(np.float64)) / (WHITE - BLACK)).sum()
        area = cv2.contourArea(frame.corners_px.astype(np.float32))
        perimeter = cv2.arcLength(frame.corners_px.astype(np.float32), True)
        # 8-bit rounding is at most half a grey level per pixel of edge.
        assert abs(darkness - area) < 0.02 * perimeter + 2.0, (darkness, area)


def test_square_marker_has_its_dark_region_and_white_quiet_zone() -> None:
    rvec = np.array([math.pi, 0.0, 0.0])  # facing the camera, upright
    frame = render_marker(CAM, SQUARE, rvec, [0.0, 0.0, 1.0], effects=Effects.clean(background="plain"))
    c = frame.corners_px
    assert frame.visible
    np.testing.assert_allclose(c, [[259.5, 179.5], [379.5, 179.5], [379.5, 299.5], [259.5, 299.5]], atol=1e-9)
    img = frame.image
    assert img[240, 320] == round(BLACK)
    assert img[240, 259 - 10] == round(WHITE)  # quiet zone: 0.25 x 120 px = 30 px
    assert img[240, 259 - 40] == 128  # plain background beyond it
    # An edge on a pixel boundary (259.5, between columns 259 and 260): the anti-aliasing
    # filter (one pixel box plus a fraction of a pixel of texture filtering) is symmetric.
    assert img[240, 258] == round(WHITE) and img[240, 261] == round(BLACK)
    assert abs(int(img[240, 259]) + int(img[240, 260]) - (WHITE + BLACK)) <= 1
    assert img[240, 259] > WHITE - 0.1 * (WHITE - BLACK)


def test_aruco_orientation_follows_the_pose() -> None:
    # The marker turned by 90 deg in its plane: the detector's corner 0 is still our TL.
    for roll in (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi):
        R = R_from_rvec(np.array([0, 0, roll])) @ R_from_rvec(np.array([math.pi, 0, 0]))
        rvec = cv2.Rodrigues(R)[0].ravel()
        frame = render_marker(CAM, ARUCO, rvec, [0.02, -0.01, 0.9], effects=Effects.clean())
        corners, ids = _aruco_detect(frame.image, "DICT_4X4_50")
        assert ids is not None and list(ids.ravel()) == [7]
        np.testing.assert_allclose(corners[0].reshape(4, 2), frame.corners_px, atol=0.5)


def test_marker_behind_or_turned_away_is_not_visible() -> None:
    away = render_marker(CAM, SQUARE, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], effects=Effects.clean())
    assert not away.visible  # its back faces the camera
    behind = render_marker(
        CAM, SQUARE, [math.pi, 0.0, 0.0], [0.0, 0.0, -1.0], effects=Effects.clean(background="plain")
    )
    assert not behind.visible
    assert np.all(behind.image == 128)
    off = render_marker(CAM, SQUARE, [math.pi, 0.0, 0.0], [2.0, 0.0, 1.0], effects=Effects.clean())
    assert not off.visible


def test_effects_and_seeds() -> None:
    rvec, tvec = [math.pi, 0.0, 0.0], [0.0, 0.0, 1.0]
    a = render_marker(CAM, SQUARE, rvec, tvec, rng=np.random.default_rng(4)).image
    b = render_marker(CAM, SQUARE, rvec, tvec, rng=np.random.default_rng(4)).image
    c = render_marker(CAM, SQUARE, rvec, tvec, rng=np.random.default_rng(5)).image
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    clean = render_marker(CAM, SQUARE, rvec, tvec, effects=Effects.clean(background="plain")).image
    noisy = render_marker(
        CAM, SQUARE, rvec, tvec, rng=np.random.default_rng(1), effects=Effects.clean(background="plain", noise_gray=4.0)
    ).image
    diff = noisy.astype(float) - clean
    assert 3.5 < diff[200:280, 280:360].std() < 4.5  # inside the dark square
    blurred = render_marker(CAM, SQUARE, rvec, tvec, effects=Effects.clean(background="plain", blur_px=2.0)).image
    # Blur spreads the edge: the pixel just outside darkens, the one just inside lightens.
    assert blurred[240, 257] < clean[240, 257] - 20 and blurred[240, 262] > clean[240, 262] + 20
    jpeg = render_marker(CAM, SQUARE, rvec, tvec, effects=Effects.clean(jpeg_quality=30)).image
    assert jpeg.shape == (480, 640) and not np.array_equal(
        jpeg, render_marker(CAM, SQUARE, rvec, tvec, effects=Effects.clean()).image
    )
    moving = render_marker(
        CAM,
        SQUARE,
        rvec,
        tvec,
        effects=Effects.clean(background="plain", motion_blur_px=8.0, motion_blur_angle_deg=0.0),
    ).image
    # Horizontal smear: vertical edges spread, horizontal edges stay sharp.
    assert moving[240, 262] > clean[240, 262] + 25
    assert abs(int(moving[200, 320]) - int(clean[200, 320])) <= 2
    lit = render_empty(
        CAM, effects=Effects.clean(background="plain", lighting_gradient=0.4), rng=np.random.default_rng(0)
    )
    assert (lit.max() - lit.min()) / 128.0 == pytest.approx(0.4, abs=0.02)


@pytest.mark.parametrize("gamma", [2.2, "srgb"])
def test_a_gamma_camera_blurs_in_linear_light_then_encodes(gamma) -> None:
    """A real camera's frame: the scene blurs in linear light, the camera then encodes it.
    Flat paper and ink keep the levels set; a blurred edge is the encoded linear blur."""
    rvec, tvec = [math.pi, 0.0, 0.0], [0.0, 0.0, 1.0]
    fx = dict(background="plain", plain_gray=180.0, blur_px=2.0)
    encoded = render_marker(CAM, SQUARE, rvec, tvec, effects=Effects.clean(gamma=gamma, **fx)).image
    white, black, grey = decode(np.array([WHITE, BLACK, 180.0]), gamma).tolist()
    linear = render_marker(
        CAM,
        SQUARE,
        rvec,
        tvec,
        effects=Effects.clean(white=white, black=black, background="plain", plain_gray=grey, blur_px=2.0),
    ).image
    # Rounded to 8 bits in between: the encoding's slope in the darks magnifies that step.
    expected = encode(linear.astype(float), gamma)
    assert np.abs(encoded - expected).max() <= 0.6 * (encode(np.array([1.0]), gamma)[0] - 0.0) + 1.0
    assert encoded[240, 320] == pytest.approx(BLACK, abs=1) and encoded[240, 245] == pytest.approx(WHITE, abs=1)
    # The half-way grey level of the encoded edge lies inside the true edge (x = 259.5).
    row = encoded[240, 250:270].astype(float)
    half = 0.5 * (BLACK + WHITE)
    crossing = 250 + np.interp(half, row[::-1], np.arange(20)[::-1])
    assert crossing > 259.5 + 0.5


def test_sharpening_overshoots_both_sides_of_an_edge() -> None:
    rvec, tvec = [math.pi, 0.0, 0.0], [0.0, 0.0, 1.0]
    fx = dict(background="plain", plain_gray=150.0, blur_px=1.0, white=200.0, black=60.0)
    soft = render_marker(CAM, SQUARE, rvec, tvec, effects=Effects.clean(**fx)).image.astype(int)
    sharp = render_marker(CAM, SQUARE, rvec, tvec, effects=Effects.clean(sharpen=2.0, **fx)).image.astype(int)
    row_soft, row_sharp = soft[240, 250:270], sharp[240, 250:270]
    assert row_sharp.max() > row_soft.max() + 3 and row_sharp.min() < row_soft.min() - 3
    # Flat areas are untouched.
    assert sharp[240, 320] == soft[240, 320] and sharp[100, 100] == soft[100, 100]


def test_motion_blur_of_8_px_spreads_the_edge_over_8_px() -> None:
    rvec, tvec = [math.pi, 0.0, 0.0], [0.0, 0.0, 1.0]
    img = render_marker(
        CAM,
        SQUARE,
        rvec,
        tvec,
        effects=Effects.clean(background="plain", plain_gray=220.0, motion_blur_px=8.0, motion_blur_angle_deg=0.0),
    ).image
    row = img[240, 240:280].astype(float)
    level = (row - BLACK) / (WHITE - BLACK)
    # A linear ramp across the smear: 10 %..90 % takes 0.8 of its length.
    x = np.arange(40)
    x10 = np.interp(0.1, level[::-1], x[::-1])
    x90 = np.interp(0.9, level[::-1], x[::-1])
    assert x10 - x90 == pytest.approx(0.8 * 8.0, abs=0.7)


@pytest.mark.parametrize("angle_deg", [0.0, 30.0, 90.0, 135.0])
def test_motion_blur_moves_nothing(angle_deg: float) -> None:
    """A smear is symmetric about where the marker is: the darkness keeps its centroid
    (a kernel half a pixel off would shift the whole marker against its true corners)."""
    rvec, tvec = [math.pi, 0.0, 0.0], [0.01, -0.02, 1.5]
    fx = dict(background="plain", plain_gray=WHITE)

    def centroid(effects: Effects) -> np.ndarray:
        dark = WHITE - render_marker(CAM, SQUARE, rvec, tvec, effects=effects).image.astype(np.float64)
        yy, xx = np.mgrid[: dark.shape[0], : dark.shape[1]]
        return np.array([(dark * xx).sum(), (dark * yy).sum()]) / dark.sum()

    sharp = centroid(Effects.clean(**fx))
    smeared = centroid(Effects.clean(motion_blur_px=8.0, motion_blur_angle_deg=angle_deg, **fx))
    assert np.abs(smeared - sharp).max() < 0.01, smeared - sharp


def test_render_empty_has_no_dark_quadrilateral_and_varies() -> None:
    rng = np.random.default_rng(0)
    frames = [render_empty(CAM, rng=rng) for _ in range(3)]
    assert all(f.shape == (480, 640) and f.dtype == np.uint8 for f in frames)
    assert not np.array_equal(frames[0], frames[1])
    assert all(30 < f.mean() < 220 for f in frames)


@pytest.mark.parametrize("kind", ["wall", "floor"])
def test_trajectories_are_smooth_and_keep_the_marker_in_view(kind: str) -> None:
    poses = trajectory(kind, 600, 30.0, seed=3, camera=CAM, marker=SQUARE)
    assert len(poses) == 600 and poses[1].t_s == pytest.approx(1 / 30)
    R = np.array([R_from_rvec(p.rvec) for p in poses])
    t = np.array([p.tvec for p in poses])
    step_m = np.linalg.norm(np.diff(t, axis=0), axis=1)
    step_deg = np.degrees(np.arccos(np.clip((np.einsum("nij,nij->n", R[1:], R[:-1]) - 1) / 2, -1, 1)))
    assert step_m.max() < 0.05 and step_deg.max() < 3.0
    assert 0.3 < t[:, 2].min() and t[:, 2].max() < 4.0
    for p in poses[::20]:
        pts = SQUARE.object_points @ R_from_rvec(p.rvec).T + p.tvec
        px = CAM.project(pts)
        assert np.all(pts[:, 2] > 0) and np.all((px > 0) & (px < [639, 479]))
        assert float(R_from_rvec(p.rvec)[:, 2] @ p.tvec) < 0  # faces the camera
    rolls = np.degrees(np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    spread = np.ptp(np.unwrap(np.radians(rolls)))
    assert spread > (math.pi if kind == "floor" else 0.05)
    # Starts near upright (the first sighting of a plain square fixes its corner labels).
    assert abs(rolls[0]) < 35.0
    assert trajectory(kind, 5, 30.0, seed=3, camera=CAM, marker=SQUARE)[4].tvec == pytest.approx(t[4])


def test_random_pose_keeps_the_marker_inside_with_bounded_tilt() -> None:
    rng = np.random.default_rng(9)
    for _ in range(200):
        rvec, tvec = random_pose(rng, CAM, SQUARE, (0.5, 3.0), 60)
        R = R_from_rvec(rvec)
        assert 0.5 - 1e-9 <= np.linalg.norm(tvec) <= 3.0 + 1e-9
        px = CAM.project(SQUARE.object_points @ R.T + tvec)
        assert np.all((px >= 4) & (px <= [635, 475]))
        view = -tvec / np.linalg.norm(tvec)
        assert np.degrees(np.arccos(R[:, 2] @ view)) <= 60 + 1e-6


@pytest.mark.pi
def test_render_is_cheap_and_right_on_the_pi_stack() -> None:
    frame = render_marker(CAM, ARUCO, [math.pi, 0.2, 0.1], [0.01, 0.02, 0.8], rng=np.random.default_rng(0))
    corners, ids = _aruco_detect(frame.image, "DICT_4X4_50")
    assert ids is not None and 7 in ids.ravel()
    np.testing.assert_allclose(corners[0].reshape(4, 2), frame.corners_px, atol=0.6)


@pytest.mark.parametrize(
    "bad, message",
    [
        ({"blur_px": -1.0}, "blur_px must be a number >= 0"),
        ({"noise_gray": float("nan")}, "noise_gray must be a number >= 0"),
        ({"jpeg_quality": 101}, "jpeg_quality must be 0"),
        ({"background": "stars"}, "background must be 'texture' or 'plain'"),
        ({"supersample": 0}, "supersample must be >= 1"),
        ({"gamma": "cinema"}, "gamma must be a number in \\[0.2, 5\\] or 'srgb'"),
        ({"gamma": 0.0}, "gamma must be a number in \\[0.2, 5\\] or 'srgb'"),
        ({"sharpen": -0.5}, "sharpen must be a number >= 0"),
    ],
)
def test_bad_effects_are_refused(bad, message) -> None:
    with pytest.raises(ValueError, match=message):
        Effects(**bad)


def test_bad_render_inputs_are_refused() -> None:
    with pytest.raises(ValueError, match="finite"):
        render_marker(CAM, SQUARE, [np.nan, 0, 0], [0, 0, 1])
    with pytest.raises(ValueError, match="background must be 480x640"):
        render_marker(CAM, SQUARE, [math.pi, 0, 0], [0, 0, 1], background=np.zeros((10, 10)))
    with pytest.raises(ValueError, match="size_m must be positive"):
        render_plane(CAM, np.zeros((8, 8), np.uint8), (0.0, 1.0), [math.pi, 0, 0], [0, 0, 1])
    with pytest.raises(ValueError, match="not in DICT_4X4_50"):
        render_marker(CAM, Marker(0.2, type="aruco", dictionary="DICT_4X4_50", id=50), [math.pi, 0, 0], [0, 0, 1])
    with pytest.raises(ValueError, match="trajectory must be one of wall, floor"):
        trajectory("ceiling", 3, 30.0)
