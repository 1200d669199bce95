"""The links under the outputs, on real files, sockets and pseudo-terminals: nothing stale waits
in a kernel buffer, the last age check is right before the bytes, junk does not starve the
stream, signing authenticates what comes back, one port has one daemon, and a full disk never
leaves a broken JSON line."""

from __future__ import annotations

import json
import os
import subprocess

import pytest
from mavlink_helpers import lost_result, vehicle_result, wait_for

from pose_daemon import geometry as g
from pose_daemon.config import JsonlOutputConfig
from pose_daemon.outputs import JsonlOutput

WALL = g.VehicleFrames.from_settings("forward", placement="wall")


@pytest.fixture
def small_tmpfs(tmp_path):
    """A real 64 KiB tmpfs (root only): a disk that fills up."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        if os.environ.get("CI"):
            pytest.fail(f"cannot mount a tmpfs in CI: {proc.stderr.strip()}")
        pytest.skip(f"mounting a tmpfs is not permitted here (root needed): {proc.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def _fill(path, leave_bytes: int) -> None:
    """Fill the filesystem of ``path`` (a file to create) until about ``leave_bytes`` are free."""
    st = os.statvfs(os.path.dirname(path))
    free = st.f_bavail * st.f_frsize
    with open(path, "wb") as f:
        f.write(b"\0" * max(0, free - leave_bytes))


def test_jsonl_on_a_full_disk_never_leaves_a_broken_line(small_tmpfs):
    path = small_tmpfs / "poses.jsonl"
    filler = small_tmpfs / "filler"
    _fill(str(filler), 4096)   # one page left: the lines fill it, one is cut at the edge
    out = JsonlOutput(JsonlOutputConfig(path=str(path)), queue_size=0, retry_s=0.0, retry_max_s=0.0)
    try:
        k = 0
        while out.stats()["errors"] + out.stats()["link_failures"] == 0 and k < 200:
            out.submit(vehicle_result(WALL, k, 10.0 + k / 30, (-2.0, 0.01 * k, 0.0)))
            k += 1
        assert k < 200, "the disk never filled"
        for j in range(3):                        # more lines while it is full
            out.submit(lost_result(k + j, 20.0 + j))
        filler.unlink()                           # space again
        assert wait_for(lambda: out.link_up, 5.0), out.status()
        for j in range(5):
            out.submit(vehicle_result(WALL, 1000 + j, 30.0 + j / 30, (-2.0, 0.0, 0.0)))
    finally:
        out.close()
    text = path.read_text()
    assert text.endswith("\n")
    frames = [json.loads(line)["frame"] for line in text.splitlines()]   # every line is a whole object
    assert frames[-5:] == [1000, 1001, 1002, 1003, 1004]
    assert frames == sorted(frames) and len(frames) >= 6
    assert out.stats()["dropped"].get("link_down", 0) >= 1


def _signed_heartbeat(key, system: int = 1) -> bytes:
    """An ArduPilot copter's HEARTBEAT signed with ``key`` (MAVLink 2 signing, a fresh time stamp)."""
    import time

    from pymavlink.dialects.v20 import common as mavlink2

    ap = mavlink2.MAVLink(None, srcSystem=system, srcComponent=1)
    ap.signing.secret_key, ap.signing.sign_outgoing, ap.signing.link_id = key, True, 0
    ap.signing.timestamp = int((time.time() - 1420070400) * 1e5)
    return ap.heartbeat_encode(2, 3, 0, 0, 4).pack(ap)


def test_with_a_signing_key_only_correctly_signed_messages_are_believed():
    import hashlib

    from mavlink_helpers import UdpPeer, autopilot_heartbeat, mavlink_output, of_type

    key = hashlib.sha256(b"correct horse battery staple").digest()
    peer = UdpPeer(signing_key=key)
    out = mavlink_output(f"udpout:127.0.0.1:{peer.port}", WALL, wait_heartbeat=True, queue_size=0,
                         signing_key="correct horse battery staple", origin=(47.397742, 8.545594, 488.0))
    t = [50.0]

    def poses(n):
        for _ in range(n):
            t[0] += 1 / 30
            out.submit(vehicle_result(WALL, 0, t[0], (-2.0, 0.0, 0.0)))

    try:
        assert peer.collect(2.0, until=lambda ms: bool(of_type(ms, "HEARTBEAT")))
        peer.send(autopilot_heartbeat(system=1))                                # unsigned
        peer.send(_signed_heartbeat(hashlib.sha256(b"wrong").digest(), system=1))  # another key
        assert wait_for(lambda: out.stats()["ignored"].get("bad_signature", 0) >= 2, 3.0), out.status()
        poses(5)
        msgs = peer.collect(0.3)
        assert out.autopilot_system is None
        assert not of_type(msgs, "ODOMETRY") and not of_type(msgs, "SET_GPS_GLOBAL_ORIGIN")
        assert "ignored bad_signature=2" in out.status()
        peer.send(_signed_heartbeat(key, system=1))                             # the autopilot
        assert wait_for(lambda: out.autopilot_system == 1, 3.0), out.status()
        poses(3)
        msgs = peer.collect(2.0, until=lambda ms: len(of_type(ms, "ODOMETRY")) >= 3)
    finally:
        out.close()
        peer.close()
    assert len(of_type(msgs, "ODOMETRY")) == 3 and len(of_type(msgs, "SET_GPS_GLOBAL_ORIGIN")) == 1
    assert out.stats()["ignored"] == {"bad_signature": 2}


