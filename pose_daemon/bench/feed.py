"""``pose-daemon bench feed``: the flight feed under CPU load, and who made each late pose late.

One core (``core``) holds everything: ``busy`` busy loops at nice 0, a reader process at nice
0 (the autopilot's side: it receives the UDP datagrams on 127.0.0.1 and stamps each one on
CLOCK_MONOTONIC, the clock of ``t_capture_s``), and this process at nice ``nice`` standing for
the daemon: a frame thread that stamps a capture time, works ``work_ms`` of CPU (the detection
and pose a frame costs) and hands the result over, and the MAVLink output's own thread (a
queued ``MavlinkOutput`` with the budget, as the daemon runs it). Per pose sent, four times:
capture, the output's last budget check, the datagram queued in the reader's socket (the
kernel's SO_TIMESTAMPNS), and the reader's receive. A pose that reached the reader after the
budget is split into its parts: the daemon's before the check (frame work, the hand-over, the
queue), the daemon's between the check and its send (what the check cannot see: a preemption
right before the system call), the kernel's delivery after the send (loopback's softirq, which
ksoftirqd at nice 0 may run late on a busy core) and the reader's (the datagram waited for the
reader to be scheduled).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from ..camera import Camera, Marker
from ..config import MavlinkOutputConfig
from ..geometry import R_from_euler_rpy, VehicleFrames, VehiclePose, paper_angles_deg_from_R_cam_marker, rvec_from_R
from ..outputs.mavlink import MavlinkOutput
from ..pose.types import Pose
from ..result import FrameResult

# The reader: receives until the datagram b"end" (from the bench); prints "t_recv t_queued hex"
# lines: when it got each datagram and when the kernel queued it (SO_TIMESTAMPNS, taken on
# CLOCK_REALTIME and moved to CLOCK_MONOTONIC by their offset read here).
_READER = r"""
import socket, struct, sys, time
s = socket.socket(fileno=int(sys.argv[1]))
SO_TIMESTAMPNS = 35  # Linux (asm-generic/socket.h); Python's socket module lacks the name
s.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
offsets = []
for _ in range(5):
    a = time.monotonic(); r = time.time(); b = time.monotonic()
    offsets.append((b - a, r - (a + b) / 2))
offset = min(offsets)[1]
out = []
while True:
    data, anc, _, _ = s.recvmsg(65536, 64)
    t_recv = time.monotonic()
    if data == b"end":
        break
    t_queued = t_recv
    for level, kind, raw in anc:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
            sec, nsec = struct.unpack("@ll", raw[: struct.calcsize("@ll")])  # struct timespec
            t_queued = sec + nsec * 1e-9 - offset
    out.append((t_recv, t_queued, data))
