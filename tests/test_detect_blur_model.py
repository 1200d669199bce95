"""The model of a blurred ArUco marker's whole pattern (detect/blur_model.py), against the
renderer's truth: defocus, motion smears, gamma-encoded, sharpened and JPEG frames, small
markers; what it does not take (occlusions, sharp frames); its option."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from detect_helpers import ARUCO, CAM, aligned, facing_pose, render, rms

from pose_daemon import Marker, MarkerDetector
from pose_daemon.config import parse_config
from pose_daemon.detect import blur_model
from pose_daemon.detect.blur_model import MarkerModel
from pose_daemon.detect.response import decode_lut
from pose_daemon.detect.square import side_lengths
from pose_daemon.render import Effects, random_pose


def _model_of(detector: MarkerDetector) -> MarkerModel:
    return detector._finder._model


def _compare(marker: Marker, effects: dict, distance_m, n: int, seed: int):
    """Per frame (true corners, model's corners, edge fits' corners), same frames; frames
    either misses are left out (and counted)."""
    rng = np.random.default_rng(seed)
    gamma = effects.get("gamma", 1.0)
    rows, misses = [], 0
    for i in range(n):
        rvec, tvec = random_pose(rng, CAM, marker, distance_m=distance_m, max_tilt_deg=45)
        fx = Effects(motion_blur_angle_deg=float(rng.uniform(0, 180)), **effects)
        image, truth = render(marker, rvec, tvec, seed=seed + i, effects=fx)
        model = MarkerDetector(marker, gamma=gamma).detect(image)
        edges = MarkerDetector(marker, gamma=gamma, blur_model=False).detect(image)
        if model is None or edges is None:
            misses += 1
            continue
        rows.append((truth, aligned(model, truth), aligned(edges, truth)))
    return rows, misses


def _figures(rows, which: int):
    err = np.concatenate([r[which] - r[0] for r in rows])
    size = [float(side_lengths(r[which]).sum() / side_lengths(r[0]).sum() - 1.0) for r in rows]
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1)))), float(np.mean(size))


# (effects, distance m): each within the bounds, corner RMS 0.1 px and size bias 0.2 %.
SWEEP = {
    "defocus 2.5 px": (dict(blur_px=2.5), (0.5, 1.0)),
    "sRGB, defocus 2.5 px": (dict(blur_px=2.5, gamma="srgb"), (0.5, 1.0)),
    "sRGB, motion 8 px": (dict(blur_px=0.8, motion_blur_px=8.0, gamma="srgb"), (0.5, 1.0)),
    "sRGB, sharpened, JPEG 85": (dict(blur_px=1.5, gamma="srgb", sharpen=0.6, jpeg_quality=85), (0.5, 1.0)),
    # Small markers (cells of 5-7 px): the code's light blurs right into the border.
    "sRGB, defocus 2.5 px, small": (dict(blur_px=2.5, gamma="srgb"), (1.2, 1.5)),
    "sRGB, motion 8 px, small": (dict(blur_px=0.8, motion_blur_px=8.0, gamma="srgb"), (1.2, 1.5)),
}


@pytest.mark.parametrize("condition", list(SWEEP))
def test_blurred_markers_corners_and_size_within_the_bounds_and_better_than_the_edge_fits(condition: str) -> None:
    effects, distance_m = SWEEP[condition]
    rows, misses = _compare(ARUCO, effects, distance_m, 8, 71)
    assert misses <= 1 and len(rows) >= 7
    model_rms, model_size = _figures(rows, 1)
    edges_rms, _ = _figures(rows, 2)
    assert model_rms <= 0.1, (model_rms, edges_rms)
    assert abs(model_size) <= 0.002, model_size
    assert model_rms < edges_rms, (model_rms, edges_rms)


def _blurred_frame(effects: Effects, roll_deg: float = 17.0, distance_m: float = 1.1, shift_m=(0.0, 0.0), seed=3):
    image, truth = render(ARUCO, *facing_pose(roll_deg, distance_m, 25.0, shift_m), seed=seed, effects=effects)
    return image, truth


@pytest.mark.pi
def test_the_model_recovers_corners_and_blur_from_a_wrong_start() -> None:
    """From corners 0.3-0.4 px off and a blur guess 30 % short: the renderer's corners within
    0.03 px, its defocus (sigma 2.5 px, plus the pixel's own 1/12 px^2) within 5 %."""
    image, truth = _blurred_frame(Effects(blur_px=2.5, noise_gray=2.0))
    start = truth + np.array([[0.3, -0.2], [-0.3, 0.25], [0.2, 0.3], [-0.25, -0.3]])
    fit = _model_of(MarkerDetector(ARUCO)).fit(image, start, 1.75, 6.0)
    assert fit is not None
    assert rms(fit.corners, truth) < 0.03
    var = np.linalg.eigvalsh(fit.blur_cov_px2)
    assert np.allclose(var, 2.5**2 + 1.0 / 12.0, rtol=0.05), var
    assert fit.smear_px == 0.0
    assert fit.misfit < 1.2


@pytest.mark.pi
def test_a_motion_smear_is_fitted_as_one_of_its_length_and_direction() -> None:
    effects = Effects(blur_px=0.8, motion_blur_px=8.0, motion_blur_angle_deg=30.0, noise_gray=2.0, gamma="srgb")
    image, truth = _blurred_frame(effects)
    fit = _model_of(MarkerDetector(ARUCO)).fit(image, truth + 0.2, 2.5, 6.0, 1.0, decode_lut("srgb"))
    assert fit is not None
    assert rms(fit.corners, truth) < 0.05
    assert 7.0 < fit.smear_px < 9.0, fit.smear_px
    # The smear's direction: the covariance's long axis.
    _, vec = np.linalg.eigh(fit.blur_cov_px2)
    angle = math.degrees(math.atan2(vec[1, 1], vec[0, 1])) % 180.0
    assert abs(angle - 30.0) < 3.0, angle


def test_a_marker_at_the_frames_edge_is_fitted_on_the_pixels_in_it() -> None:
    """The model's margin runs past the frame's edge (the marker 5 px from it): it is drawn
    there all the same and compared only where the frame is; the edge fits there are 0.2-0.35
    px off."""
    for seed in (3, 4, 5):
        effects = Effects(blur_px=2.5, noise_gray=2.0)
        image, truth = _blurred_frame(effects, roll_deg=5.0, shift_m=(0.0, 0.43), seed=seed)
        assert truth[:, 1].max() > CAM.height - 6  # the model's margin leaves the frame
        modelled = MarkerDetector(ARUCO).detect(image)
        edges = MarkerDetector(ARUCO, blur_model=False).detect(image)
        assert modelled is not None and edges is not None
        assert rms(modelled, truth) < 0.05 and rms(modelled, truth) < 0.5 * rms(edges, truth)


def test_an_occluded_marker_keeps_its_edge_fit() -> None:
    """A dark bar across the code (a propeller, a cable) is not in the model: many of its
    pixels miss the model by far more than any noise, and the edge fits' corners stay."""
    image, truth = _blurred_frame(Effects(blur_px=2.5, noise_gray=2.0))
    blocked = image.copy()
    centre = truth.mean(axis=0)
    cv2.line(blocked, tuple(int(v) for v in truth[0]), (int(centre[0] + 3), int(centre[1] + 8)), 0, 4)
    fit = _model_of(MarkerDetector(ARUCO)).fit(blocked, truth, 2.5, 6.0)
    assert fit is not None and fit.outlier_share > 5 * blur_model.MODEL_MAX_OUTLIER_SHARE
    assert not blur_model.accept(fit, truth, 2.5)
    with_model = MarkerDetector(ARUCO).detect(blocked)
    without = MarkerDetector(ARUCO, blur_model=False).detect(blocked)
    if with_model is not None or without is not None:
        assert with_model is not None and without is not None
        assert np.array_equal(with_model, without)


def test_sharp_frames_and_square_markers_are_left_to_the_edge_fits() -> None:
    """Below ``MODEL_MIN_BLUR_PX`` (the renderer's default 0.8 px defocus) the result is the
    edge fits' to the bit, and a plain square has no pattern to model."""
    for marker in (ARUCO, Marker(0.20, 0.20)):
        image, _ = render(marker, *facing_pose(12, 1.0, 20.0), seed=8)
        a = MarkerDetector(marker).detect(image)
        b = MarkerDetector(marker, blur_model=False).detect(image)
        assert a is not None and np.array_equal(a, b)
    image, _ = render(Marker(0.20, 0.20), *facing_pose(12, 1.0, 20.0), seed=8, effects=Effects(blur_px=2.0))
    a = MarkerDetector(Marker(0.20, 0.20)).detect(image)
    assert a is not None and np.array_equal(a, MarkerDetector(Marker(0.20, 0.20), blur_model=False).detect(image))


def test_a_tracked_blurred_marker_is_modelled_too() -> None:
    detector = MarkerDetector(ARUCO)
    errors = []
    for i, roll in enumerate((10.0, 10.5, 11.0, 11.5)):
        image, truth = _blurred_frame(Effects(blur_px=2.5, noise_gray=2.0), roll_deg=roll, seed=20 + i)
        corners = detector.detect(image)
        assert corners is not None
        errors.append(rms(corners, truth))
    assert detector.last_stage == "follow"
    assert max(errors) < 0.05, errors


def _tracked_twice(monkeypatch, effects: Effects, gamma):
    """Per tracked frame (its model fits, as (given the last frame's blur, steps, a smear), the
    corners and the truth) of a detector that tracks six frames, and the same of a second one
    whose fits are made to start afresh every frame."""
    log = []  # (given the last frame's blur, steps, a smear) of each model fit
    fit = MarkerModel.fit

    def logged(self, gray, corners, blur_px, quiet_px, least_blur_px=None, lut=None, start=None):
        out = fit(self, gray, corners, blur_px, quiet_px, least_blur_px, lut, start)
        if out is not None:
            log.append((start is not None, out.steps, out.smear_px > 0.0))
        return out

    monkeypatch.setattr(MarkerModel, "fit", logged)
    warm, fresh = MarkerDetector(ARUCO, gamma=gamma), MarkerDetector(ARUCO, gamma=gamma)
    rows = []
    for i, roll in enumerate((10.0, 10.4, 10.8, 11.2, 11.6, 12.0)):
        image, truth = _blurred_frame(effects, roll_deg=roll, seed=40 + i)
        log.clear()
        a = warm.detect(image)
        warm_log = list(log)
        fresh._finder._model_start = None
        log.clear()
        b = fresh.detect(image)
        assert a is not None and b is not None
        if i > 0:
            assert warm.last_stage == "follow" and fresh.last_stage == "follow"
            rows.append((warm_log, a, list(log), b, truth))
    return rows


def test_a_tracked_defocus_starts_from_its_last_blur_and_lands_where_a_fresh_fit_does(monkeypatch) -> None:
    """A tracked frame's fit starts from the last frame's blur: fewer steps, and the corners
    of a fit from a round blur, on the same frames tracked afresh."""
    rows = _tracked_twice(monkeypatch, Effects(blur_px=2.5, noise_gray=2.0), 1.0)
    assert all([f[0] for f in r[0]] == [True] and [f[0] for f in r[2]] == [False] for r in rows)
    apart = [float(np.abs(r[1] - r[3]).max()) for r in rows]
    warm_err, fresh_err = [rms(r[1], r[4]) for r in rows], [rms(r[3], r[4]) for r in rows]
    assert max(apart) < 0.05, apart
    assert float(np.mean(warm_err)) <= float(np.mean(fresh_err)) + 0.005, (warm_err, fresh_err)
    assert sum(r[0][0][1] for r in rows) < sum(r[2][0][1] for r in rows)


def test_a_tracked_smear_is_fitted_afresh(monkeypatch) -> None:
    """A smear's fit does not start from the last frame's smear (from there it stayed at the
    edge fits' corners): every frame's is the fresh fit's."""
    effects = Effects(blur_px=0.8, motion_blur_px=8.0, motion_blur_angle_deg=30.0, noise_gray=2.0, gamma="srgb")
    rows = _tracked_twice(monkeypatch, effects, "srgb")
    assert all(np.array_equal(r[1], r[3]) for r in rows)
    # ... a smear fitted as the fresh one is, as many steps (a Gaussian's, then the smear's).
    assert all(len(r[0]) == 1 and r[0][0][2] and r[0][0][1] == r[2][0][1] for r in rows)


def test_degenerate_input_gives_none_not_an_error() -> None:
    model = _model_of(MarkerDetector(ARUCO))
    flat = np.full((CAM.height, CAM.width), 128, np.uint8)
    square = np.array([[100.0, 80.0], [150.0, 80.0], [150.0, 130.0], [100.0, 130.0]])
    fit = model.fit(flat, square, 2.0, 6.0)
    assert fit is None or not blur_model.accept(fit, square, 2.0)
    assert model.fit(flat, np.zeros((4, 2)), 2.0, 6.0) is None
    assert model.fit(flat, square + 1000.0, 2.0, 6.0) is None
    with pytest.raises(ValueError, match="grid must be square"):
        MarkerModel(np.zeros((3, 4)))


def test_the_option_in_the_api_and_the_config() -> None:
    with pytest.raises(ValueError, match="blur_model must be True or False, got 'yes'"):
        MarkerDetector(ARUCO, blur_model="yes")
    text = '[marker]\ntype = "aruco"\ndictionary = "DICT_4X4_50"\nid = 7\n[detector]\nblur_model = false\n'
    cfg = parse_config(text, "c.toml")
    assert cfg.detector.blur_model is False
    assert parse_config("", "c.toml").detector.blur_model is True
    with pytest.raises(Exception, match="blur_model"):
        parse_config("[detector]\nblur_model = 1\n", "c.toml")
