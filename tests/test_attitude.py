"""attitude.py: TIMESYNC clock mapping under jitter and a reboot, interpolation at capture
time, staleness. Time is simulated: every clock here is a number the test sets."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pose_daemon.attitude import Attitude, AttitudeHistory, AutopilotAttitude, ClockMapper, slerp
from pose_daemon.geometry import R_from_euler_rpy, quaternion_from_R_3x3, rotation_angle_deg_3x3

OFFSET_S = 1234.5678  # our clock - the autopilot's boot clock


def _exchange(mapper: ClockMapper, t_send_s: float, up_s: float, down_s: float, offset_s: float = OFFSET_S) -> bool:
    """One TIMESYNC request sent at t_send_s (ours), up_s to reach the autopilot, down_s back."""
    ts1 = mapper.request(int(round(t_send_s * 1e9)))
    tc1 = int(round((t_send_s + up_s - offset_s) * 1e9))
    return mapper.on_reply(tc1, ts1, int(round((t_send_s + up_s + down_s) * 1e9)))


def test_offset_under_asymmetric_jitter_is_within_the_shortest_round_trip():
    rng = np.random.default_rng(1)
    mapper = ClockMapper()
    assert mapper.offset_s is None
    for k in range(40):
        # A busy link: delays of 1-20 ms each way, drawn independently (asymmetric).
        up, down = rng.uniform(0.001, 0.020, 2)
        _exchange(mapper, 2000.0 + k, up, down)
    err = abs(mapper.offset_s - OFFSET_S)
    assert err <= mapper.rtt_s / 2 + 1e-9
    assert mapper.rtt_s < 0.015
    assert err < 0.006


def test_slow_replies_and_foreign_replies_are_not_used():
    mapper = ClockMapper(max_rtt_s=0.01)
    assert not _exchange(mapper, 2010.0, 0.03, 0.03)  # round trip 60 ms > 10 ms
    assert mapper.rejected_rtt == 1 and mapper.offset_s is None
    # A reply to a request someone else sent: its ts1 is not one of ours.
    assert not mapper.on_reply(5_000_000_000, 42, 11_000_000_000)
    assert _exchange(mapper, 2012.0, 0.001, 0.001)
    assert mapper.offset_s == pytest.approx(OFFSET_S, abs=1e-6)


def test_a_time_jump_resyncs_after_a_few_exchanges_and_one_stray_does_not():
    mapper = ClockMapper(jump_count=3)
    for k in range(5):
        _exchange(mapper, 2100.0 + k, 0.002, 0.002)
    # One reply far off (a stray): ignored.
    _exchange(mapper, 2106.0, 0.002, 0.002, offset_s=OFFSET_S + 50.0)
    assert mapper.offset_s == pytest.approx(OFFSET_S, abs=1e-3)
    _exchange(mapper, 2107.0, 0.002, 0.002)
    # The autopilot rebooted without us seeing its ATTITUDE stream: its clock restarted.
    new_offset = 107.5
    for k in range(3):
        _exchange(mapper, 2108.0 + k, 0.002, 0.002, offset_s=new_offset)
    assert mapper.offset_s == pytest.approx(new_offset, abs=1e-3)
    assert mapper.resets == 1


def test_reboot_seen_in_the_attitude_stream_clears_history_and_clock():
    att = AutopilotAttitude()
    for k in range(3):
        _exchange(att.clock, 5000.0 + k, 0.001, 0.001)
    for k in range(100):  # 50 Hz
        att.on_attitude(600_000 + 20 * k, 0.1, 0.0, 0.0, OFFSET_S + 600.0 + 0.02 * k + 0.001)
    t_cap = OFFSET_S + 600.0 + 1.0
    assert att.attitude_at(t_cap, t_now_s=t_cap + 0.01) is not None
    # Reboot: time_boot_ms starts again near 0; until TIMESYNC answers again only arrival times map it.
    t_arr = OFFSET_S + 602.0
    att.on_attitude(1500, -0.2, 0.0, 0.0, t_arr)
    assert att.reboots == 1 and len(att.history) == 1 and not att.clock.synced
    att.on_attitude(1520, -0.2, 0.0, 0.0, t_arr + 0.02)
    got = att.attitude_at(t_arr + 0.01, t_now_s=t_arr + 0.03)
    assert got is not None and got.rpy_rad[0] == pytest.approx(-0.2, abs=1e-9)
    assert att.freshness(t_arr + 0.03)["sync"] == "arrival"


def test_interpolation_at_capture_time_is_the_slerp_of_the_neighbours():
    att = AutopilotAttitude(max_extrapolation_s=0.05)
    for k in range(3):
        _exchange(att.clock, 2000.0 + k, 0.0005, 0.0005)
    # A steady roll rate of 1 rad/s sampled at 50 Hz, delivered 2 ms late.
    for k in range(50):
        t_boot = 10.0 + 0.02 * k
        att.on_attitude(int(round(t_boot * 1e3)), 1.0 * (t_boot - 10.0), 0.05, 2.0, t_boot + OFFSET_S + 0.002)
    t_boot_query = 10.317  # between two samples
    got = att.attitude_at(t_boot_query + OFFSET_S, t_now_s=10.99 + OFFSET_S)
    assert got is not None
    want = R_from_euler_rpy(t_boot_query - 10.0, 0.05, 2.0)
    assert rotation_angle_deg_3x3(got.R_local_body, want) < 0.01
    # Extrapolation past the newest sample: allowed up to the bound, at the last rate.
    t_last = 10.0 + 0.02 * 49
    near = att.attitude_at(t_last + 0.03 + OFFSET_S, t_now_s=t_last + 0.04 + OFFSET_S)
    assert near is not None and near.rpy_rad[0] == pytest.approx(t_last + 0.03 - 10.0, abs=1e-6)
    assert att.attitude_at(t_last + 0.06 + OFFSET_S, t_now_s=t_last + 0.07 + OFFSET_S) is None
    # Before the history: not guessed.
    assert att.attitude_at(9.9 + OFFSET_S, t_now_s=t_last + OFFSET_S) is None


def test_stale_stream_and_holes_give_no_attitude():
    att = AutopilotAttitude(max_age_s=0.3, max_gap_s=0.1)
    for k in range(3):
        _exchange(att.clock, 2000.0 + k, 0.0005, 0.0005)
    for k in range(10):
        att.on_attitude(1000 + 20 * k, 0.0, 0.0, 0.0, 1.0 + 0.02 * k + OFFSET_S)
    att.on_attitude(1500, 0.0, 0.0, 0.0, 1.5 + OFFSET_S)  # 320 ms hole before it
    t_last_arrival = 1.5 + OFFSET_S
    assert att.attitude_at(1.3 + OFFSET_S, t_now_s=t_last_arrival + 0.01) is None  # in the hole
    assert att.attitude_at(1.1 + OFFSET_S, t_now_s=t_last_arrival + 0.01) is not None
    # The link went quiet: nothing for more than max_age_s, so nothing is trusted.
    assert att.attitude_at(1.5 + OFFSET_S, t_now_s=t_last_arrival + 0.31) is None
    f = att.freshness(t_last_arrival + 0.31)
    assert f["age_s"] == pytest.approx(0.31) and f["missing"] == 2 and f["used"] == 1
    assert "attitude" in att.status(t_last_arrival + 0.31)
    assert not att.on_attitude(1520, math.nan, 0.0, 0.0, t_last_arrival)


def test_history_keeps_order_and_slerp_takes_the_short_way():
    h = AttitudeHistory(capacity=4)
    q = [quaternion_from_R_3x3(R_from_euler_rpy(0.0, 0.0, a)) for a in (0.0, 0.1, 0.2, 0.3, 0.4)]
    for t, qq in zip((0.0, 0.02, 0.06, 0.04, 0.08), (q[0], q[1], q[3], q[2], q[4])):
        h.add(t, qq)
    assert len(h) == 4 and h.newest_t_s == 0.08
    assert h.at(0.0) is None  # dropped (capacity)
    np.testing.assert_allclose(h.at(0.05), slerp(q[2], q[3], 0.5), atol=1e-12)
    # q and -q are the same rotation: interpolation never swings the long way round.
    mid = slerp(q[1], -q[2], 0.5)
    assert rotation_angle_deg_3x3(Attitude.from_quaternion(mid).R_local_body, R_from_euler_rpy(0.0, 0.0, 0.15)) < 1e-6


def test_attitude_refuses_non_finite_angles():
    with pytest.raises(ValueError, match="finite"):
        Attitude((0.0, math.inf, 0.0))
    with pytest.raises(ValueError, match="sigma"):
        Attitude((0.0, 0.0, 0.0), sigma_rad=-1.0)


def test_attitude_source_from_config():
    from pose_daemon.attitude import attitude_connection, autopilot_attitude_from_config
    from pose_daemon.config import ConfigError, parse_config

    with_link = parse_config('[output.mavlink]\nconnection = "udpin:0.0.0.0:14550"\n')
    assert attitude_connection(with_link) == "udpin:0.0.0.0:14550"
    assert attitude_connection(parse_config("")) is None  # "mavlink" without a MAVLink output
    assert (
        attitude_connection(
            parse_config('[attitude]\nsource = "none"\n[output.mavlink]\nconnection = "udpin:0.0.0.0:1"\n')
        )
        is None
    )
    # A connection of its own, listened on for the attitude (outputs/mavlink/attitude_link.py).
    own = parse_config('[attitude]\nsource = "/dev/ttyACM0"\nbaud = 57600\n')
    assert attitude_connection(own) == "/dev/ttyACM0" and own.attitude.baud == 57600
    assert attitude_connection(parse_config('[attitude]\nsource = "udpin:0.0.0.0:14551"\n')) == "udpin:0.0.0.0:14551"
    with pytest.raises(
        ConfigError, match=r"^x.toml: \[attitude\] source: expected .*udpin:HOST:PORT .*, got \"udpin:0.0.0.0\"$"
    ):
        parse_config('[attitude]\nsource = "udpin:0.0.0.0"\n', "x.toml")
    with pytest.raises(ConfigError, match=r"\[attitude\] source: expected \"mavlink\" for the \[output.mavlink\] link"):
        parse_config(
            '[attitude]\nsource = "udpin:0.0.0.0:14550"\n[output.mavlink]\nconnection = "udpin:0.0.0.0:14550"\n'
        )
    with pytest.raises(ConfigError, match=r"\[attitude\] baud: expected"):
        parse_config('[attitude]\nsource = "/dev/ttyACM0"\nbaud = 12\n')
    with pytest.raises(ConfigError, match=r"\[attitude\] source: expected \"mavlink\", \"none\" or a pymavlink"):
        parse_config('[attitude]\nsource = "autopilot"\n')
    att = autopilot_attitude_from_config(parse_config("[attitude]\nmax_age_s = 0.2\nsigma_deg = 2.0\n"))
    assert att.max_age_s == 0.2 and att.sigma_rad == pytest.approx(math.radians(2.0))
