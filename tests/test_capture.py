"""Frame sources: synthetic, fake picamera2, video written by cv2.VideoWriter, image folders."""

from __future__ import annotations

import sys
import time
import types
from concurrent.futures import CancelledError, Future
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from pose_daemon import Camera, Marker
from pose_daemon.capture import SOURCE_FORMS, FrameSource, open_source, parse_source
from pose_daemon.capture.opencv import OpenCVSource
from pose_daemon.capture.picamera2 import Picamera2Source
from pose_daemon.capture.replay import ReplaySource
from pose_daemon.capture.synthetic import SyntheticSource
from pose_daemon.config import CameraConfig, Config
from pose_daemon.errors import EndOfStream, SourceError
from pose_daemon.render import Effects, render_marker, trajectory

CAM = Camera(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=640, height=480)


class FakeClock:
    def __init__(self, t: float = 100.0) -> None:
        self.t = t
        self.sleeps = []

    def __call__(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.sleeps.append(dt)
        self.t += dt


def _camera_cfg(source: str, **kw) -> CameraConfig:
    return replace(CameraConfig(), source=source, fx=600.0, fy=600.0, **kw)


def test_source_kinds_and_unknown_source() -> None:
    assert parse_source("picamera2") == ("picamera2", "")
    assert parse_source(" synthetic ") == ("synthetic", "")
    assert parse_source("opencv:0") == ("opencv", "0")
    assert parse_source("opencv:/dev/video2") == ("opencv", "/dev/video2")
    assert parse_source("video:/tmp/a.mp4") == ("video", "/tmp/a.mp4")
    assert parse_source("replay:/tmp/rec") == ("replay", "/tmp/rec")
    pipeline = "v4l2src ! videoconvert ! appsink"
    assert parse_source(pipeline) == ("gstreamer", pipeline)
    for bad, expected in (
        ("webcam", SOURCE_FORMS),
        ("video:", SOURCE_FORMS),
        ("opencv:front", '"opencv:N" with a camera index N or a device path'),
    ):
        with pytest.raises(ValueError) as info:
            parse_source(bad)
        assert str(info.value) == expected
    with pytest.raises(SourceError, match="unknown camera source 'webcam': expected \"picamera2\""):
        open_source(_camera_cfg("webcam"))


def test_synthetic_source_follows_the_trajectory_with_truth() -> None:
    cfg = Config.default()
    source = open_source(cfg.camera, cfg, realtime=False)
    assert isinstance(source, SyntheticSource) and isinstance(source, FrameSource)
    source.open()
    frames = [source.read() for _ in range(3)]
    source.close()
    truth = trajectory(
        cfg.synthetic.trajectory,
        3,
        cfg.camera.fps,
        seed=cfg.synthetic.seed,
        camera=cfg.camera.model(),
        marker=cfg.marker.model(),
    )
    for i, f in enumerate(frames):
        assert f.seq == i and f.image.shape == (cfg.camera.height, cfg.camera.width)
        assert f.t_capture_s - frames[0].t_capture_s == pytest.approx(i / cfg.camera.fps)
        np.testing.assert_allclose(f.metadata["true_tvec"], truth[i].tvec)
        assert f.metadata["visible"]
    # The same config gives the same frames (seeded noise and background).
    again = open_source(cfg.camera, cfg, realtime=False)
    again.open()
    assert np.array_equal(again.read().image, frames[0].image)


@pytest.mark.parametrize("kind", ["wall", "floor"])
def test_synthetic_source_makes_its_texture_levels_before_its_first_frame(kind) -> None:
    """Every texture level a frame along the trajectory picks is made when the source opens,
    none on a frame (the demo's frame 35, the first at a new level, was rendered so late that
    it was dropped); the depths sampled over 200 s lie within the trajectory's depth range."""
    from pose_daemon.render.effects import linear_effects
    from pose_daemon.render.texture import marker_pyramid

    cfg = Config.default()
    camera = cfg.camera.model()
    marker = Marker(0.2017)  # a texture of its own: texture.py caches them by size
    source = SyntheticSource(camera, marker, trajectory=kind, realtime=False)
    source.open()
    pyramid = marker_pyramid(marker, linear_effects(source.effects))
    made = []
    pyramid._make = lambda ppm: made.append(ppm)  # a level made from here on is noted, not made
    near, far = source.path.depth_range_m()
    f_px = max(camera.fx, camera.fy) * source.effects.supersample
    for t_s in np.arange(0.0, 200.0, 0.05):
        depth = float(source.path.at(t_s).tvec[2])
        assert near <= depth <= far
        pyramid.pick(f_px / depth)  # what render_plane_layer asks for
    assert made == []
    source.close()


def test_synthetic_source_paces_in_real_time_and_ends() -> None:
    clock = FakeClock()
    source = SyntheticSource(
        CAM, Marker(0.2), fps=20.0, frames=3, effects=Effects.clean(), clock=clock, sleep=clock.sleep
    )
    with pytest.raises(SourceError):
        source.read()
    source.open()
    times = [source.read().t_capture_s for _ in range(3)]
    assert times == pytest.approx([100.0, 100.05, 100.1])
    assert clock.sleeps == pytest.approx([0.05, 0.05])
    with pytest.raises(EndOfStream):
        source.read()


def test_synthetic_source_pays_the_renderers_first_use_before_its_schedule(monkeypatch) -> None:
    """The renderer's first use is slow (caches, allocations): the source renders once, unseen,
    in open() before it starts its clock, so frame 0 does not carry that time as capture
    latency; the frames are the same as without it (the warm-up has its own random stream)."""
    from pose_daemon.capture import synthetic

    clock = FakeClock()
    calls = []

    def slow_first(*args, **kwargs):
        calls.append(clock.t)
        clock.t += 0.5 if len(calls) == 1 else 0.01
        return render_marker(*args, **kwargs)

    monkeypatch.setattr(synthetic, "render_marker", slow_first)
    source = SyntheticSource(CAM, Marker(0.2), fps=20.0, frames=2, clock=clock, sleep=clock.sleep)
    source.open()
    assert len(calls) == 1  # the warm-up, before any read
    frame = source.read()
    assert clock.t - frame.t_capture_s == pytest.approx(0.01)  # only its own render
    monkeypatch.undo()
    plain = SyntheticSource(CAM, Marker(0.2), fps=20.0, frames=2, realtime=False)
    plain._warm_up = lambda: None  # type: ignore[method-assign]  # as before the warm-up
    plain.open()
    assert np.array_equal(plain.read().image, frame.image)


def test_synthetic_source_behind_by_more_than_a_frame_restarts_its_schedule() -> None:
    clock = FakeClock()
    source = SyntheticSource(
        CAM, Marker(0.2), fps=20.0, frames=6, effects=Effects.clean(), clock=clock, sleep=clock.sleep
    )
    source.open()
    frames = [source.read()]  # due at 100.0
    clock.t += 1.0  # a slow first render: 19 frame periods lost
    frames.append(source.read())  # stamped now, not at its missed 100.05
    frames.append(source.read())  # one period later, on the new schedule
    clock.t += 0.08  # 101.13: behind 101.1 by less than a period, kept
    frames.append(source.read())
    clock.t += 0.0701  # 101.2001: behind 101.15 by just over a period
    frames.append(source.read())
    frames.append(source.read())
    assert [f.t_capture_s for f in frames] == pytest.approx([100.0, 101.0, 101.05, 101.1, 101.2001, 101.2501], abs=1e-9)
    assert clock.sleeps == pytest.approx([0.05, 0.05])
    assert source.restarts == 2
    # The trajectory goes on frame by frame: no frame's truth is skipped.
    assert [f.seq for f in frames] == list(range(6))
    assert [f.metadata["trajectory_t_s"] for f in frames] == pytest.approx([k / 20.0 for k in range(6)])


# --------------------------------------------------------------------------- picamera2


class _FakeRequest:
    def __init__(self, cam: _FakePicamera2) -> None:
        self.cam = cam
        self.released = False

    def make_array(self, name: str) -> np.ndarray:
        assert name == "lores"
        w, h = self.cam.config["lores"]["size"]
        stride = (w + 63) // 64 * 64  # rows padded, as libcamera does
        yuv = np.full((h * 3 // 2, stride), 128, np.uint8)
        yuv[:h, :w] = self.cam.y_plane
        yuv[:h, w:] = 255  # padding that must not leak into the frame
        return yuv

    def get_metadata(self) -> dict:
        self.cam.frame += 1
        return {
            "SensorTimestamp": 5_000_000_000 + self.cam.frame * 33_333_333,
            "ExposureTime": 4000,
            "AnalogueGain": 2.0,
            "Lux": 100.0,
        }

    def release(self) -> None:
        self.released = True
        self.cam.released += 1


class _FakeJob:
    """picamera2.job.Job: a concurrent.futures.Future the camera's event loop completes."""

    def __init__(self) -> None:
        self.future: Future = Future()

    def get_result(self, timeout=None):
        return self.future.result(timeout=timeout)

    def cancel(self) -> None:
        self.future.set_exception(CancelledError())


class _FakePicamera2:
    """The part of picamera2's interface the source uses (picamera2 >= 0.3.20: capture_request
    (wait=...), wait(job, timeout=...), cancel_all_and_flush())."""

    instances: list = []
    fail_start = False
    #: instance index -> frames it delivers before it stalls (stops completing requests).
    stall_after: dict = {}

    def __init__(self, camera_num: int = 0) -> None:
        if camera_num != 0:
            raise IndexError("list index out of range")
        self.config = None
        self.started = self.closed = False
        self.frame = 0
        self.released = 0
        self.y_plane = None
        self.jobs: list = []
        self.waits: list = []
        self.flushes = 0
        _FakePicamera2.instances.append(self)

    def create_video_configuration(self, main=None, lores=None, buffer_count=6, controls=None):
        return {"main": main, "lores": lores, "buffer_count": buffer_count, "controls": controls}

    def configure(self, config) -> None:
        self.config = config
        w, h = config["lores"]["size"]
        self.y_plane = (np.arange(w * h) % 251).astype(np.uint8).reshape(h, w)

    def start(self) -> None:
        if _FakePicamera2.fail_start:
            raise RuntimeError("Camera __init__ sequence did not complete.")
        self.started = True

    def capture_request(self, wait=None, signal_function=None, flush=None):
        """As picamera2's: a job run by the camera's event loop; ``wait`` True/None blocks, a
        number blocks at most that many seconds (TimeoutError), False gives the job."""
        time.sleep(0.002)  # a camera delivers frames at its own pace
        job = _FakeJob()
        stall_after = _FakePicamera2.stall_after.get(_FakePicamera2.instances.index(self))
        if stall_after is not None and self.frame >= stall_after:
            self.jobs.append(job)  # a stalled camera: the job never completes
        else:
            job.future.set_result(_FakeRequest(self))
        if wait is None:
            wait = signal_function is None
        timeout = None if wait is True else wait
        return job.get_result(timeout=timeout) if wait else job

    def wait(self, job, timeout=None):
        self.waits.append(timeout)
        return job.get_result(timeout=timeout)

    def cancel_all_and_flush(self) -> None:
        for job in self.jobs:
            job.cancel()
        self.jobs = []
        self.flushes += 1

    def stop(self) -> None:
        # picamera2's stop() is itself a job queued behind the pending ones: it would hang.
        assert not self.jobs, "stop() behind a pending capture job would never return"
        self.started = False

    def close(self) -> None:
        self.closed = True


@pytest.fixture
def fake_picamera2(monkeypatch):
    module = types.ModuleType("picamera2")
    module.Picamera2 = _FakePicamera2
    _FakePicamera2.instances = []
    _FakePicamera2.fail_start = False
    _FakePicamera2.stall_after = {}
    monkeypatch.setitem(sys.modules, "picamera2", module)
    return _FakePicamera2


def test_picamera2_y_plane_fixed_exposure_and_sensor_time(fake_picamera2) -> None:
    cfg = _camera_cfg("picamera2", width=600, height=400, fps=25.0, exposure_us=4000, analogue_gain=2.0)
    source = open_source(cfg)
    assert isinstance(source, Picamera2Source)
    source.open()
    cam = fake_picamera2.instances[0]
    assert cam.started
    assert cam.config["lores"] == {"size": (600, 400), "format": "YUV420"}
    assert cam.config["controls"] == {
        "FrameDurationLimits": (40000, 40000),
        "AeEnable": False,
        "ExposureTime": 4000,
        "AnalogueGain": 2.0,
    }
    f0, f1 = source.read(), source.read()
    assert f0.image.shape == (400, 600) and f0.image.dtype == np.uint8
    assert np.array_equal(f0.image, cam.y_plane)  # the Y plane only, no stride padding
    assert f0.t_capture_s == pytest.approx(5.033333333)
    assert f1.t_capture_s - f0.t_capture_s == pytest.approx(0.033333333)
    assert (f0.seq, f1.seq) == (0, 1)
    assert f0.metadata["ExposureTime"] == 4000 and "Lux" not in f0.metadata
    assert cam.released == 2  # every request goes back to the camera
    source.close()
    assert cam.closed


def test_picamera2_auto_exposure_and_failures(fake_picamera2, monkeypatch) -> None:
    source = Picamera2Source(640, 480, fps=30.0)
    assert source.controls() == {"FrameDurationLimits": (33333, 33333)}
    fake_picamera2.fail_start = True
    with pytest.raises(SourceError, match="cannot start camera 0: Camera __init__"):
        source.open()
    with pytest.raises(SourceError, match="cannot start camera 1"):
        Picamera2Source(640, 480, camera_index=1).open()
    monkeypatch.setitem(sys.modules, "picamera2", None)  # not installed
    with pytest.raises(SourceError, match="picamera2 module is not installed"):
        Picamera2Source(640, 480).open()


def test_picamera2_stalled_camera_is_a_source_error_not_a_hang(fake_picamera2) -> None:
    fake_picamera2.stall_after = {0: 2}
    source = Picamera2Source(64, 48, fps=30.0, read_timeout_s=0.05)
    source.open()
    cam = fake_picamera2.instances[0]
    assert [source.read().seq for _ in range(2)] == [0, 1]
    with pytest.raises(SourceError, match=r"no frame from camera 0 within 0.05 s \(camera stalled\)"):
        source.read()
    # picamera2's own timeout, longer for the first frame after start.
    assert cam.waits == [3.0, 0.05, 0.05]
    assert cam.flushes == 1 and cam.jobs == []  # the hung job cancelled: stop() can run
    source.close()
    assert cam.closed and not cam.started
    # The default: four frame periods, at least a second.
    assert Picamera2Source(64, 48, fps=30.0).read_timeout_s == 1.0
    assert Picamera2Source(64, 48, fps=2.0).read_timeout_s == 2.0


def test_picamera2_stall_in_the_pipeline_becomes_a_reopen(fake_picamera2, caplog) -> None:
    from pipeline_fakes import FakeOutput, FakeProcessor, outputs_of

    from pose_daemon.pipeline import Pipeline

    fake_picamera2.stall_after = {0: 3}  # the first camera stalls; the reopened one works
    # The timeout is far above what a loaded machine takes to hand over a frame, so only the
    # stalled camera times out.
    source = Picamera2Source(64, 48, fps=30.0, read_timeout_s=0.5)
    # The fake's sensor time stamps start at 5 s: no latency budget applies here.
    pipeline = Pipeline(
        source,
        FakeProcessor(),
        outputs_of(FakeOutput),
        latency_budget_s=1e9,
        source_retry_s=0.01,
        source_retry_max_s=0.01,
    )
    (out,) = pipeline.outputs
    caplog.set_level("WARNING", logger="pose_daemon.pipeline")
    pipeline.start()
    try:
        deadline = time.monotonic() + 30.0  # a bound a loaded machine cannot reach, not a measure
        while time.monotonic() < deadline:
            # More results than the first camera gave frames: the reopened one delivers.
            if len(out.got) > 3:
                break
            time.sleep(0.005)
    finally:
        pipeline.stop()
    first, second = fake_picamera2.instances[:2]
    assert first.closed and first.flushes == 1 and second.frame >= 1
    assert pipeline.stats.snapshot()["source_failures"] == 1
    assert [r.getMessage() for r in caplog.records if r.name == "pose_daemon.pipeline"] == [
        "source failed: source picamera2: no frame from camera 0 within 0.5 s (camera stalled); reopening in 0.0 s"
    ]
    assert len(out.got) > 3 and len(fake_picamera2.instances) == 2


# --------------------------------------------------------------------------- files


def _frames(n: int, seed: int = 1):
    marker = Marker(0.2)
    poses = trajectory("wall", n, 30.0, seed=seed, camera=CAM, marker=marker)
    return [render_marker(CAM, marker, p.rvec, p.tvec, rng=np.random.default_rng(i)).image for i, p in enumerate(poses)]


def test_video_file_written_by_videowriter(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    images = _frames(12)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 15.0, (640, 480), isColor=True)
    assert writer.isOpened()
    for img in images:
        writer.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    writer.release()
    for source in (
        open_source(_camera_cfg(f"video:{path}"), realtime=False),
        OpenCVSource(str(path), "video"),
        ReplaySource(path, realtime=False),
    ):
        source.open()
        got = []
        while True:
            try:
                got.append(source.read())
            except EndOfStream:
                break
        source.close()
        assert len(got) == 12
        assert [f.t_capture_s for f in got] == pytest.approx([i / 15.0 for i in range(12)])
        for f, img in zip(got, images):
            assert f.image.shape == (480, 640) and f.image.ndim == 2
            assert np.abs(f.image.astype(int) - img).mean() < 3.0  # MJPG is lossy


def test_missing_video_and_camera_are_source_errors(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="cannot open video"):
        OpenCVSource(str(tmp_path / "none.avi"), "video").open()
    bogus = tmp_path / "bogus.mp4"
    bogus.write_bytes(b"not a video at all")
    with pytest.raises(SourceError):
        ReplaySource(bogus).open()


def test_folder_sorted_by_name_with_a_corrupt_frame_skipped(tmp_path: Path, caplog) -> None:
    images = _frames(5)
    for i, img in enumerate(images):
        cv2.imwrite(str(tmp_path / f"img_{i:02d}.png"), img)
    (tmp_path / "img_02.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")  # corrupt, in the middle
    (tmp_path / "notes.txt").write_text("not an image")
    source = open_source(_camera_cfg(f"replay:{tmp_path}", fps=10.0), realtime=False)
    source.open()
    got = []
    with caplog.at_level("WARNING"):
        while True:
            try:
                got.append(source.read())
            except EndOfStream:
                break
    assert [f.seq for f in got] == [0, 1, 3, 4]
    assert [f.t_capture_s for f in got] == pytest.approx([0.0, 0.1, 0.3, 0.4])
    for f in got:
        assert np.array_equal(f.image, images[f.seq])  # PNG: lossless
    assert [Path(p).name for p, _ in source.skipped] == ["img_02.png"]
    assert "img_02.png" in caplog.text and "corrupt" in caplog.text


def test_replay_paces_at_recorded_times(tmp_path: Path) -> None:
    for i, img in enumerate(_frames(3)):
        cv2.imwrite(str(tmp_path / f"{i}.png"), img)
    clock = FakeClock(50.0)
    source = ReplaySource(tmp_path, realtime=True, fps=4.0, clock=clock, sleep=clock.sleep)
    source.open()
    frames = [source.read() for _ in range(3)]
    assert [f.t_capture_s for f in frames] == pytest.approx([50.0, 50.25, 50.5])
    assert [f.metadata["t_recorded_s"] for f in frames] == pytest.approx([0.0, 0.25, 0.5])
    assert clock.sleeps == pytest.approx([0.25, 0.25])


def test_replay_bad_paths(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="no such file or folder"):
        ReplaySource(tmp_path / "missing").open()
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(SourceError, match="not a recording"):
        ReplaySource(empty).open()
    text = tmp_path / "poses.txt"
    text.write_text("x")
    with pytest.raises(SourceError, match="not a recording, a folder of images or a video"):
        ReplaySource(text).open()


def test_live_opencv_source_stamps_at_grab_and_reports_a_lost_camera(tmp_path: Path) -> None:
    # A file opened as a "camera": the live path's time stamps and its failure at the end.
    path = tmp_path / "cam.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (320, 240))
    for i in range(3):
        writer.write(np.full((240, 320, 3), 40 * i, np.uint8))
    writer.release()
    clock = FakeClock(7.0)
    source = OpenCVSource(str(path), "camera", clock=clock)
    source.open()
    frames = []
    for _ in range(3):
        frames.append(source.read())
        clock.t += 0.04
    assert [f.t_capture_s for f in frames] == pytest.approx([7.0, 7.04, 7.08])
    assert [int(f.image.mean()) for f in frames] == pytest.approx([0, 40, 80], abs=3)
    with pytest.raises(SourceError, match="no frame"):
        source.read()
    source.close()
    with pytest.raises(SourceError, match="before open"):
        source.read()


def test_recording_cut_off_mid_line_replays_the_frames_before_it(tmp_path: Path, caplog) -> None:
    from pose_daemon.capture.base import Frame
    from pose_daemon.capture.recording import INDEX_FILE, RecordingWriter, read_index

    rec = tmp_path / "rec"
    with RecordingWriter(rec, Camera(fx=500.0, fy=500.0, cx=159.5, cy=119.5, width=320, height=240)) as w:
        for i, img in enumerate(_frames(3)):
            w.write(Frame(image=cv2.resize(img, (320, 240)), t_capture_s=10.0 + i / 30, seq=i))
    index = rec / INDEX_FILE
    full = index.read_text()
    # A power loss while the third line was being written: no line end after it.
    index.write_text(full[:-25])
    assert [e["seq"] for e in read_index(rec)] == [0, 1]
    assert "unfinished last line" in caplog.text
    source = ReplaySource(rec)
    source.open()
    assert [source.read().seq for _ in range(2)] == [0, 1]
    with pytest.raises(EndOfStream):
        source.read()
    # A damaged line anywhere else is still an error naming it.
    lines = full.splitlines(keepends=True)
    index.write_text(lines[0] + "garbage\n" + lines[2])
    with pytest.raises(SourceError, match=r"index.jsonl:2: not a frame entry"):
        read_index(rec)
    index.write_text(full + "garbage\n")
    with pytest.raises(SourceError, match=r"index.jsonl:4: not a frame entry"):
        read_index(rec)


# --------------------------------------------------------------------------- grey conversion


def test_as_gray_is_the_one_conversion_of_sources_detector_and_calibration() -> None:
    from pose_daemon.capture import opencv, replay
    from pose_daemon.detect import detector
    from pose_daemon.image import as_gray
    from pose_daemon.tools.calibrate import collect as calibrate

    assert detector.as_gray is as_gray and opencv.as_gray is as_gray
    assert replay.as_gray is as_gray and calibrate.as_gray is as_gray
    grey = (np.arange(12 * 16) % 256).astype(np.uint8).reshape(12, 16)
    assert np.array_equal(as_gray(grey), grey)
    assert np.array_equal(as_gray(grey[:, :, None]), grey)
    assert np.array_equal(as_gray(grey.astype(np.uint16) << 8 | 0xFF), grey)  # the top byte
    bgr = np.dstack([grey, grey, grey])
    assert np.array_equal(as_gray(bgr), grey)
    assert np.array_equal(as_gray(np.dstack([bgr, np.full_like(grey, 7)])), grey)


@pytest.mark.parametrize(
    "image, message",
    [
        (np.zeros((4, 4), np.float32), "uint8 (or uint16) grey levels, got dtype float32"),
        (np.zeros((4, 4), np.int32), "got dtype int32"),
        (np.zeros((4, 4, 2), np.uint8), "got shape (4, 4, 2)"),
        (np.zeros((2, 4, 4, 3), np.uint8), "got shape (2, 4, 4, 3)"),
        (np.zeros((0, 4), np.uint8), "image is empty"),
        ([[0, 1]], "must be a numpy array, got list"),
    ],
)
def test_as_gray_refuses_what_it_cannot_convert(image, message: str) -> None:
    from pose_daemon.image import as_gray

    with pytest.raises(ValueError) as info:
        as_gray(image)
    assert message in str(info.value)


def test_a_float_image_in_a_replay_folder_is_skipped_by_name(tmp_path: Path) -> None:
    frames = _frames(2)
    cv2.imwrite(str(tmp_path / "000.png"), frames[0])
    assert cv2.imwrite(str(tmp_path / "001.tiff"), frames[1].astype(np.float32))
    source = ReplaySource(tmp_path, realtime=False)
    source.open()
    assert source.read().seq == 0
    with pytest.raises(EndOfStream):
        source.read()
    assert [(Path(f).name, why) for f, why in source.skipped] == [
        ("001.tiff", "image must be uint8 (or uint16) grey levels, got dtype float32")
    ]


def _recording(path: Path, times_s):
    from pose_daemon.capture.base import Frame
    from pose_daemon.capture.recording import RecordingWriter

    with RecordingWriter(path, Camera(fx=500.0, fy=500.0, cx=159.5, cy=119.5, width=320, height=240)) as w:
        for i, (img, t) in enumerate(zip(_frames(len(times_s)), times_s)):
            w.write(Frame(image=cv2.resize(img, (320, 240)), t_capture_s=t, seq=i))
    return path


def test_replay_cuts_an_absurd_step_of_the_index_and_says_so(tmp_path: Path, caplog) -> None:
    from pose_daemon.capture.replay import MAX_GAP_S

    # An index that jumps 1e6 s forward (11 days of sleep) and, later, 50.3 s backwards.
    times = [10.0, 10.1, 1e6 + 10.2, 1e6 + 10.3, 1e6 - 40.0, 1e6 - 39.9]
    rec = _recording(tmp_path / "rec", times)
    clock = FakeClock(50.0)
    source = ReplaySource(rec, realtime=True, clock=clock, sleep=clock.sleep)
    source.open()
    with caplog.at_level("WARNING"):
        frames = [source.read() for _ in times]
    period = 1.0 / source.fps
    assert clock.sleeps == pytest.approx([0.1, period, 0.1, period, 0.1])
    assert max(clock.sleeps) <= MAX_GAP_S
    # On this run's clock the frames keep their recorded spacing around the cut steps.
    assert [f.t_capture_s for f in frames] == pytest.approx(
        [50.0, 50.1, 50.1 + period, 50.2 + period, 50.2 + 2 * period, 50.3 + 2 * period]
    )
    assert [f.metadata["t_recorded_s"] for f in frames] == pytest.approx(times)
    assert source.gaps_cut == 2
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 2
    assert "frame 2 is recorded 1e+06 s after the previous one" in warnings[0]
    assert "frame 4 is recorded -50.3 s after the previous one" in warnings[1]


@pytest.mark.parametrize("file", ["../outside.png", "frames/../../outside.png", "/tmp/outside.png"])
def test_index_entry_outside_the_recording_folder_is_refused(tmp_path: Path, file: str) -> None:
    from pose_daemon.capture.recording import INDEX_FILE, read_index

    rec = _recording(tmp_path / "rec", [0.0, 0.1, 0.2])
    cv2.imwrite(str(tmp_path / "outside.png"), _frames(1)[0])
    index = rec / INDEX_FILE
    lines = index.read_text().splitlines(keepends=True)
    lines[1] = lines[1].replace('"frames/000001.png"', f'"{file}"')
    index.write_text("".join(lines))
    with pytest.raises(SourceError) as err:
        read_index(rec)
    assert str(err.value) == (
        f'{index}:2: frame file "{file}" lies outside the recording folder (absolute, or with ..)'
    )
    with pytest.raises(SourceError, match="lies outside"):
        ReplaySource(rec).open()


def _damaged_video(path: Path, n: int = 90) -> Path:
    # MPEG-4 part 2 in MP4, 20% of the bytes in the middle overwritten: the decoder stops there.
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (320, 240), False)
    assert writer.isOpened()
    rng = np.random.default_rng(0)
    for i in range(n):
        img = np.full((240, 320), 200, np.uint8)
        cv2.rectangle(img, (60 + i, 60), (160 + i, 160), 30, -1)
        writer.write((img + rng.integers(0, 5, img.shape)).astype(np.uint8))
    writer.release()
    data = bytearray(path.read_bytes())
    a, b = int(len(data) * 0.4), int(len(data) * 0.6)
    data[a:b] = rng.integers(0, 256, b - a, dtype=np.uint8).tobytes()
    path.write_bytes(bytes(data))
    return path


def test_damaged_video_counts_and_reports_the_lost_frames(tmp_path: Path) -> None:
    path = _damaged_video(tmp_path / "damaged.mp4")
    source = OpenCVSource(str(path), "video")
    source.open()
    got = []
    with pytest.raises(EndOfStream) as end:
        while True:
            got.append(source.read())
    source.close()
    assert source.frame_count == 90 and 0 < len(got) < 90
    assert source.lost == 90 - len(got)
    assert end.value.lost == f"{source.lost} of 90 frames of {path} could not be decoded: a damaged video"
    # The frames that came keep their places on the video's time line.
    assert [f.t_capture_s for f in got] == pytest.approx([f.seq / 30.0 for f in got])
    # An undamaged video loses nothing and says nothing.
    clean = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(clean), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (320, 240), False)
    for img in _frames(5):
        writer.write(cv2.resize(img, (320, 240)))
    writer.release()
    source = OpenCVSource(str(clean), "video")
    source.open()
    assert [source.read().seq for _ in range(5)] == [0, 1, 2, 3, 4]
    with pytest.raises(EndOfStream) as end:
        source.read()
    assert end.value.lost == "" and source.lost == 0