sys.stdout.write("".join(f"{t!r} {q!r} {d.hex()}\n" for t, q, d in out))
"""


class _TimedMavlink(MavlinkOutput):
    """The MAVLink output, noting (t_capture_s, t_last_check, t_sent) of each pose message."""

    timeline: List[Tuple[float, float, float]]

    def _after_send(self, nbytes: int) -> None:
        t_check, item = self._t_send_check, self._current
        super()._after_send(nbytes)
        if item is not None:
            self.timeline.append((float(item.t_capture_s), t_check, self._clock()))


def _pose(frames: VehicleFrames, k: int) -> Pose:
    v = VehiclePose(np.array([-2.0, 0.2 * np.sin(k / 20), -0.1]), R_from_euler_rpy(0.0, 0.0, 0.1 * np.sin(k / 30)))
    R, t = frames.camera_pose(v)
    a, b, c = paper_angles_deg_from_R_cam_marker(R)
    return Pose(rvec=rvec_from_R(R), tvec=t, R=R, alpha_deg=a, beta_deg=b, gamma_deg=c, reprojection_error_px=0.2)


def _spin(seconds: float) -> None:
    end = time.thread_time() + seconds  # CPU time: on a shared core the work takes longer
    x = 0
    while time.thread_time() < end:
        x += 1


def _at_nice_0() -> None:
    os.setpriority(os.PRIO_PROCESS, 0, 0)


def run_bench(
    poses: int = 2000,
    fps: float = 30.0,
    work_ms: float = 15.0,
    busy: int = 2,
    core: int = 0,
    nice: int = 0,
    budget_s: float = 0.1,
) -> Dict[str, Any]:
    """``poses`` frames at ``fps``: the report for ``print_report``. ``nice`` is this process's
    (the daemon's) nice value; lowering it below 0 needs root, as systemd's ``Nice=`` has."""
    cores, nice_was = os.sched_getaffinity(0), os.getpriority(os.PRIO_PROCESS, 0)
    # Both apply to this thread (Linux) and to every thread and process it starts after.
    os.sched_setaffinity(0, {core})
    os.setpriority(os.PRIO_PROCESS, 0, nice)
    try:
        return _run(poses, fps, work_ms, busy, core, nice, budget_s)
    finally:
        os.setpriority(os.PRIO_PROCESS, 0, max(nice_was, nice) if os.geteuid() else nice_was)
        os.sched_setaffinity(0, cores)


def _run(poses: int, fps: float, work_ms: float, busy: int, core: int, nice: int, budget_s: float) -> Dict[str, Any]:
    frames = VehicleFrames.from_settings("forward", placement="wall")
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    sink.bind(("127.0.0.1", 0))
    loops = [subprocess.Popen([sys.executable, "-c", "while True: pass"], preexec_fn=_at_nice_0) for _ in range(busy)]
    reader = subprocess.Popen(
        [sys.executable, "-c", _READER, str(sink.fileno())],
        pass_fds=(sink.fileno(),),
        stdout=subprocess.PIPE,
        text=True,
        preexec_fn=_at_nice_0,
    )
    out = _TimedMavlink(
        MavlinkOutputConfig(connection=f"udpout:127.0.0.1:{sink.getsockname()[1]}", wait_heartbeat=False),
        frames,
        camera=Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5),
        marker=Marker(width=0.2),
        max_age_s=budget_s,
        start=False,
    )
    out.timeline = []
    out.start()
    pose = [_pose(frames, k) for k in range(64)]
    try:
        t_next = time.monotonic()
        for k in range(poses):
            t_next += 1.0 / fps
            t_capture = time.monotonic()
            _spin(work_ms / 1e3)
            out.submit(FrameResult(seq=k, t_capture_s=t_capture, pose=pose[k % len(pose)]))
            time.sleep(max(0.0, t_next - time.monotonic()))
        time.sleep(0.3)
        out.close()
        sink.sendto(b"end", sink.getsockname())
        received, _ = reader.communicate(timeout=60)
    finally:
        for p in loops:
            p.kill()
            p.wait()
        if reader.poll() is None:
            reader.kill()
            reader.wait()
        sink.close()
    return {
        "poses": poses,
        "fps": fps,
        "work_ms": work_ms,
        "busy": busy,
        "core": core,
        "nice": nice,
        "budget_s": budget_s,
        "timeline": out.timeline,
        "received": _arrivals(received),
        "stats": out.stats(),
    }


def _arrivals(text: str) -> Dict[int, Tuple[float, float]]:
    """time_usec of each ODOMETRY -> (when the kernel queued it for the reader, when the reader got it)."""
    from pymavlink.dialects.v20 import common as mavlink2

    mav = mavlink2.MAVLink(None)
    out: Dict[int, Tuple[float, float]] = {}
    for line in text.splitlines():
        t, q, hexdata = line.split()
        for m in mav.parse_buffer(bytes.fromhex(hexdata)) or []:
            if m.get_type() == "ODOMETRY":
                out[int(m.time_usec)] = (float(q), float(t))
    return out


def parts(report: Dict[str, Any]) -> Optional[Dict[str, np.ndarray]]:
    """Per pose received, seconds: capture -> check (the daemon before its last check), check
    -> sent (the daemon from that check until its send returned, or until the datagram was in
    the reader's socket if that came first), sent -> queued (the kernel's delivery after the
    send returned: loopback's softirq), queued -> received (the reader's scheduling), total."""
    from ..result import time_usec_from_s

    rows = []
    for t_capture, t_check, t_sent in report["timeline"]:
        got = report["received"].get(time_usec_from_s(t_capture))
        if got is not None:
            t_queued, t_recv = got
            t_queued = min(max(t_queued, t_check), t_recv)  # the two clocks' offset is read to ~us
            t_out = min(t_sent, t_queued)
            rows.append((t_check - t_capture, t_out - t_check, t_queued - t_out, t_recv - t_queued, t_recv - t_capture))
    if not rows:
        return None
    a = np.array(rows)
    names = ("capture -> check", "check -> sent", "sent -> queued", "queued -> received", "total")
    return {name: a[:, i] for i, name in enumerate(names)}


def print_report(report: Dict[str, Any]) -> None:
    """Medians, p99 and max of each part; the late poses and whose time made them late."""
    r = report
    print(
        f"{r['poses']} frames at {r['fps']:g} fps, {r['work_ms']:g} ms of CPU each, on core {r['core']} with "
        f"{r['busy']} busy loops and the reader at nice 0, the daemon at nice {r['nice']}; budget "
        f"{r['budget_s'] * 1e3:g} ms"
    )
    p = parts(r)
    s = r["stats"]
    print(f"  sent {s['sent']}, dropped {s['dropped'] or 'none'}, received {len(r['received'])}")
    if p is None:
        print("  nothing received")
        return
    for name, seconds in p.items():
        ms = seconds * 1e3
        print(
            f"  {name:18s} median {np.median(ms):7.3f} ms, p99 {np.percentile(ms, 99):7.3f} ms, max {ms.max():7.3f} ms"
        )
    late = p["total"] > r["budget_s"]
    n = int(late.sum())
    print(f"  late at the reader (> budget): {n} of {len(late)}")
    if n:
        for name in ("capture -> check", "check -> sent", "sent -> queued", "queued -> received"):
            share = p[name][late].sum() / p["total"][late].sum()
            print(f"    of their time, {name:18s} {share * 100:5.1f} % (max {p[name][late].max() * 1e3:.1f} ms)")
