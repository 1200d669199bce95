"""outputs/mavlink/attitude_link.py: the [attitude] source's own MAVLink link, over real UDP to the fake
autopilot (real pymavlink both ways): ATTITUDE asked for at 50 Hz, TIMESYNC both ways, the
attitude at a capture time, the status line's text; and a link that cannot open."""

from __future__ import annotations

import math
import time

import pytest
from fake_autopilot import FakeAutopilot
from mavlink_helpers import of_type, wait_for

from pose_daemon.attitude import AutopilotAttitude, autopilot_attitude_from_config
from pose_daemon.config import parse_config
from pose_daemon.outputs.mavlink import MavlinkAttitudeListener


def test_the_listener_feeds_the_attitude_from_a_px4_over_udp_and_sends_no_poses():
    roll, pitch, yaw = math.radians(-6.0), math.radians(3.0), math.radians(-120.0)
    fc = FakeAutopilot("px4", heartbeat_s=0.2, timesync_s=0.2, vehicle_state=lambda t: ((0, 0, -1), (roll, pitch, yaw)))
    cfg = parse_config(f'[attitude]\nsource = "{fc.connection}"\nmax_age_s = 0.3\n', "a.toml")
    att = autopilot_attitude_from_config(cfg)
    link = MavlinkAttitudeListener.of_config(cfg, att)
    try:
        # PX4 sends TIMESYNC requests too: answered, its offset to our clock is known.
        assert wait_for(lambda: att.samples >= 20 and att.clock.synced and fc.timesync_offset_ns is not None, 15.0), (
            att.samples,
            link.stats(),
        )
        now = time.monotonic()
        a = link.attitude_at(now - 0.03, now)
        status = link.status(now)
    finally:
        link.close()
        fc.close()
    asks = [m for m in of_type(fc.tally.received, "COMMAND_LONG") if m.command == 511]
    assert asks and all(int(m.param1) == 30 and m.param2 == 20_000 for m in asks)  # ATTITUDE at 50 Hz
    assert fc.intervals_us.get(30) == 20_000 and not fc.data_stream_requests
    assert a is not None and a.rpy_rad == pytest.approx((roll, pitch, yaw), abs=1e-4)
    assert a.sigma_rad == pytest.approx(math.radians(cfg.attitude.sigma_deg))
    assert status.startswith("attitude ") and "sync timesync" in status and "link" not in status, status
    sent = {m.get_type() for m in fc.tally.received}
    assert "HEARTBEAT" in sent and not sent & {"ODOMETRY", "VISION_POSITION_ESTIMATE", "LANDING_TARGET"}
    with pytest.raises(RuntimeError, match="sends no poses"):
        link._write(None)  # type: ignore[arg-type]


def test_a_listener_whose_link_cannot_open_says_so_and_gives_no_attitude(tmp_path):
    cfg = parse_config(f'[attitude]\nsource = "{tmp_path / "no-such-tty"}"\n', "a.toml")
    att = AutopilotAttitude()
    link = MavlinkAttitudeListener.of_config(cfg, att)
    try:
        assert wait_for(lambda: "cannot open" in link.status(), 10.0), link.status()
        now = time.monotonic()
        assert link.attitude_at(now, now) is None
        assert link.status(now).startswith("attitude none yet (attitude link down: cannot open")
    finally:
        link.close()
