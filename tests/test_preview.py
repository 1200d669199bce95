"""The live preview over real sockets: the HTTP endpoints, the MJPEG stream, a viewer that stops
reading, the snapshot and record actions, the warnings, and the daemon that serves it."""

from __future__ import annotations

import dataclasses
import functools
import json
import re
import socket
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest
from pipeline_fakes import FakeSource, outputs_of

from pose_daemon.capture import recording
from pose_daemon.capture.base import Frame
from pose_daemon.capture.replay import ReplaySource
from pose_daemon.config import ConfigError, parse_config
from pose_daemon.pipeline import Pipeline
from pose_daemon.preview import FrameTap, PreviewServer
from pose_daemon.preview.warnings import Context, evaluate
from pose_daemon.processing.marker import FrameProcessor
from pose_daemon.render import render_marker, trajectory
from pose_daemon.result import FrameResult
from pose_daemon.service import Service

BASE = """
[camera]
source = "synthetic"
fps = 30.0
[preview]
listen = "127.0.0.1:0"
max_fps = {fps}
max_width = {width}
data_dir = "{data}"
"""


def _cfg(tmp_path: Path, fps: float = 5.0, width: int = 640, extra: str = ""):
    return parse_config(BASE.format(fps=fps, width=width, data=tmp_path / "data") + extra, "p.toml")


@pytest.fixture(scope="module")
def processed():
    """Real frames of the wall trajectory with their real processing results."""
    cfg = parse_config('[camera]\nsource = "synthetic"\n', "c.toml")
    camera, marker = cfg.camera.model(), cfg.marker.model()
    processor = FrameProcessor.from_config(cfg)
    poses = trajectory("wall", 8, fps=10.0, seed=1, camera=camera, marker=marker)
    out = []
    for i, p in enumerate(poses):
        image = render_marker(camera, marker, p.rvec, p.tvec, rng=np.random.default_rng(i)).image
        frame = Frame(image, 100.0 + i / 30.0, i)
        out.append((frame, processor.process(frame)))
    assert all(r.ok for _, r in out)
    return out


class Feeder:
    """Plays the processing thread: hands (frame, result) to the tap, numbering frames on."""

    def __init__(self, tap: FrameTap, pipeline: Pipeline, processed, t0_s: float = 100.0) -> None:
        self.tap, self.pipeline, self.processed = tap, pipeline, processed
        self.seq = 0
        self.t0_s = t0_s
        self._stop = threading.Event()
        self._thread = None

    def feed(self, n: int = 1, period_s: float = 1 / 30) -> None:
        for _ in range(n):
            frame, result = self.processed[self.seq % len(self.processed)]
            t = self.t0_s + self.seq * period_s
            f = Frame(frame.image, t, self.seq)
            r = dataclasses.replace(result, seq=self.seq, t_capture_s=t, stage_s=dict(result.stage_s))
            self.pipeline.stats.processed_frame(r, {"detect": 0.001})
            self.tap(f, r)
            self.seq += 1

    def start(self, pause_s: float = 0.005) -> None:
        def run():
            while not self._stop.is_set():
                self.feed()
                time.sleep(pause_s)

        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)


@pytest.fixture
def served(tmp_path, processed):
    servers = []

    def make(**kw):
        cfg = _cfg(tmp_path, **kw)
        processor = FrameProcessor.from_config(cfg)
        tap = FrameTap(processor)
        pipeline = Pipeline(FakeSource(0), processor, outputs_of())
        server = PreviewServer(cfg, pipeline, tap)
        server.start()
        servers.append(server)
        return server, Feeder(tap, pipeline, processed)

    yield make
    for s in servers:
        s.stop()


def _get(server, path, **kw):
    with urllib.request.urlopen(server.url.rstrip("/") + path, timeout=10, **kw) as resp:
        return resp.status, resp.headers.get("Content-Type"), resp.read()


def _post(server, path, header=True):
    req = urllib.request.Request(
        server.url.rstrip("/") + path, data=b"", method="POST", headers={"X-Pose-Daemon": "1"} if header else {}
    )
    try:
        with urllib.request.urlopen(req, timeout=10) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as err:
        return err.code, json.loads(err.read())


def _wait(cond, timeout_s=60.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.02)
    return cond()


# --------------------------------------------------------------------------- config


