"""pose-daemon calibrate on rendered views of a chessboard and a ChArUco board seen through a
lens with known intrinsics and distortion; bad inputs; the in-place config update."""

from __future__ import annotations

import re
from pathlib import Path
from typing import List

import cv2
import numpy as np
import pytest

from pose_daemon.camera import Camera
from pose_daemon.capture.base import Frame
from pose_daemon.capture.recording import RecordingWriter
from pose_daemon.cli import main
from pose_daemon.config import load_config, parse_config
from pose_daemon.geometry import R_from_rvec, rot_x, rot_y, rot_z, rvec_from_R
from pose_daemon.render import Effects, render_empty, render_plane
from pose_daemon.tools import calibrate as cal

TRUE = Camera(fx=520.0, fy=515.0, cx=322.0, cy=236.0, dist=(-0.25, 0.08, 0.0, 0.0, 0.0), width=640, height=480)
CHESSBOARD = "chessboard:11x8:0.03"
CHARUCO = "charuco:7x5:0.05:0.03:DICT_4X4_50"
# A real camera's defocus and sensor noise.
EFFECTS = Effects(blur_px=1.0, noise_gray=2.0, background="plain")


def board_pose(u_px: float, v_px: float, z_m: float, tilt_x_rad: float, tilt_y_rad: float, roll_rad: float):
    """(rvec, tvec) of a board facing the camera, its centre seen at pixel (u, v), z_m away."""
    n = TRUE.undistort_normalized(np.array([[u_px, v_px]]))[0]
    R_cam_board = rot_z(roll_rad) @ rot_y(tilt_y_rad) @ rot_x(tilt_x_rad) @ rot_x(np.pi)
    return rvec_from_R(R_cam_board), np.array([n[0] * z_m, n[1] * z_m, z_m])


def render_views(
    board: str,
    camera: Camera = TRUE,
    anchors=(0.0, 0.5, 1.0),
    z_m=(0.65, 0.75),
    tilt_deg: float = 25.0,
    margin_px: float = 12.0,
    effects: Effects = EFFECTS,
    seed: int = 0,
) -> List[np.ndarray]:
    """18 views on a 3x3 grid of the image, twice, tilted about both axes: a board at anchor
    0 / 1 has its squares ``margin_px`` from the image's left / right (top / bottom) edge, so
    the board's corners reach the image's corners where distortion is; between them the
    board's centre is at that fraction of the image."""
    spec = cal.parse_board(board)
    texture, size_m = cal.board_image(spec, 40), cal.board_image_size_m(spec)
    w2, h2 = spec.size_m[0] / 2, spec.size_m[1] / 2
    outline = np.array(
        [[x, y, 0.0] for x in np.linspace(-w2, w2, 9) for y in (-h2, h2)]
        + [[x, y, 0.0] for y in np.linspace(-h2, h2, 7) for x in (-w2, w2)]
    )
    size = np.array([camera.width, camera.height], dtype=float)
    images = []
    targets = [(fu, fv) for fv in anchors for fu in anchors] * 2
    for i, (fu, fv) in enumerate(targets):
        a = np.radians(tilt_deg) * (1 if i < 9 else -1) * (1 if i % 3 != 1 else -1)
        b = np.radians(tilt_deg - 5) * (1 if fu < 0.5 else -1)
        roll = np.radians(10 * (i % 5 - 2))
        anchor = np.array([fu, fv])
        centre = 0.5 * size
        for _ in range(6):  # move the board until its outline sits where the anchor says
            rvec, tvec = board_pose(centre[0], centre[1], z_m[i % 2], a, b, roll)
            pts = camera.project(outline @ R_from_rvec(rvec).T + tvec)
            lo, hi = pts.min(axis=0), pts.max(axis=0)
            want_lo = np.where(
                anchor == 0.0,
                margin_px,
                np.where(anchor == 1.0, size - margin_px - (hi - lo), anchor * size - 0.5 * (hi - lo)),
            )
            centre = centre + (want_lo - lo)
        images.append(
            render_plane(camera, texture, size_m, rvec, tvec, effects=effects, rng=np.random.default_rng(seed + i))
        )
    return images


