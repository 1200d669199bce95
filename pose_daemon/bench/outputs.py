"""``pose-daemon bench outputs``: the time each output takes to put one pose on its link.

Writes direct (``publish`` returns once the bytes are written) to local links: MAVLink over
UDP to 127.0.0.1, ``$POSE`` lines to a pseudo-terminal, JSON lines to a file, and prints
median / p99 / max per output. The daemon's whole capture -> bytes-written latency is
``pose-daemon bench pipeline``; this is the outputs' share of it. Then the MAVLink share of one
pose, its parts timed side by side on the same poses (interleaved, so a loaded machine slows
them alike): the quality and covariance (``PoseMessageInputs.from_pose``), pymavlink's
``odometry_encode`` and ``pack`` (the bytes on the wire), and the two together.
"""

from __future__ import annotations

import os
import socket
import sys
import tempfile
import time
from typing import Any, Dict, List

import numpy as np

from ..camera import Camera, Marker
from ..config import JsonlOutputConfig, MavlinkOutputConfig, SerialOutputConfig
from ..geometry import R_from_euler_rpy, VehicleFrames, VehiclePose, paper_angles_deg_from_R_cam_marker, rvec_from_R
from ..outputs.jsonl import JsonlOutput
from ..outputs.mavlink import MavlinkOutput, PoseMessageInputs, encode_pose_messages
from ..outputs.plain_serial import PlainSerialOutput
from ..pose.types import Pose
from ..result import FrameResult


def _results(frames: VehicleFrames, n: int) -> List[FrameResult]:
    """A vehicle swaying 2 m in front of a wall marker at 30 fps."""
    out = []
    for k in range(n):
        v = VehiclePose(np.array([-2.0, 0.2 * np.sin(k / 20), -0.1]), R_from_euler_rpy(0.0, 0.0, 0.1 * np.sin(k / 30)))
        R, t = frames.camera_pose(v)
        a, b, c = paper_angles_deg_from_R_cam_marker(R)
        pose = Pose(
            rvec=rvec_from_R(R),
            tvec=t,
            R=R,
            alpha_deg=a,
            beta_deg=b,
            gamma_deg=c,
            reprojection_error_px=0.2,
            ambiguity_ratio=0.05,
        )
        out.append(FrameResult(seq=k, t_capture_s=1000.0 + k / 30.0, pose=pose))
    return out


def run_bench(poses: int = 3000) -> Dict[str, Any]:
    """``poses`` poses published through each output in turn: the report for ``print_report``
    (per output its name, the publish times in seconds and the messages sent)."""
    if poses < 1:
        raise ValueError(f"poses must be at least 1, got {poses}")
    frames = VehicleFrames.from_settings("forward", placement="wall")
    results = _results(frames, poses)
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    master, slave = os.openpty()
    os.set_blocking(master, False)
    tmp = tempfile.TemporaryDirectory(prefix="pose-daemon-bench-")
    udp = f"udpout:127.0.0.1:{sink.getsockname()[1]}"
    common: Dict[str, Any] = dict(
        camera=Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5), marker=Marker(width=0.2), queue_size=0
    )
    all_three = ("ODOMETRY", "VISION_POSITION_ESTIMATE", "LANDING_TARGET")
    rows = []
    try:
        outputs = [
            (
                "mavlink ODOMETRY, UDP",
                lambda: MavlinkOutput(MavlinkOutputConfig(connection=udp, wait_heartbeat=False), frames, **common),
            ),
            (
                "mavlink ODOMETRY+VPE+LANDING_TARGET, UDP",
                lambda: MavlinkOutput(
                    MavlinkOutputConfig(connection=udp, wait_heartbeat=False, messages=all_three), frames, **common
                ),
            ),
            (
                "plain $POSE, pty",
                lambda: PlainSerialOutput(SerialOutputConfig(port=os.ttyname(slave)), frames, queue_size=0),
            ),
            (
                "jsonl, file",
                lambda: JsonlOutput(JsonlOutputConfig(path=os.path.join(tmp.name, "poses.jsonl")), queue_size=0),
            ),
        ]
        for name, make in outputs:
            out = make()
            times = np.empty(len(results))
            for i, r in enumerate(results):
                t0 = time.perf_counter()
                out.submit(r)
                times[i] = time.perf_counter() - t0
                _drain(sink, master)
            out.close()
            rows.append({"name": name, "publish_s": times, "sent": out.stats()["sent"]})
    finally:
        sink.close()
        os.close(master)
        os.close(slave)
        tmp.cleanup()
    return {"poses": poses, "platform": sys.platform, "rows": rows, "parts": mavlink_parts(frames, results, common)}


def mavlink_parts(frames: VehicleFrames, results: List[FrameResult], common: Dict[str, Any]) -> Dict[str, np.ndarray]:
    """Per pose, seconds: the quality and covariance (``from_pose``), pymavlink's encode and
    pack of the ODOMETRY it makes, timed one after the other on each pose."""
    from pymavlink.dialects.v20 import common as mavlink2

    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=197)
    fx, width = float(common["camera"].fx), float(common["marker"].width)
    inputs_s, encode_s = np.empty(len(results)), np.empty(len(results))
    for i, r in enumerate(results):
        assert r.pose is not None
        t0 = time.perf_counter()
        inputs = PoseMessageInputs.from_pose(1_000_000 + i, r.pose, frames, fx_px=fx, marker_width_m=width)
        t1 = time.perf_counter()
        for msg in encode_pose_messages(mav, ("ODOMETRY",), inputs):
            msg.pack(mav)
        t2 = time.perf_counter()
        inputs_s[i], encode_s[i] = t1 - t0, t2 - t1
    return {"quality and covariance": inputs_s, "pymavlink encode + pack": encode_s}


def print_report(report: Dict[str, Any]) -> None:
    """One line per output: median, p99 and max publish time."""
    print(f"publish -> bytes written, {report['poses']} poses per output (this machine, {report['platform']}):")
    for row in report["rows"]:
        ms = row["publish_s"] * 1e3
        print(
            f"  {row['name']:42s} median {np.median(ms):.3f} ms, p99 {np.percentile(ms, 99):.3f} ms, "
            f"max {ms.max():.3f} ms ({row['sent']} messages)"
        )
    parts = report.get("parts")
    if parts:
        print("one ODOMETRY pose, its parts side by side:")
        for name, seconds in parts.items():
            ms = seconds * 1e3
            print(f"  {name:42s} median {np.median(ms):.3f} ms, p99 {np.percentile(ms, 99):.3f} ms")


def _drain(sink: socket.socket, master: int) -> None:
    try:
        while True:
            sink.recv(65536, socket.MSG_DONTWAIT)
    except BlockingIOError:
        pass
    try:
        os.read(master, 65536)
    except BlockingIOError:
        pass