def test_a_flood_of_junk_datagrams_does_not_starve_the_pose_stream():
    """100 random 64 KiB datagrams a second at the daemon's MAVLink socket while poses stream at
    30 Hz: every pose still goes out, the junk is dropped unparsed, a real message still arrives."""
    import socket
    import threading
    import time

    from mavlink_helpers import UdpPeer, mavlink_output, of_type
    from pymavlink.dialects.v20 import common as mavlink2

    peer = UdpPeer()
    out = mavlink_output(f"udpout:127.0.0.1:{peer.port}", WALL, wait_heartbeat=False, queue_size=4)
    got = []
    out.subscribe("SYSTEM_TIME", lambda msg, now_s: got.append(msg.time_boot_ms))
    stop = threading.Event()
    sent_junk = [0]

    def flood(addr):
        rng = __import__("random").Random(7)
        junk = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            while not stop.is_set() and sent_junk[0] < 400:   # at most 4 s of it
                junk.sendto(rng.randbytes(65507), addr)
                sent_junk[0] += 1
                time.sleep(0.01)
        finally:
            junk.close()

    try:
        assert peer.collect(2.0, until=lambda ms: bool(of_type(ms, "HEARTBEAT")))
        daemon_addr = peer.sender
        flooder = threading.Thread(target=flood, args=(daemon_addr,), daemon=True)
        flooder.start()
        submitted = 0
        for k in range(60):                       # 2 s of poses at 30 Hz
            out.submit(vehicle_result(WALL, k, 100.0 + k / 30, (-2.0, 0.0, 0.0)))
            submitted += 1
            if k == 30:                           # a real message amid the junk
                ap = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
                peer.send(ap.system_time_encode(0, 4321).pack(ap))
            time.sleep(1 / 30)
        wait_for(lambda: out.stats()["written"] + out.stats()["dropped_total"] >= submitted, 5.0)
        msgs = peer.collect(3.0, until=lambda ms: len(of_type(ms, "ODOMETRY")) >= submitted)
        assert wait_for(lambda: bool(got), 3.0)
    finally:
        stop.set()
        out.close()
        peer.close()
    odo = of_type(msgs, "ODOMETRY")
    assert sent_junk[0] >= 20
    assert len(odo) >= submitted - 3, (len(odo), submitted, out.status())
    assert got == [4321]
    assert out.stats()["ignored"].get("oversized", 0) >= 10


def _free_udp_port() -> int:
    import socket

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def test_a_serial_port_is_held_by_one_daemon_only(tmp_path, caplog):
    from mavlink_helpers import VanishingPty, mavlink_output

    from pose_daemon.config import SerialOutputConfig
    from pose_daemon.outputs import PlainSerialOutput
    from pose_daemon.outputs.plain_serial import parse_pose_line

    pty = VanishingPty(str(tmp_path / "ttyMCU"))
    first = PlainSerialOutput(SerialOutputConfig(port=pty.path), WALL, queue_size=0)
    caplog.set_level("WARNING", logger="pose_daemon.outputs")
    second = PlainSerialOutput(SerialOutputConfig(port=pty.path, retry_s=0.05, retry_max_s=0.1), WALL,
                               queue_size=0)
    fc = mavlink_output(pty.path, WALL, wait_heartbeat=False, queue_size=0, retry_s=0.05, retry_max_s=0.1)
    try:
        assert first.link_up and not second.link_up and not fc.link_up
        for k in range(5):
            second.submit(vehicle_result(WALL, k, 200.0 + k / 30, (-3.0, 0.0, 0.0)))
            first.submit(vehicle_result(WALL, k, 100.0 + k / 30, (-2.0, 0.0, 0.0)))
        data = pty.read(1.0, until=lambda b: b.count(b"\r\n") >= 5)
        wait_for(lambda: False, 0.3)               # the second's retries: still one line each
        refused = second.status()
    finally:
        second.close()
        fc.close()
        first.close()
        pty.close()
    lines = [parse_pose_line(s + "\r\n") for s in data.decode("ascii").split("\r\n")[:-1]]
    assert [f["t_us"] for f in lines] == [round((100.0 + k / 30) * 1e6) for k in range(5)]
    assert "in use by another process" in refused and second.stats()["dropped"] == {"link_down": 5}
    warnings = [r.getMessage() for r in caplog.records if "in use by another process" in r.getMessage()]
    assert len(warnings) == 2, warnings            # one line for each refused output, not one per retry


def test_a_second_udpin_daemon_on_one_port_is_warned_about(caplog):
    from mavlink_helpers import mavlink_output

    port = _free_udp_port()
    caplog.set_level("WARNING", logger="pose_daemon.outputs")
    first = mavlink_output(f"udpin:127.0.0.1:{port}", WALL, wait_heartbeat=False, queue_size=0)
    try:
        assert first.link_up and not [r for r in caplog.records if "UDP port" in r.getMessage()]
        second = mavlink_output(f"udpin:127.0.0.1:{port}", WALL, wait_heartbeat=False, queue_size=0)
        second.close()
    finally:
        first.close()
    warnings = [r.getMessage() for r in caplog.records if "UDP port" in r.getMessage()]
    assert len(warnings) == 1 and f"127.0.0.1:{port}" in warnings[0] and "another" in warnings[0], warnings