def write_folder(path: Path, images: List[np.ndarray]) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    for k, image in enumerate(images):
        cv2.imwrite(str(path / f"view{k:02d}.png"), image)
    return path


@pytest.fixture(scope="module")
def chessboard_views() -> List[np.ndarray]:
    return render_views(CHESSBOARD)


@pytest.fixture(scope="module")
def chessboard_dir(tmp_path_factory, chessboard_views) -> Path:
    return write_folder(tmp_path_factory.mktemp("chessboard"), chessboard_views)


CHARUCO_SEEDS = (0, 100, 200)


@pytest.fixture(scope="module")
def charuco_seed_views():
    # A ChArUco board is found with only part of it in view, but its markers must stay large
    # enough to decode: the board does not need to hug the image edges.
    return {
        seed: render_views(CHARUCO, anchors=(0.25, 0.5, 0.75), z_m=(0.55, 0.65), seed=seed) for seed in CHARUCO_SEEDS
    }


@pytest.fixture(scope="module")
def charuco_dir(tmp_path_factory, charuco_seed_views) -> Path:
    return write_folder(tmp_path_factory.mktemp("charuco"), charuco_seed_views[0])


def read_camera(path: Path) -> Camera:
    return parse_config(path.read_text(), str(path)).camera.model()


def assert_close_to_truth(cam: Camera) -> None:
    for key in ("fx", "fy", "cx", "cy"):
        got, want = getattr(cam, key), getattr(TRUE, key)
        assert abs(got / want - 1) < 0.005, f"{key} {got:.3f} vs {want} ({(got / want - 1) * 100:+.2f}%)"
    assert (cam.width, cam.height) == (640, 480)
    assert cal.distortion_difference_px(TRUE, cam) < 0.2


