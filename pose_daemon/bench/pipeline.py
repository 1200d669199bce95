"""``pose-daemon bench pipeline``: end-to-end latency (capture -> bytes written) and memory over a long run.

Runs the daemon's real pipeline (detector, estimator, MAVLink over UDP to 127.0.0.1 and JSON
lines to /dev/null) on rendered 640x480 frames handed out at a fixed rate by a paced source
that stamps each frame when it is handed out, as a camera driver would. The rendered frames
are played forth and back, so the camera moves continuously (and turns round) as in flight.
``preview="idle"`` adds the live preview with nobody watching, ``preview="watch"`` with one
viewer (a separate process reading /stream.mjpg), to measure what the page costs.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import platform
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np

from ..capture.base import Frame
from ..config import Config, parse_config
from ..errors import EndOfStream

# A Raspberry Pi 2 (900 MHz Cortex-A7) runs this Python/OpenCV path about this many times slower
# than an x86-64 desktop core: the figure the "Pi 2 equivalent" column multiplies by.
PI2_FACTOR = 20.0


class PacedSource:
    """Plays pre-rendered images forth and back (0, 1, .., n-1, n-2, .., 1, 0, 1, ..) at ``fps``;
    t_capture_s is the moment a frame is handed out.

    Forth and back, not round and round: a jump from the last image to the first would be
    the camera leaping across the room every ``n`` frames, making the tracker search the
    whole frame again on 2 frames in 48 (+1 to +5 ms each), a loss no steady flight has;
    a turn round costs the tracker's motion prediction as a real one would.
    """

    def __init__(self, images: List[np.ndarray], frames: int, fps: float) -> None:
        self.images = images
        self.frames = frames
        self.period_s = 1.0 / fps
        self.seq = 0
        self._next_s = 0.0

    def open(self) -> None:
        self._next_s = time.monotonic()

    def read(self) -> Frame:
        if self.seq >= self.frames:
            raise EndOfStream()
        delay = self._next_s - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        self._next_s += self.period_s
        seq = self.seq
        self.seq += 1
        return Frame(self.images[self.index(seq)], time.monotonic(), seq)

    def index(self, seq: int) -> int:
        """The image shown as frame ``seq``."""
        n = len(self.images)
        if n == 1:
            return 0
        k = seq % (2 * n - 2)
        return k if k < n else 2 * n - 2 - k

    def close(self) -> None:
        pass


class CpuTimedProcessor:
    """The processor, with the processing thread's CPU time per frame recorded (seconds): the
    work itself, which other programs on a loaded machine do not stretch as they stretch the
    wall-clock stages."""

    def __init__(self, processor: Any, size: int) -> None:
        self.processor = processor
        self.cpu_s = np.zeros(size)
        self.count = 0

    def process(self, frame: Frame):
        t0 = time.thread_time()
        result = self.processor.process(frame)
        if self.count < self.cpu_s.size:
            self.cpu_s[self.count] = time.thread_time() - t0
            self.count += 1
        return result

    def reset(self) -> None:
        self.processor.reset()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.processor, name)


def back_to_back_cpu_s(processor: Any, source: PacedSource, fps: float) -> np.ndarray:
    """The thread CPU time (seconds) of each of the paced run's frames processed again, back to
    back by a fresh ``processor``, stamped as at ``fps``: the work itself, without the pauses
    between frames, after which a core that comes back from idle slow (cold caches, a lower
    clock) doubled the paced run's CPU per frame on the development machine."""
    cpu_s = np.zeros(source.frames)
    for seq in range(source.frames):
        frame = Frame(source.images[source.index(seq)], seq / fps, seq)
        t0 = time.thread_time()
        processor.process(frame)
        cpu_s[seq] = time.thread_time() - t0
    return cpu_s


