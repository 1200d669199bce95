"""A stop signal during ``pose-daemon run``'s start-up whose exception Python drops (raised while
a weakref callback runs, as importlib's module locks have, it is printed as "Exception ignored
in ..." and discarded) still stops the daemon: exit 0, STOPPING=1, never READY=1."""

from __future__ import annotations

import signal
import subprocess
import sys

import pytest
from test_run import ENV, _config, _notify_lines, _notify_socket

# Runs the daemon with a SIGTERM delivered, at one point of its start-up, to a handler that runs
# inside a weakref callback: its StartupStop is dropped. Points: "import:M" while module M is
# being imported (a finder first on sys.meta_path); "after:M:F" / "before:M:F" right after or
# before the start-up step F (a function or Class.method) of module M, patched in.
_DROPPED_STOP_DAEMON = r"""
import functools, importlib, os, runpy, signal, sys, weakref

class _Box:
    pass

def drop_a_stop():
    box = _Box()

    def callback(_ref):
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):  # the Python handler runs in here: its exception is dropped
            pass

    ref = weakref.ref(box, callback)
    del box  # the callback runs now, while ref lives
    print("start-up went on after the dropped stop", file=sys.stderr)
    return ref

class Gate:
    def __init__(self, name):
        self.name, self.done = name, False

    def find_spec(self, name, path=None, target=None):
        if name == self.name and not self.done:
            self.done = True
            drop_a_stop()
        return None

point = sys.argv.pop(1)
how, module = point.split(":")[:2]
if how == "import":
    sys.meta_path.insert(0, Gate(module))
else:
    owner = importlib.import_module(module)
    *path, attr = point.split(":")[2].split(".")
    for part in path:
        owner = getattr(owner, part)
    step = getattr(owner, attr)

    @functools.wraps(step)
    def patched(*args, **kwargs):
        if how == "before":
            drop_a_stop()
        result = step(*args, **kwargs)
        if how == "after":
            drop_a_stop()
        return result

    setattr(owner, attr, patched)
runpy.run_module("pose_daemon", run_name="__main__", alter_sys=True)
"""


@pytest.mark.parametrize(
    "point",
    [
        "import:numpy",
        "import:cv2",
        "import:pose_daemon.service",
        "import:pose_daemon.capture.synthetic",
        "import:pose_daemon.pose.estimator",
        "after:pose_daemon.commands.run:check_whole",
        "after:pose_daemon.service:Service.__init__",
        "before:pose_daemon.service:Service.install_signal_handlers",
    ],
)
def test_a_dropped_stop_during_start_up_still_stops_the_daemon(tmp_path, point):
    # 60 frames: had the stop been lost, the daemon would end by itself (READY=1 sent first)
    # rather than run on.
    cfg = _config(tmp_path, '[camera]\nsource = "synthetic"\n[synthetic]\nframes = 60\n[output.jsonl]\npath = "-"\n')
    notify, notify_path = _notify_socket(tmp_path)
    proc = subprocess.run(
        [sys.executable, "-c", _DROPPED_STOP_DAEMON, point, "run", "--config", str(cfg)],
        capture_output=True,
        text=True,
        env=dict(ENV, NOTIFY_SOCKET=notify_path),
        timeout=120,
    )
    lines = _notify_lines(notify)
    notify.close()
    err = proc.stderr
    assert "start-up went on after the dropped stop" in err, err  # its exception was dropped ...
    assert "Exception ignored" not in err and "Traceback" not in err, err  # ... without a word
    assert proc.returncode == 0, (proc.returncode, err)
    assert "stopping: SIGTERM during start-up" in err, err
    assert "READY=1" not in lines and "STOPPING=1" in lines, lines
    assert proc.stdout == ""  # no pose went out


def test_a_stop_signal_after_the_first_is_raised_again_while_held():
    """The handler raises on every stop signal while held, not only the first (that one may be
    the dropped one), and ``check()`` raises a held stop at a safe point until handed over."""
    from pose_daemon import startup

    startup.hold()
    try:
        for _ in range(2):
            with pytest.raises(startup.StartupStop, match="SIGTERM"):
                signal.raise_signal(signal.SIGTERM)
        with pytest.raises(startup.StartupStop, match="SIGTERM"):
            startup.check()
        with pytest.raises(startup.StartupStop, match="SIGTERM"):
            __import__("pose_daemon.not_a_module_at_all")  # every import is a safe point
        assert sys.unraisablehook is startup._unraisable
        assert startup.handed_over() == signal.SIGTERM
        assert sys.unraisablehook is not startup._unraisable and startup._FINDER not in sys.meta_path
        startup.check()  # handed over: nothing held any more
        signal.raise_signal(signal.SIGHUP)  # ignored until release
    finally:
        startup.release()