def run_cli(args, capsys):
    code = main(["calibrate", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


# --------------------------------------------------------------------------- accuracy


@pytest.mark.parametrize("board", ["chessboard", "charuco"])
def test_recovers_intrinsics_and_distortion(board, chessboard_dir, charuco_dir, tmp_path, capsys):
    folder, spec = (chessboard_dir, CHESSBOARD) if board == "chessboard" else (charuco_dir, CHARUCO)
    out = tmp_path / "camera.toml"
    code, stdout, stderr = run_cli([folder, "--board", spec, "--out", out], capsys)
    assert code == 0, stderr
    cam = read_camera(out)
    assert_close_to_truth(cam)
    # Without distortion correction the image corners would be off by tens of pixels.
    assert cal.distortion_difference_px(TRUE, Camera(TRUE.fx, TRUE.fy, TRUE.cx, TRUE.cy)) > 20
    rms = float(re.search(r"RMS reprojection error: ([0-9.]+) px over 18 views", stdout).group(1))
    assert 0 < rms < 0.15
    assert len(re.findall(r"^\s+view\s+\d+ view\d\d\.png\s+\d+ corners\s+[0-9.]+ px$", stdout, re.M)) == 18
    cover = int(re.search(r"coverage of the image: (\d+)%", stdout).group(1))
    assert cover >= 90
    assert "[camera]" in out.read_text() and "OUTLIER" not in stdout
    # These renders are linear: the response exponent measured on the board's dark squares is 1.
    gamma = float(re.search(r"camera response: \[detector\] gamma = ([0-9.]+)", stdout).group(1))
    assert abs(gamma - 1.0) < 0.15


@pytest.mark.parametrize("seed", CHARUCO_SEEDS)
def test_charuco_over_noise_seeds(seed, charuco_seed_views):
    detector = cal.BoardDetector(cal.parse_board(CHARUCO))
    views = [v for v in (detector.detect(image) for image in charuco_seed_views[seed]) if v is not None]
    assert len(views) == 18
    cam = cal.calibrate_views(views, TRUE.width, TRUE.height).camera
    for key in ("fx", "fy", "cx", "cy"):
        assert abs(getattr(cam, key) / getattr(TRUE, key) - 1) < 0.005, key
    # Over the part of the image the corners reached; beyond it (the outer ~40 px, where these
    # views put no corner) the fit extrapolates.
    pts = np.concatenate([v.image_points for v in views])
    box = (*pts.min(axis=0), *pts.max(axis=0))
    assert cal.distortion_difference_px(TRUE, cam, box_px=box) < 0.2


def test_stdout_section_is_valid_config(chessboard_dir, capsys):
    code, stdout, stderr = run_cli([chessboard_dir, "--board", CHESSBOARD], capsys)
    assert code == 0
    # The section alone on stdout, the report on stderr: `> camera.toml` gives a clean file.
    assert stdout.lstrip().startswith("#") and "[camera]" in stdout and "RMS" in stderr
    cam = parse_config(stdout).camera.model()
    assert_close_to_truth(cam)


def test_outlier_flagged_then_dropped(chessboard_views, tmp_path, capsys):
    # One view taken after the lens was refocused (other focal length, no distortion).
    other = Camera(fx=600.0, fy=600.0, cx=300.0, cy=250.0, width=640, height=480)
    spec = cal.parse_board(CHESSBOARD)
    rvec, tvec = board_pose(300, 250, 0.6, 0.4, -0.3, 0.1)
    bad = render_plane(
        other,
        cal.board_image(spec, 40),
        cal.board_image_size_m(spec),
        rvec,
        tvec,
        effects=EFFECTS,
        rng=np.random.default_rng(99),
    )
    folder = write_folder(tmp_path / "views", list(chessboard_views) + [bad])
    code, stdout, _ = run_cli([folder, "--board", CHESSBOARD, "--out", tmp_path / "a.toml"], capsys)
    assert code == 0
    flagged = [line for line in stdout.splitlines() if "OUTLIER" in line]
    assert len(flagged) == 1 and "view18.png" in flagged[0]
    assert "--drop-outliers" in stdout
    code, stdout, _ = run_cli([folder, "--board", CHESSBOARD, "--drop-outliers", "--out", tmp_path / "b.toml"], capsys)
    assert code == 0
    assert "dropping 1 outlier view(s)" in stdout
    assert "over 18 views" in stdout.split("dropping")[1]
    assert_close_to_truth(read_camera(tmp_path / "b.toml"))


# One corner a detector put on a neighbouring edge, 9 px off, in four views (seen with the
# classic chessboard detector on rendered views); (view, corner index) of each.
MISLOCATED = ((2, 0), (7, 40), (11, 87), (15, 10))
SHIFT_PX = np.array([9.0, -9.0]) / np.sqrt(2.0)


@pytest.fixture(scope="module")
def chessboard_detected(chessboard_views) -> List[cal.BoardView]:
    detector = cal.BoardDetector(cal.parse_board(CHESSBOARD))
    return [detector.detect(image, f"view{k:02d}.png") for k, image in enumerate(chessboard_views)]


def with_mislocated_corners(views: List[cal.BoardView]) -> List[cal.BoardView]:
    out = [cal.BoardView(v.image_points.copy(), v.object_points.copy(), v.name) for v in views]
    for k, corner in MISLOCATED:
        out[k].image_points[corner] += SHIFT_PX
    return out


def test_mislocated_corners_left_out_of_the_fit(chessboard_detected):
    views = with_mislocated_corners(chessboard_detected)
    plain = cal.calibrate_views(views, TRUE.width, TRUE.height, robust=False)
    # Without the re-fit the four corners pull the lens far off: this test would see it.
    assert abs(plain.camera.cy / TRUE.cy - 1) > 0.005 or cal.distortion_difference_px(TRUE, plain.camera) > 0.2
    result = cal.calibrate_views(views, TRUE.width, TRUE.height)
    assert_close_to_truth(result.camera)
    assert result.rejected == [1 if any(k == m for m, _ in MISLOCATED) else 0 for k in range(18)]
    assert result.rms_px < 0.05
    # The same lens as from the clean corners, to a hundredth of a percent.
    clean = cal.calibrate_views(chessboard_detected, TRUE.width, TRUE.height)
    assert clean.rejected_corners == 0
    for key in ("fx", "fy", "cx", "cy"):
        assert abs(getattr(result.camera, key) / getattr(clean.camera, key) - 1) < 1e-4
    # The views stay flagged over all their corners, so the user can look at them.
    assert result.outliers == [m for m, _ in MISLOCATED]


def test_cli_recovers_lens_despite_mislocated_corners(
    chessboard_dir, chessboard_detected, tmp_path, capsys, monkeypatch
):
    by_name = {v.name: v for v in with_mislocated_corners(chessboard_detected)}
    monkeypatch.setattr(cal.BoardDetector, "detect", lambda self, gray, name="": by_name[name])
    out = tmp_path / "camera.toml"
    code, stdout, stderr = run_cli([chessboard_dir, "--board", CHESSBOARD, "--out", out], capsys)
    assert code == 0, stderr
    assert "4 corner(s) in 4 view(s) left out of the fit" in stdout
    assert "dropping" not in stdout
    assert_close_to_truth(read_camera(out))


# --------------------------------------------------------------------------- recordings and live


def write_recording(path: Path, images: List[np.ndarray], repeat: int, fps: float) -> Path:
    with RecordingWriter(path, TRUE, source="synthetic", fps=fps) as writer:
        seq = 0
        for image in images:
            for _ in range(repeat):
                writer.write(Frame(image=image, t_capture_s=seq / fps, seq=seq))
                seq += 1
    return path


def test_recording_keeps_only_new_views(chessboard_views, tmp_path, capsys):
    # Each view held for 3 frames, as a board held still in front of a camera.
    rec = write_recording(tmp_path / "rec", chessboard_views, repeat=3, fps=30.0)
    code, stdout, stderr = run_cli([rec, "--board", CHESSBOARD, "--out", tmp_path / "c.toml"], capsys)
    assert code == 0, stderr
    assert "board seen in 54 of 54 frame(s); 18 distinct view(s) kept" in stdout
    assert_close_to_truth(read_camera(tmp_path / "c.toml"))


def test_live_source_stops_at_view_target(chessboard_views, tmp_path, capsys):
    rec = write_recording(tmp_path / "rec", chessboard_views, repeat=2, fps=500.0)
    config = tmp_path / "live.toml"
    config.write_text(f'[camera]\nsource = "replay:{rec}"\nfps = 500.0\n')
    saved = tmp_path / "saved"
    code, stdout, stderr = run_cli(
        ["--config", config, "--board", CHESSBOARD, "--views", 12, "--save-views", saved], capsys
    )
    assert code == 0, stderr
    kept = re.findall(r"kept view\s+(\d+)/12 .*coverage (\d+)%", stdout)
    assert [int(k) for k, _ in kept] == list(range(1, 13))
    cover = [int(c) for _, c in kept]
    assert cover == sorted(cover) and cover[-1] > cover[0]
    assert "over 12 views" in stdout
    cfg = load_config(config)
    assert cfg.camera.source == f"replay:{rec}"
    assert abs(cfg.camera.fx / TRUE.fx - 1) < 0.01
    # The kept frames, saved, calibrate again to the same camera.
    assert sorted(p.name for p in saved.iterdir()) == [f"view{k:03d}.png" for k in range(1, 13)]
    code, stdout, _ = run_cli([saved, "--board", CHESSBOARD, "--out", tmp_path / "again.toml"], capsys)
    assert code == 0 and "board found in 12 of 12 image(s)" in stdout
    assert abs(read_camera(tmp_path / "again.toml").fx - cfg.camera.fx) < 1e-3


# --------------------------------------------------------------------------- refusals


def one_line_error(stderr: str, *fragments: str) -> None:
    lines = stderr.strip().splitlines()
    assert lines and lines[-1].startswith("pose-daemon: error: "), stderr
    assert "Traceback" not in stderr
    for fragment in fragments:
        assert fragment in lines[-1], lines[-1]


@pytest.mark.parametrize("board, noun", [(CHESSBOARD, "chessboard"), (CHARUCO, "ChArUco board")])
def test_no_board_in_any_image(board, noun, tmp_path, capsys):
    rng = np.random.default_rng(3)
    folder = write_folder(tmp_path / "empty", [render_empty(TRUE, rng=rng) for _ in range(3)])
    code, stdout, err = run_cli([folder, "--board", board], capsys)
    assert code == 2
    one_line_error(err, f"no {noun} found in any of its 3 image(s)")
    assert err.count(": no board found") == 3


def test_unreadable_files(tmp_path, capsys):
    folder = tmp_path / "broken"
    folder.mkdir()
    for k in range(3):
        (folder / f"img{k}.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really a picture")
    code, _, err = run_cli([folder, "--board", CHESSBOARD], capsys)
    assert code == 2
    one_line_error(err, "none of its 3 image file(s) could be read")
    assert err.count("unreadable image, skipped") == 3


def test_unreadable_file_among_good_ones_is_skipped(chessboard_views, tmp_path, capsys):
    folder = write_folder(tmp_path / "views", chessboard_views[:12])
    (folder / "zz.jpg").write_bytes(b"garbage")
    code, stdout, _ = run_cli([folder, "--board", CHESSBOARD, "--out", tmp_path / "d.toml"], capsys)
    assert code == 0
    assert "zz.jpg: unreadable image, skipped" in stdout and "board found in 12 of 13" in stdout


def test_too_few_views(chessboard_views, tmp_path, capsys):
    folder = write_folder(tmp_path / "few", chessboard_views[:9])
    code, _, err = run_cli([folder, "--board", CHESSBOARD], capsys)
    assert code == 2
    one_line_error(err, "only 9 usable view(s)", "at least 10")


def test_poor_coverage(tmp_path, capsys):
    # Far away and always near the centre: the edges, where distortion is, are never seen.
    images = render_views(CHESSBOARD, anchors=(0.45, 0.5, 0.55), z_m=(1.0, 1.1), tilt_deg=20)[:10]
    folder = write_folder(tmp_path / "centre", images)
    code, _, err = run_cli([folder, "--board", CHESSBOARD], capsys)
    assert code == 2
    one_line_error(err, "poor coverage", "need 50%")


@pytest.mark.parametrize(
    "spec, fragment",
    [
        ("chessboard:9x6", "expected chessboard:COLSxROWS:SQUARE_M"),
        ("chessboard:9by6:0.03", "expected chessboard:COLSxROWS:SQUARE_M"),
        ("chessboard:6x6:0.03", "COLS different from ROWS"),
        ("chessboard:9x6:-1", "positive number of metres"),
        ("charuco:9x7:0.03:0.04:DICT_4X4_50", "smaller than the square"),
        ("charuco:9x7:0.03:0.02:DICT_NOPE", "unknown ArUco dictionary 'DICT_NOPE'"),
        ("circles:9x6:0.03", "expected chessboard:"),
    ],
)
def test_bad_board_spec(spec, fragment, tmp_path, capsys):
    code, _, err = run_cli([tmp_path, "--board", spec], capsys)
    assert code == 2
    one_line_error(err, fragment)


def test_missing_input(tmp_path, capsys):
    code, _, err = run_cli([tmp_path / "nope", "--board", CHESSBOARD], capsys)
    assert code == 2
    one_line_error(err, "no such folder or recording")


# --------------------------------------------------------------------------- config in place


CONFIG = """\
# My robot's camera.  Keep this comment.
[camera]                 # the front camera
source = "opencv:0"      # USB camera
width = 1280
height = 720
fx = 900.0               # focal length from the datasheet
# cx and cy were guessed
cx = 640.0
cy = 360.0
dist = [0.0, 0.0,        # radial
        0.0, 0.0, 0.0]   # tangential, k3
fps = 30.0

[marker]
type = "aruco"           # printed with pose-daemon marker
width = 0.16
height = 0.16
dictionary = "DICT_4X4_50"
id = 7
placement = "floor"

[output.jsonl]
path = "-"
"""


@pytest.mark.pi
def test_update_camera_text_keeps_everything_else():
    cam = Camera(
        fx=521.25, fy=514.5, cx=321.75, cy=236.125, dist=(-0.25, 0.08, 1e-4, -2e-4, 0.0), width=640, height=480
    )
    new = cal.update_camera_text(CONFIG, cam)
    cfg = parse_config(new)
    got = cfg.camera
    assert (got.width, got.height, got.fx, got.fy, got.cx, got.cy) == (640, 480, 521.25, 514.5, 321.75, 236.125)
    assert np.allclose(got.dist, cam.dist, atol=1e-12)
    assert got.source == "opencv:0" and cfg.marker.id == 7 and cfg.output.jsonl.path == "-"
    old_lines, new_lines = CONFIG.splitlines(), new.splitlines()
    # Only the calibrated values changed; comments stay on their lines.
    changed = [b for b in new_lines if b not in old_lines]
    # The two-line dist array became one line; fy, missing, was added at the table's end.
    assert len(new_lines) == len(old_lines)
    assert new_lines[new_lines.index("fps = 30.0") + 1] == "fy = 514.5000"
    for line in old_lines:
        if "#" in line and not line.lstrip().startswith(("dist", "0.0")):
            assert line.split("#", 1)[1] in new
    assert "fx = 521.2500               # focal length from the datasheet" in new_lines
    assert "dist = [-0.25, 0.08, 0.0001, -0.0002, 0.0]   # tangential, k3" in new_lines
    assert len(changed) == 7 and all(re.match(r"(width|height|fx|fy|cx|cy|dist) = ", b) for b in changed)
    assert new.split("[marker]")[1] == CONFIG.split("[marker]")[1]


@pytest.mark.pi
def test_update_camera_text_adds_missing_keys_and_table():
    cam = Camera(fx=500.5, fy=501.5, cx=320.0, cy=240.0, width=640, height=480)
    text = '[camera]\nsource = "picamera2"\n\n# the marker\n[marker]\nwidth = 0.2\n'
    new = cal.update_camera_text(text, cam)
    assert new.startswith('[camera]\nsource = "picamera2"\nwidth = 640\n')
    assert new.endswith("\n\n# the marker\n[marker]\nwidth = 0.2\n")
    assert parse_config(new).camera.fy == 501.5
    new = cal.update_camera_text("# nothing yet\n[marker]\nwidth = 0.2\n", cam)
    assert new.startswith("# nothing yet\n[marker]\nwidth = 0.2\n\n[camera]\n")
    assert parse_config(new).camera.fx == 500.5
    # A file written on Windows keeps its line ends, new lines included.
    new = cal.update_camera_text("[camera]\r\nfx = 1.0  # f\r\n\r\n[marker]\r\nwidth = 0.2\r\n", cam)
    assert new.startswith("[camera]\r\nfx = 500.5000  # f\r\nwidth = 640\r\nheight = 480\r\n")
    assert new.endswith("\r\n\r\n[marker]\r\nwidth = 0.2\r\n") and "\n" not in new.replace("\r\n", "")
    assert parse_config(new).camera.cy == 240.0


def test_config_updated_in_place(chessboard_dir, tmp_path, capsys):
    config = tmp_path / "robot.toml"
    config.write_text(CONFIG)
    code, stdout, stderr = run_cli([chessboard_dir, "--board", CHESSBOARD, "--config", config], capsys)
    assert code == 0, stderr
    assert f"updated [camera] in {config}" in stdout
    text = config.read_text()
    assert "# My robot's camera.  Keep this comment." in text and "# cx and cy were guessed" in text
    assert text.split("[marker]")[1] == CONFIG.split("[marker]")[1]
    cfg = load_config(config)
    assert cfg.camera.source == "opencv:0" and cfg.marker.placement == "floor"
    assert_close_to_truth(cfg.camera.model())
    assert [p.name for p in tmp_path.iterdir()] == ["robot.toml"]  # no temporary file left


def test_broken_config_is_not_rewritten(chessboard_dir, tmp_path, capsys):
    config = tmp_path / "broken.toml"
    config.write_text("[camera]\nfx = -3\n")
    code, _, err = run_cli([chessboard_dir, "--board", CHESSBOARD, "--config", config], capsys)
    assert code == 2
    one_line_error(err, "broken.toml", "fx")
    assert config.read_text() == "[camera]\nfx = -3\n"


class ListSource:
    """Frames from a list, as a FrameSource; ``interrupt_after``: Ctrl-C after so many frames."""

    def __init__(self, images: List[np.ndarray], interrupt_after: int = -1) -> None:
        self.images, self.interrupt_after = images, interrupt_after
        self.pos, self.closed = 0, False

    def open(self) -> None:
        self.pos = 0

    def read(self) -> Frame:
        if self.pos == self.interrupt_after:
            raise KeyboardInterrupt
        if self.pos >= len(self.images):
            from pose_daemon.errors import EndOfStream

            raise EndOfStream("end")
        self.pos += 1
        return Frame(image=self.images[self.pos - 1], t_capture_s=self.pos / 30.0, seq=self.pos - 1)

    def close(self) -> None:
        self.closed = True


def test_ctrl_c_ends_live_collection_with_the_views_so_far(chessboard_views):
    from pose_daemon.tools.calibrate import views_from_source

    lines: List[str] = []
    source = ListSource(list(chessboard_views), interrupt_after=13)
    views, size, _ = views_from_source(source, cal.parse_board(CHESSBOARD), say=lines.append, name="camera")
    assert len(views) == 13 and size == (640, 480) and source.closed
    assert "stopped after 13 frame(s)" in lines


def test_seconds_limit_ends_live_collection(chessboard_views):
    from pose_daemon.tools.calibrate import views_from_source

    source = ListSource(list(chessboard_views))
    lines: List[str] = []
    # A camera at 1 frame per second: the clock is the number of frames read so far.
    views, _, _ = views_from_source(
        source,
        cal.parse_board(CHESSBOARD),
        seconds=5.0,
        say=lines.append,
        name="camera",
        clock=lambda: float(source.pos),
    )
    assert len(views) == 5 and source.pos == 5
    # A status line every 5 s, whether or not the board is in view (here at the 5th frame).
    status = [x for x in lines if "frame(s), board seen in" in x]
    assert status == ["  5 frame(s), board seen in 4, 4 view(s) kept"]


def _accuracy_report(seeds: int = 6) -> None:
    """Prints, per board and noise seed, what the accuracy test measures (run this file)."""
    import time

    charuco_kw = dict(anchors=(0.25, 0.5, 0.75), z_m=(0.55, 0.65))
    for board, kw in ((CHESSBOARD, {}), (CHARUCO, charuco_kw)):
        for seed in range(0, 100 * seeds, 100):
            images = render_views(board, seed=seed, **kw)
            t0 = time.perf_counter()
            detector = cal.BoardDetector(cal.parse_board(board))
            views = [v for v in (detector.detect(im) for im in images) if v is not None]
            t1 = time.perf_counter()
            result = cal.calibrate_views(views, TRUE.width, TRUE.height)
            t2 = time.perf_counter()
            cam = result.camera
            pts = np.concatenate([v.image_points for v in views])
            box = (*pts.min(axis=0), *pts.max(axis=0))
            errors = " ".join(
                f"{k} {(getattr(cam, k) / getattr(TRUE, k) - 1) * 100:+.3f}%" for k in ("fx", "fy", "cx", "cy")
            )
            print(
                f"{board} seed {seed:3d}: {len(views)}/{len(images)} views, RMS {result.rms_px:.3f} px, "
                f"{errors}, distortion {cal.distortion_difference_px(TRUE, cam):.3f} px "
                f"({cal.distortion_difference_px(TRUE, cam, box_px=box):.3f} px where corners were seen), "
                f"{result.rejected_corners} corner(s) left out, "
                f"detect {(t1 - t0) / len(images) * 1000:.0f} ms/view, calibrate {(t2 - t1) * 1000:.0f} ms",
                flush=True,
            )


if __name__ == "__main__":
    _accuracy_report()


def test_an_image_of_another_dtype_is_a_clear_error_not_a_silent_cast(tmp_path: Path, capsys) -> None:
    image = np.full((48, 64), 0.5, np.float32)
    assert cv2.imwrite(str(tmp_path / "a.tiff"), image)
    code, _, err = run_cli([tmp_path, "--board", CHESSBOARD], capsys)
    assert code == 2
    assert err.strip().splitlines()[-1] == (
        f"pose-daemon: error: {tmp_path / 'a.tiff'}: image must be uint8 (or uint16) grey levels, got dtype float32"
    )