def rss_bytes() -> int:
    """Resident set size of this process (Linux /proc), bytes."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def render_frames(cfg: Config, n: int, seed: int) -> List[np.ndarray]:
    from ..render import Effects, render_marker, trajectory

    camera, marker = cfg.camera.model(), cfg.marker.model()
    poses = trajectory(cfg.marker.placement, n, fps=10.0, seed=seed, camera=camera, marker=marker)
    rng = np.random.default_rng(seed)
    fx = Effects()
    return [render_marker(camera, marker, p.rvec, p.tvec, effects=fx, rng=rng).image for p in poses]


def with_user_config(bench: Config, user: Config) -> Config:
    """The bench's outputs (UDP to the local sink, JSON lines to /dev/null) around the user's
    camera (size, intrinsics, rate), marker, detector, estimator, mount, gate and pipeline: the
    pipeline the user's config runs, on rendered frames of its marker."""
    if user.map is not None:
        raise ValueError("a [map] config: bench pipeline renders one [marker]; give a config with [marker]")
    # The user's outputs, on local stand-ins: their MAVLink messages over UDP, JSON lines (also
    # for a plain serial output, whose line is as cheap) to /dev/null.
    mav = bench.output.mavlink
    if user.output.mavlink is not None and mav is not None:
        mav = dataclasses.replace(mav, messages=user.output.mavlink.messages)
    outputs = dataclasses.replace(
        bench.output,
        mavlink=mav if user.output.mavlink is not None else None,
        jsonl=bench.output.jsonl if user.output.jsonl is not None or user.output.serial is not None else None,
    )
    if outputs.mavlink is None and outputs.jsonl is None:
        outputs = bench.output
    return dataclasses.replace(
        bench,
        output=outputs,
        camera=dataclasses.replace(user.camera, source="synthetic"),
        marker=user.marker,
        detector=user.detector,
        estimator=user.estimator,
        mount=user.mount,
        gate=user.gate,
        pipeline=user.pipeline,
        name=user.name,
    )


def _bench_config(port: int):
    return parse_config(
        f"""
[camera]
source = "synthetic"
width = 640
height = 480
fx = 500.0
fy = 500.0
cx = 319.5
cy = 239.5
[pipeline]
latency_budget_s = 0.1
output_buffer = 4
[output.mavlink]
connection = "udpout:127.0.0.1:{port}"
wait_heartbeat = false
messages = ["ODOMETRY"]
[output.jsonl]
path = "{os.devnull}"
""",
        "<bench>",
    )


# The viewer of --preview watch: a separate process, so its reading is not the daemon's CPU.
VIEWER = r"""
import signal, sys, urllib.request
frames = size = 0
signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
try:
    with urllib.request.urlopen(sys.argv[1], timeout=30) as r:
        while True:
            chunk = r.read(65536)
            if not chunk:
                break
            size += len(chunk)
            frames += chunk.count(b"--frame")
except Exception:
    pass
finally:
    print(frames, size, flush=True)
"""


def _percentiles_ms(values: np.ndarray) -> str:
    if values.size == 0:
        return "no samples"
    p50, p99 = np.percentile(values, (50, 99)) * 1e3
    return f"median {p50:.2f} ms, p99 {p99:.2f} ms, max {values.max() * 1e3:.2f} ms ({values.size} frames)"


PREVIEW_MODES = ("off", "idle", "watch")