def test_preview_is_off_unless_present_and_its_keys_are_checked(tmp_path):
    assert parse_config("", "c.toml").preview is None
    cfg = parse_config("[preview]\n", "c.toml")
    assert (cfg.preview.listen, cfg.preview.max_fps, cfg.preview.max_width) == ("127.0.0.1:8080", 5.0, 640)
    assert cfg.preview.address == ("127.0.0.1", 8080)
    assert parse_config('[preview]\nlisten = "[::1]:9000"\n', "c.toml").preview.address == ("::1", 9000)
    assert "[preview]" in cfg.to_toml() and "[preview]" not in parse_config("", "c.toml").to_toml()
    for text, key in (
        ('listen = "127.0.0.1"', "listen"),
        ('listen = "h:70000"', "listen"),
        ("max_fps = 0", "max_fps"),
        ("max_width = 10", "max_width"),
        ("port = 1", "port"),
    ):
        with pytest.raises(ConfigError) as err:
            parse_config(f"[preview]\n{text}\n", "c.toml")
        msg = str(err.value)
        assert msg.startswith(f"c.toml: [preview] {key}:") and "\n" not in msg


# --------------------------------------------------------------------------- endpoints


def test_status_json_is_the_status_and_the_last_per_frame_object(served):
    server, feeder = served()
    status, ctype, body = _get(server, "/status.json")
    data = json.loads(body)
    assert ctype == "application/json" and data["last"] is None
    assert [w["code"] for w in data["status"]["warnings"]] == []
    feeder.feed(20)
    data = json.loads(_get(server, "/status.json")[2])
    assert set(data) == {"status", "last"}
    last_result = server.tap.latest.result
    assert data["last"] == json.loads(json.dumps(last_result.to_json_dict()))
    s = data["status"]
    assert s["frames"] == 20 and s["detected"] == 20 and s["detected_pct"] == 100.0
    assert s["fps"] == pytest.approx(30.0, rel=0.01)  # from the frames' capture times
    assert s["latency_ms"]["detect"][0] == pytest.approx(1.0)
    assert "frames 20, drops none" in s["line"]  # the status line, as the journal has it
    assert s["warnings"] == [] and s["source"] == "starting"
    hist = json.loads(_get(server, "/history.json")[2])
    assert len(hist["t"]) == 20 and hist["t"][-1] == 0.0
    assert hist["z"][-1] == pytest.approx(float(last_result.pose.camera_position[2]), abs=1e-4)
    status, ctype, page = _get(server, "/")
    assert ctype.startswith("text/html") and b"/stream.mjpg" in page
    assert b"http://" not in page and b"https://" not in page  # no external assets
    with pytest.raises(urllib.error.HTTPError) as err:
        _get(server, "/nothing")
    assert err.value.code == 404


def test_status_json_camera_fps_is_the_status_lines_figure(served):
    """camera_fps has one owner, the pipeline's status figures: status.json's first answer has
    it (it was null there while the line said 29.2), equal to the line's "(camera N)"."""
    server, feeder = served()
    server.pipeline.stats.count("captured", 30)
    feeder.feed(20)
    for _ in range(2):  # the first answer, and one after it
        s = json.loads(_get(server, "/status.json")[2])["status"]
        said = re.search(r"fps \(camera ([0-9.]+)\)", s["line"])
        assert s["camera_fps"] is not None and said is not None, s
        assert abs(s["camera_fps"] - float(said.group(1))) <= 0.051 and s["camera_fps"] > 0  # 2 vs 1 decimals


def test_nothing_is_encoded_while_nobody_watches_and_a_snapshot_is_capped_in_width(served):
    server, feeder = served(width=320)
    with pytest.raises(urllib.error.HTTPError) as err:
        _get(server, "/snapshot.jpg")
    assert err.value.code == 503
    feeder.feed(50)
    _get(server, "/status.json")
    assert server.counts["encoded"] == 0
    status, ctype, body = _get(server, "/snapshot.jpg")
    image = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
    assert ctype == "image/jpeg" and image.shape == (240, 320, 3)
    assert server.counts["encoded"] == 1
    _get(server, "/snapshot.jpg")
    assert server.counts["encoded"] == 1  # the same frame is encoded once


