"""Time each output takes to put one pose on its link: ``python -m pose_daemon.outputs.bench``.

Writes direct (``publish`` returns once the bytes are written) to local links: MAVLink over
UDP to 127.0.0.1, ``$POSE`` lines to a pseudo-terminal, JSON lines to a file, and prints
median / p99 / max per output. The daemon's whole capture -> bytes-written latency is
``pose-daemon bench pipeline``; this is the outputs' share of it.
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
import tempfile
import time
from typing import List, Optional, Sequence

import numpy as np

from ..camera import Camera, Marker
from ..config import JsonlOutputConfig, MavlinkOutputConfig, SerialOutputConfig
from ..geometry import (
    R_from_euler_rpy,
    VehicleFrames,
    VehiclePose,
    paper_angles_deg_from_R_cam_marker,
    rvec_from_R,
)
from ..pose.types import Pose
from ..result import FrameResult
from .jsonl import JsonlOutput
from .mavlink import MavlinkOutput
from .plain_serial import PlainSerialOutput


def _results(frames: VehicleFrames, n: int) -> List[FrameResult]:
    """A vehicle swaying 2 m in front of a wall marker at 30 fps."""
    out = []
    for k in range(n):
        v = VehiclePose(np.array([-2.0, 0.2 * np.sin(k / 20), -0.1]), R_from_euler_rpy(0.0, 0.0, 0.1 * np.sin(k / 30)))
        R, t = frames.camera_pose(v)
        a, b, c = paper_angles_deg_from_R_cam_marker(R)
        pose = Pose(rvec=rvec_from_R(R), tvec=t, R=R, alpha_deg=a, beta_deg=b, gamma_deg=c,
                    reprojection_error_px=0.2, ambiguity_ratio=0.05)
        out.append(FrameResult(seq=k, t_capture_s=1000.0 + k / 30.0, pose=pose))
    return out


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pose_daemon.outputs.bench", description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=3000, help="poses per output (default 3000)")
    args = parser.parse_args(argv)
    if args.poses < 1:
        parser.error("--poses must be at least 1")
    frames = VehicleFrames.from_settings("forward", placement="wall")
    results = _results(frames, args.poses)
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    master, slave = os.openpty()
    os.set_blocking(master, False)
    tmp = tempfile.TemporaryDirectory(prefix="pose-daemon-bench-")
    udp = f"udpout:127.0.0.1:{sink.getsockname()[1]}"
    common = dict(camera=Camera(fx=500.0, fy=500.0, cx=319.5, cy=239.5), marker=Marker(width=0.2), queue_size=0)
    all_three = ("ODOMETRY", "VISION_POSITION_ESTIMATE", "LANDING_TARGET")
    outputs = [
        ("mavlink ODOMETRY, UDP",
         MavlinkOutput(MavlinkOutputConfig(connection=udp, wait_heartbeat=False), frames, **common)),
        ("mavlink ODOMETRY+VPE+LANDING_TARGET, UDP",
         MavlinkOutput(MavlinkOutputConfig(connection=udp, wait_heartbeat=False, messages=all_three), frames,
                       **common)),
        ("plain $POSE, pty", PlainSerialOutput(SerialOutputConfig(port=os.ttyname(slave)), frames, queue_size=0)),
        ("jsonl, file", JsonlOutput(JsonlOutputConfig(path=os.path.join(tmp.name, "poses.jsonl")), queue_size=0)),
    ]
    print(f"publish -> bytes written, {args.poses} poses per output (this machine, {sys.platform}):")
    try:
        for name, out in outputs:
            times = np.empty(len(results))
            for i, r in enumerate(results):
                t0 = time.perf_counter()
                out.submit(r)
                times[i] = time.perf_counter() - t0
                _drain(sink, master)
            out.close()
            ms = times * 1e3
            print(f"  {name:42s} median {np.median(ms):.3f} ms, p99 {np.percentile(ms, 99):.3f} ms, "
                  f"max {ms.max():.3f} ms ({out.stats()['sent']} messages)")
    finally:
        sink.close()
        os.close(master)
        os.close(slave)
        tmp.cleanup()
    return 0


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


if __name__ == "__main__":
    sys.exit(main())
