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