def _read_parts(sock_file, n):
    """n JPEG parts of a multipart/x-mixed-replace stream (after the response headers)."""
    parts = []
    while len(parts) < n:
        line = sock_file.readline()
        if not line:
            break
        if line.strip() != b"--frame":
            continue
        headers = {}
        while True:
            h = sock_file.readline().strip()
            if not h:
                break
            k, v = h.decode().split(":", 1)
            headers[k.lower()] = v.strip()
        assert headers["content-type"] == "image/jpeg"
        parts.append(sock_file.read(int(headers["content-length"])))
    return parts


def _open_stream(server, rcvbuf=None):
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if rcvbuf:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    s.settimeout(20)
    s.connect(("127.0.0.1", server.port))
    s.sendall(b"GET /stream.mjpg HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
    f = s.makefile("rb")
    assert f.readline().split()[1] == b"200"
    headers = []
    while True:
        line = f.readline().strip()
        if not line:
            break
        headers.append(line.decode().lower())
    assert "content-type: multipart/x-mixed-replace; boundary=frame" in headers
    return s, f


def test_the_stream_sends_annotated_frames_as_a_multipart_jpeg_stream(served):
    server, feeder = served(fps=10.0)
    feeder.start()
    try:
        s, f = _open_stream(server)
        parts = _read_parts(f, 4)
        f.close()
        s.close()
    finally:
        feeder.stop()
    assert len(parts) == 4
    for data in parts:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        assert img.shape == (480, 640, 3)
        # The overlay: saturated green outline pixels on a grey rendering.
        b, g, r = (img[:, :, i].astype(int) for i in range(3))
        assert np.count_nonzero((g > 180) & (r < 90) & (b < 90)) > 100
    # A frame is counted once its write returned, which can be after the viewer has read it.
    assert _wait(lambda: server.counts["frames_sent"] >= 4)
    assert _wait(lambda: server.counts["viewers"] == 0)


def test_a_viewer_gets_the_newest_frame_and_those_it_missed_are_counted_skipped(served):
    """Frames that came while a viewer's write was under way are skipped, the newest sent."""
    server, feeder = served(fps=30.0)
    sent, in_write, release = [], threading.Event(), threading.Event()

    def write(data: bytes) -> None:
        sent.append(data)
        if len(sent) == 1:  # the first frame's write takes its time
            in_write.set()
            assert release.wait(60)

    feeder.feed()
    viewer = threading.Thread(target=server.stream, args=(write, lambda: len(sent) >= 2), daemon=True)
    viewer.start()
    assert in_write.wait(60)
    feeder.feed(5)  # frames 1-5 arrive during the write
    release.set()
    viewer.join(60)
    assert not viewer.is_alive()
    assert len(sent) == 2
    assert server.counts["frames_sent"] == 2
    assert server.counts["frames_skipped"] == 4  # 1-4: the viewer got 5, the newest


def test_stop_waits_for_the_frame_a_viewer_is_being_sent_so_the_counts_after_it_agree(served):
    """What `bench pipeline` reads after stop(): every frame encoded was also counted sent."""
    server, feeder = served(fps=30.0)
    in_write, release = threading.Event(), threading.Event()

    def slow_write(data: bytes) -> None:  # a viewer whose socket takes its time
        in_write.set()
        assert release.wait(60)

    viewer = threading.Thread(target=server.stream, args=(slow_write,), daemon=True)
    viewer.start()
    feeder.feed()
    assert in_write.wait(60)
    stopper = threading.Thread(target=server.stop, kwargs={"timeout_s": 60.0}, daemon=True)
    stopper.start()
    assert _wait(lambda: server.stopping)
    stopper.join(0.3)
    assert stopper.is_alive()  # the write is still under way: stop() waits for it
    release.set()
    stopper.join(60)
    assert not stopper.is_alive()
    assert server.counts["encoded"] == server.counts["frames_sent"] == 1
    viewer.join(5)


def test_a_viewer_that_stops_reading_is_dropped_and_holds_up_nothing(served):
    server, feeder = served(fps=30.0)
    feeder.start(pause_s=0.01)
    try:
        stalled, sf = _open_stream(server, rcvbuf=4096)  # reads the headers, then nothing
        reader, rf = _open_stream(server)
        assert _wait(lambda: server.counts["viewers"] == 2)
        fed_before = server.tap.frames
        # The stalled viewer fills its socket buffers, then its send times out.
        assert _wait(lambda: server.counts["viewers_dropped"] == 1, timeout_s=120)
        assert server.tap.frames > fed_before + 10  # the feeder never waited
        parts = _read_parts(rf, 3)  # the other viewer is still served
        assert len(parts) == 3
        assert _wait(lambda: server.counts["viewers"] == 1)
        for sock in (rf, reader, sf, stalled):
            sock.close()
    finally:
        feeder.stop()
    assert _wait(lambda: server.counts["viewers"] == 0)


def test_snapshot_and_record_write_into_the_data_directory_in_the_recording_format(served, tmp_path):
    server, feeder = served()
    assert _post(server, "/snapshot")[0] == 409  # no frame yet
    feeder.feed(3)
    code, body = _post(server, "/snapshot", header=False)
    assert code == 403 and "X-Pose-Daemon" in body["error"]
    code, body = _post(server, "/snapshot")
    assert code == 200
    saved = cv2.imread(body["saved"], cv2.IMREAD_UNCHANGED)
    assert Path(body["saved"]).parent == tmp_path / "data" / "snapshots"
    assert np.array_equal(saved, server.tap.latest.frame.image)

    assert _post(server, "/record?seconds=abc")[0] == 400
    assert _post(server, "/record?seconds=0")[0] == 400
    code, body = _post(server, "/record?seconds=0.5")
    assert code == 200
    assert _post(server, "/record?seconds=1")[0] == 409  # one recording at a time
    feeder.feed(30)  # 1 s of frames at 30 fps
    rec = server.recorder
    assert rec.join(30) and rec.done.is_set()
    path = Path(body["recording"])
    assert path.parent == tmp_path / "data" / "recordings" and recording.is_recording(path)
    entries = recording.read_index(path)
    assert len(entries) == 15 and rec.dropped == 0  # frames within 0.5 s of the first
    src = ReplaySource(path)
    src.open()
    first = src.read()
    src.close()
    assert np.array_equal(first.image, feeder.processed[entries[0]["seq"] % len(feeder.processed)][0].image)
    meta = recording.read_meta(path)
    assert meta["camera"]["fx"] == server.camera.fx and meta["marker"]["type"] == "square"
    status = json.loads(_get(server, "/status.json")[2])["status"]
    assert status["recording"]["frames"] == 15 and status["recording"]["done"]
    assert _post(server, "/record?seconds=0.1")[0] == 200  # a new one once the last is done


# --------------------------------------------------------------------------- warnings


def _tapped(processed, corners_scale=None, error=None, ok=True):
    from pose_daemon.preview.tap import Tapped

    frame, result = processed[0]
    r = dataclasses.replace(result)
    if not ok:
        r = FrameResult(seq=0, t_capture_s=0.0, error=error or "no marker")
    elif corners_scale is not None:
        c = r.corners.mean(axis=0)
        r = dataclasses.replace(r, corners=c + (r.corners - c) * corners_scale)
    return Tapped(frame, r, None), r


def _codes(**kw):
    base = dict(last=None, history=[], source_state="ok", since_frame_s=0.0, recent_drops={}, outputs=[])
    base.update(kw)
    return [w.code for w in evaluate(Context(**base))]


def test_each_cause_of_a_missing_pose_gives_its_warning(processed):
    tracked, r = _tapped(processed)
    assert _codes(last=tracked, history=[r]) == []
    lost, lost_r = _tapped(processed, ok=False)
    assert _codes(last=lost, history=[lost_r]) == ["no_marker"]
    small, small_r = _tapped(processed, corners_scale=0.1)
    assert _codes(last=small, history=[small_r]) == ["marker_small"]
    texts = evaluate(
        Context(last=lost, history=[small_r, lost_r], source_state="ok", since_frame_s=0.0, recent_drops={}, outputs=[])
    )
    assert "last seen" in texts[0].text and "bigger marker" in texts[0].text
    bad, _ = _tapped(processed, ok=False, error="pose: corners are collinear")
    assert _codes(last=bad) == ["pose_failed"]
    assert _codes(source_state="failed (camera unplugged), reopening in 0.5 s") == ["source"]
    assert _codes(since_frame_s=3.0) == ["stalled"]
    assert _codes(recent_drops={"late": 2}) == ["late"]
    assert _codes(recent_drops={"gated": 3, "inconsistent": 1}) == ["withheld"]
    from pose_daemon.attitude import Attitude
    from pose_daemon.preview.tap import Tapped

    frame = tracked.frame
    without = Tapped(frame, dataclasses.replace(r, attitude=None), None)
    with_att = Tapped(frame, dataclasses.replace(r, attitude=Attitude((0.0, 0.0, 0.0), 0.01)), None)
    assert _codes(last=without, history=[r], attitude_expected=True) == ["attitude_stale"]
    assert _codes(last=with_att, history=[r], attitude_expected=True) == []
    assert _codes(last=without, history=[r]) == []  # no live attitude configured: nothing to miss
    assert _codes(recent_drops={"full[mavlink]": 1}) == ["output_drops"]
    mav = {
        "name": "mavlink",
        "link_up": True,
        "link": "up, waiting for the autopilot's HEARTBEAT",
        "wait_heartbeat": True,
        "autopilot": None,
        "connection": "/dev/serial0",
    }
    assert _codes(outputs=[mav]) == ["autopilot_not_heard"]
    assert _codes(outputs=[dict(mav, autopilot=1)]) == []
    assert _codes(outputs=[dict(mav, link_up=False, link="down (no such device)")]) == ["output_down"]


def test_the_mavlink_output_that_waits_for_the_autopilot_shows_on_the_page(tmp_path, processed):
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    cfg = _cfg(tmp_path, extra=f'[output.mavlink]\nconnection = "udpout:127.0.0.1:{sink.getsockname()[1]}"\n')
    from pose_daemon.outputs import open_outputs

    processor = FrameProcessor.from_config(cfg)
    tap = FrameTap(processor)
    pipeline = Pipeline(FakeSource(0), processor, functools.partial(open_outputs, cfg))
    outputs = pipeline.outputs
    server = PreviewServer(cfg, pipeline, tap)
    server.start()
    try:
        Feeder(tap, pipeline, processed).feed(3)

        def codes():
            server._warnings_cache = (-1e18, [])
            return [w["code"] for w in json.loads(_get(server, "/status.json")[2])["status"]["warnings"]]

        assert _wait(lambda: "autopilot_not_heard" in codes(), timeout_s=20)
    finally:
        server.stop()
        for o in outputs:
            o.close()
        sink.close()


# --------------------------------------------------------------------------- in the daemon


def test_the_daemon_serves_the_preview_and_stops_it_cleanly(tmp_path):
    cfg = _cfg(tmp_path, extra="[pipeline]\nlatency_budget_s = 1.0\n")
    service = Service(cfg, outputs=outputs_of())
    assert service.pipeline.frame_observer is service.preview.tap
    code = []
    t = threading.Thread(target=lambda: code.append(service.run()), daemon=True)
    t.start()
    try:
        assert _wait(lambda: service.preview.tap.latest is not None, timeout_s=60)
        data = json.loads(_get(service.preview, "/status.json")[2])
        assert data["status"]["source"] == "ok" and data["last"]["frame"] >= 0
        assert data["status"]["detector_step"] in ("follow", "roi", "full", None)
    finally:
        service.request_stop("test")
        t.join(10)
    assert code == [0]
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", service.preview.port), timeout=2).close()


def test_a_taken_port_leaves_the_daemon_running_without_the_preview(tmp_path, caplog):
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen(1)
    text = BASE.format(fps=5.0, width=640, data=tmp_path).replace("127.0.0.1:0", f"127.0.0.1:{busy.getsockname()[1]}")
    cfg = parse_config(text, "p.toml")
    with caplog.at_level("ERROR"):
        service = Service(cfg, outputs=outputs_of())
    busy.close()
    assert service.preview is None and service.pipeline.frame_observer is None
    assert any("preview: cannot listen on 127.0.0.1:" in r.getMessage() for r in caplog.records)


def test_the_annotated_frame_shows_the_rejected_solution_and_the_warnings(processed):
    from pose_daemon.draw import REJECTED_COLOUR, WARNING_COLOUR, annotate_live

    cfg = parse_config("", "c.toml")
    frame, result = processed[3]
    assert result.pose.alternative is not None
    plain = annotate_live(
        frame.image,
        dataclasses.replace(result, pose=dataclasses.replace(result.pose, alternative=None)),
        cfg.camera.model(),
        cfg.marker.model(),
    )
    live = annotate_live(
        frame.image,
        result,
        cfg.camera.model(),
        cfg.marker.model(),
        detector_step="follow",
        warnings=["marker too small"],
    )

    def count(image, colour):
        return int(np.count_nonzero(np.all(np.abs(image.astype(int) - colour) < 40, axis=2)))

    assert count(live, REJECTED_COLOUR) > count(plain, REJECTED_COLOUR) + 50
    assert count(live, WARNING_COLOUR) > 50 and count(plain, WARNING_COLOUR) == 0


def test_a_long_warning_is_wrapped_on_the_annotated_frame(processed):
    """A warning wider than the frame is wrapped onto more rows, not cut off at its right edge."""
    from pose_daemon.draw import WARNING_COLOUR, annotate_live

    cfg = parse_config("", "c.toml")
    frame, result = processed[0]
    image = frame.image[:, :320]  # a narrow frame: 320 px
    long_warning = "output cannot keep up or fails: mavlink 120 dropped in 5 s (link_busy), jsonl 3 (failed)"
    live = annotate_live(image, result, cfg.camera.model(), cfg.marker.model(), warnings=[long_warning])
    orange = np.all(np.abs(live.astype(int) - WARNING_COLOUR) < 40, axis=2)
    rows, cols = np.nonzero(orange)
    assert cols.size > 50
    assert cols.max() < image.shape[1] - 4, "the warning runs off the frame's right edge"
    assert rows.max() - rows.min() > 19, "one row: not wrapped"


def test_a_request_naming_another_host_is_refused(served):
    from pose_daemon.preview.server import host_allowed

    server, feeder = served()
    feeder.feed(2)
    for host, ok in (
        ("127.0.0.1:8080", True),
        ("[::1]:8080", True),
        ("localhost:8080", True),
        ("robot.local:8080", True),
        ("192.168.1.20", True),
        ("evil.example:8080", False),
        ("", False),
        (None, False),
    ):
        assert host_allowed(host, "127.0.0.1") is ok, host
    s = socket.create_connection(("127.0.0.1", server.port), timeout=10)
    s.sendall(b"GET /snapshot.jpg HTTP/1.0\r\nHost: evil.example:8080\r\n\r\n")
    reply = s.makefile("rb").read()
    s.close()
    assert reply.split()[1] == b"403" and b"unexpected Host" in reply


def test_the_annotated_frame_outlines_the_detector_search_regions(processed):
    from pose_daemon.detect.detector import MarkerDetector
    from pose_daemon.draw import SEARCH_COLOUR, annotate_live

    cfg = parse_config('[camera]\nsource = "synthetic"\n', "c.toml")
    camera, marker = cfg.camera.model(), cfg.marker.model()
    detector = MarkerDetector(marker, camera=camera)
    (frame0, result0), (frame1, result1) = processed[0], processed[1]
    detector.detect(frame0.image)
    whole = detector.last_search
    detector.detect(frame1.image)
    tracked = detector.last_search
    assert whole.full == "done" and tracked.stage == "follow"
    ((step, (x0, y0, x1, y1)),) = tracked.regions

    def is_search(pixels):
        return np.all(pixels == SEARCH_COLOUR, axis=-1)

    plain = annotate_live(frame1.image, result1, camera, marker)
    live = annotate_live(frame1.image, result1, camera, marker, search=tracked)
    outline = np.concatenate([live[y0, x0:x1], live[y1 - 1, x0:x1], live[y0:y1, x0], live[y0:y1, x1 - 1]])
    assert is_search(outline).mean() > 0.9  # the corner rings may cross it here and there
    assert not is_search(plain).any()
    inside = live[y0 + 1 : y1 - 1, x0 + 1 : x1 - 1]
    assert is_search(inside).mean() < 0.05  # an outline, not a filled box
    # A whole-frame search is named at the top right; the processing thread's record reaches
    # the preview through the tap.
    full = annotate_live(frame0.image, result0, camera, marker, search=whole)
    w = full.shape[1]

    def near(image):  # anti-aliased text: near the colour
        return int(np.count_nonzero(np.all(np.abs(image.astype(int) - SEARCH_COLOUR) < 40, axis=2)))

    assert near(full[:30, w // 2 :]) > 50 and not is_search(full[30:]).any()
    assert near(annotate_live(frame0.image, result0, camera, marker)[:30, w // 2 :]) == 0
    processor = FrameProcessor.from_config(cfg)
    tap = FrameTap(processor)
    tap(frame0, processor.process(frame0))
    assert tap.latest.search is processor.detector.last_search and tap.latest.search.full == "done"