def run_bench(
    frames: int = 3000,
    fps: float = 100.0,
    distinct: int = 48,
    seed: int = 0,
    progress: Callable[[str], None] = print,
    preview: str = "off",
    config: Optional[Config] = None,
) -> Dict[str, Any]:
    """The daemon's pipeline over ``frames`` frames (``distinct`` rendered ones played forth
    and back) handed out at ``fps``: the report for ``print_report``; ``progress`` gets a line
    before the rendering and before the run. ``preview``: one of PREVIEW_MODES. ``config``:
    a user's config whose camera, marker and processing to run (``with_user_config``)."""
    if frames < 1 or fps <= 0 or distinct < 1:
        raise ValueError(f"frames and distinct must be >= 1 and fps > 0 (got {frames}, {distinct}, {fps})")
    if preview not in PREVIEW_MODES:
        raise ValueError(f"preview must be one of {', '.join(PREVIEW_MODES)}, got {preview!r}")
    from ..outputs import open_outputs
    from ..pipeline import Pipeline
    from ..processing.marker import FrameProcessor
    from ..service import GIL_SWITCH_INTERVAL_S

    previous_interval = sys.getswitchinterval()
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)  # as `pose-daemon run` does
    try:
        return _run(frames, fps, distinct, seed, progress, Pipeline, FrameProcessor, open_outputs, preview, config)
    finally:
        sys.setswitchinterval(previous_interval)


def _run(
    n_frames: int,
    fps: float,
    distinct: int,
    seed: int,
    progress: Callable[[str], None],
    Pipeline,
    FrameProcessor,
    open_outputs,
    preview: str,
    user: Optional[Config] = None,
) -> Dict[str, Any]:
    # A ground station stand-in that drains the UDP port.
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    sink.settimeout(0.2)
    port = sink.getsockname()[1]
    received = [0, 0]  # datagrams, bytes
    draining = threading.Event()

    def drain() -> None:
        while not draining.is_set():
            try:
                data = sink.recv(65536)
            except socket.timeout:
                continue
            except OSError:
                return
            received[0] += 1
            received[1] += len(data)

    threading.Thread(target=drain, daemon=True).start()

    cfg = _bench_config(port)
    if user is not None:
        cfg = with_user_config(cfg, user)
    m = cfg.marker
    what = f"{m.type} {m.width:g} m" + (f" {m.dictionary} id {m.id}" if m.type == "aruco" else "")
    progress(
        f"rendering {distinct} distinct {cfg.camera.width}x{cfg.camera.height} frames of the {what} marker "
        f"({m.placement} trajectory, seed {seed}) ..."
    )
    images = render_frames(cfg, distinct, seed)
    source = PacedSource(images, n_frames, fps)
    timed = CpuTimedProcessor(FrameProcessor.from_config(cfg), n_frames)
    processor: Any = timed
    rss_warm: List[Optional[int]] = [None]
    warm_at = min(1000, max(1, n_frames // 10))

    def on_written(name: str, result, t_written_s: float) -> None:
        n = counts[name]
        if n < totals[name].size:
            totals[name][n] = t_written_s - result.t_capture_s
            counts[name] = n + 1
        if rss_warm[0] is None and result.seq >= warm_at:
            rss_warm[0] = rss_bytes()

    tap = server = viewer = None
    data_dir = tempfile.TemporaryDirectory(prefix="bench-preview-")
    if preview != "off":
        from ..config import PreviewConfig
        from ..preview import FrameTap

        cfg = dataclasses.replace(cfg, preview=PreviewConfig(listen="127.0.0.1:0", data_dir=data_dir.name))
        tap = FrameTap(processor)
    # Garbage collection between frames, as `pose-daemon run` does.
    from ..service import IdleCollector

    collector = IdleCollector()
    pipeline = Pipeline.from_config(
        cfg,
        source,
        processor,
        functools.partial(open_outputs, cfg),
        on_written=on_written,
        on_idle=collector.run,
        frame_observer=tap,
    )
    outputs = pipeline.outputs
    totals = {o.name: np.zeros(n_frames) for o in outputs}  # filled by on_written once started
    counts = dict.fromkeys(totals, 0)
    if tap is not None:
        from ..preview import PreviewServer

        server = PreviewServer(cfg, pipeline, tap)
        server.start()
        if preview == "watch":
            viewer = subprocess.Popen(
                [sys.executable, "-c", VIEWER, server.url + "stream.mjpg"], stdout=subprocess.PIPE, text=True
            )
            while server.counts["viewers"] < 1 and viewer.poll() is None:
                time.sleep(0.01)
    rss_start = rss_bytes()
    cpu0 = time.process_time()
    t0 = time.monotonic()
    progress(
        f"running {n_frames} frames at {fps:g} fps through detect -> estimate -> "
        f"{', '.join(o.name for o in outputs)} ..."
    )
    collector.start()
    pipeline.start()
    pipeline.wait()
    elapsed = time.monotonic() - t0
    cpu_s = time.process_time() - cpu0
    status = pipeline.status_line(reset=False)
    pipeline.stop()
    preview_line = None
    if server is not None:
        # Counts once the viewer's stream loop has ended: its last frame is both encoded and sent.
        server.stop(timeout_s=10.0)
        c = dict(server.counts)
        seen = ""
        if viewer is not None:
            viewer.terminate()
            out = viewer.communicate(timeout=10)[0].split()
            seen = f"; the viewer received {out[-2]} frames, {int(out[-1]) / 1e6:.1f} MB" if len(out) >= 2 else ""
        cpu = server.stream_cpu_s
        preview_line = (
            f"preview ({preview}): {c['encoded']} frames annotated and encoded, "
            f"{c['frames_sent']} sent, {c['frames_skipped']} skipped{seen}; viewer thread CPU "
            f"{cpu * 1e3 / max(c['frames_sent'], 1):.2f} ms per frame sent, "
            f"{100 * cpu / max(elapsed, 1e-9):.2f} % of one core"
        )
    data_dir.cleanup()
    for o in outputs:
        o.close()
    time.sleep(0.3)
    draining.set()
    rss_end = rss_bytes()
    sink.close()
    from ..pipeline import STAGES

    stages = {}
    for stage in STAGES:
        values = pipeline.stats.window.values_s(stage)
        if len(values):
            stages[stage] = np.asarray(values, dtype=float)
    if timed.count:
        stages["process CPU"] = timed.cpu_s[: timed.count].copy()
    stages["work"] = back_to_back_cpu_s(FrameProcessor.from_config(cfg), source, fps)
    return {
        "config": cfg.name,
        "size": (cfg.camera.width, cfg.camera.height),
        "fps": fps,
        "stages_s": stages,
        "stats": pipeline.stats.snapshot(),
        "elapsed_s": elapsed,
        "status_line": status,
        "received_datagrams": received[0],
        "received_bytes": received[1],
        "latency_s": {name: values[: counts[name]] for name, values in totals.items()},
        "rss_start_bytes": rss_start,
        "rss_warm_bytes": rss_warm[0] or rss_start,
        "rss_end_bytes": rss_end,
        "warm_at": warm_at,
        "cpu_s": cpu_s,
        "preview_line": preview_line,
    }


def print_report(report: Dict[str, Any]) -> None:
    """The report of ``run_bench``: frames and drops, latency per output, the Pi 2 equivalent,
    stages and memory."""
    snap = report["stats"]
    print(
        f"frames: {snap['captured']} captured, {snap['processed']} processed, "
        f"{snap['detected']} with a pose, in {report['elapsed_s']:.1f} s; drops: "
        + (", ".join(f"{k} {v}" for k, v in sorted(snap["drops"].items())) or "none")
    )
    cpu_s, elapsed = report["cpu_s"], report["elapsed_s"]
    print(
        f"CPU: {cpu_s * 1e3 / max(snap['processed'], 1):.2f} ms per processed frame "
        f"({100 * cpu_s / max(elapsed, 1e-9):.1f} % of one core over the run, all threads)"
    )
    if report["preview_line"]:
        print(report["preview_line"])
    print(f"UDP ground station received {report['received_datagrams']} datagrams, {report['received_bytes']} bytes")
    print("end-to-end latency, capture -> bytes written (this machine):")
    worst = None
    for name, v in report["latency_s"].items():
        print(f"  {name:8s} {_percentiles_ms(v)}")
        if v.size:
            p50, p99 = np.percentile(v, (50, 99))
            worst = (max(p50, worst[0]), max(p99, worst[1])) if worst else (p50, p99)
    name, on_pi = machine()
    if worst and not on_pi:
        print(
            f"Pi 2 equivalent (x{PI2_FACTOR:g}): median {worst[0] * PI2_FACTOR * 1e3:.1f} ms, "
            f"p99 {worst[1] * PI2_FACTOR * 1e3:.1f} ms (goal: median < 50 ms, p99 < 100 ms; "
            f"here median <= 2.5 ms, p99 <= 5 ms: "
            f"{'met' if worst[0] <= 0.0025 and worst[1] <= 0.005 else 'NOT met'})"
        )
    for line in stage_lines(report, name, on_pi):
        print(line)
    mib = 1024 * 1024
    warm, warm_at = report["rss_warm_bytes"], report["warm_at"]
    growth = (report["rss_end_bytes"] - warm) / mib
    print(
        f"resident memory: {report['rss_start_bytes'] / mib:.1f} MiB at start, {warm / mib:.1f} MiB after "
        f"{warm_at} frames, {report['rss_end_bytes'] / mib:.1f} MiB at the end: growth {growth:+.2f} MiB over "
        f"{snap['captured'] - warm_at} frames (goal < 5 MB)"
    )


def machine() -> Tuple[str, bool]:
    """This machine's name and whether it is a Raspberry Pi (its device tree says so)."""
    try:
        model = Path("/proc/device-tree/model").read_text(errors="replace").strip("\x00\n ")
    except OSError:
        model = ""
    if model.startswith("Raspberry Pi"):
        return model, True
    return f"{platform.machine() or 'unknown'}, {os.cpu_count() or '?'} cores", False


def software() -> str:
    """The versions that set the per-call costs: Python, numpy, OpenCV."""
    import cv2

    python = f"Python {platform.python_version()} ({platform.machine()})"
    return f"{python}, numpy {np.__version__}, OpenCV {cv2.__version__}"


def stage_lines(report: Dict[str, Any], name: str, on_pi: bool) -> List[str]:
    """Each stage's median, p99 and max on this machine (and, off a Pi, the Pi 2 estimate):
    the figures a Pi user sends back to replace the estimate."""
    w, h = report["size"]
    stages = report["stages_s"]
    head = f"per stage on this machine ({name}), {w}x{h} at {report['fps']:g} fps, ms (n: samples, the last ones):"
    extra = "" if on_pi else f"   Pi 2 estimate (x{PI2_FACTOR:g}): median    p99"
    lines = [head, f"  {'stage':11s} {'median':>7s} {'p99':>7s} {'max':>7s} {'n':>6s}{extra}"]
    for stage, v in stages.items():
        p50, p99 = np.percentile(v, (50, 99)) * 1e3
        row = f"  {stage:11s} {p50:7.2f} {p99:7.2f} {v.max() * 1e3:7.2f} {v.size:6d}"
        if not on_pi:
            row += f"   {' ' * 21}{p50 * PI2_FACTOR:7.1f} {p99 * PI2_FACTOR:6.1f}"
        lines.append(row)
    if "process CPU" in stages:
        lines.append(
            "  (process CPU: the processing thread's CPU time per frame, detect + estimate + hand-over; "
            "the wall-clock rows add waiting for the CPU)"
        )
    if "work" in stages:
        lines.append(
            "  (work: the same frames processed again back to back, without the pauses between them: "
            "what the frames cost with the core awake; process CPU adds what its waking costs)"
        )
    lines.append(f"  software: {software()}")
    if on_pi:
        lines.append(
            f"measured on {name}: this Pi's own figures, not an estimate. Please send this whole output "
            "with the command you ran in an issue titled 'bench pipeline on <your Pi model>': they replace "
            "the x20 estimate (docs/performance.md#on-your-pi)"
        )
    return lines
