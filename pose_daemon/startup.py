"""The daemon's stop signals from its first line: SIGTERM, SIGINT and SIGHUP while it starts.

Loading numpy and OpenCV and building the pipeline takes ~0.5 s on an x86-64 core and far
longer on a Pi 2. A stop signal in that time must not print a KeyboardInterrupt traceback
(SIGINT) nor kill the process before systemd hears STOPPING=1 (SIGTERM, SIGHUP), and a SIGUSR1
(``systemctl reload``: a status line) must not kill it either. So
``pose-daemon run`` calls ``hold()`` before anything heavy is imported: a stop signal then
raises ``StartupStop`` in the main thread, which the command line turns into STOPPING=1, one
line on stderr and exit 0, the same as a stop after start-up. Once the service has installed
its own handlers (which only set flags), ``handed_over()`` makes these ignore what still comes
while the process ends. Standard library only: this module must load in milliseconds.

A raised exception can be lost: one raised while Python runs a weakref callback (importlib's
module locks have one) or a ``__del__`` is printed as "Exception ignored in ..." and dropped. So
the stop is also recorded (``_stop_signum``) and raised again at safe points until the
process hands over or finishes: at every import (a finder first on ``sys.meta_path``) and at
each ``check()`` between start-up steps; ``handed_over()`` returns a stop still pending so
that the service acts on it. The dropped exception's "Exception ignored in" traceback is
not printed (``sys.unraisablehook``, while held): the stop it carried is not lost.
"""

from __future__ import annotations

import signal
import sys
from typing import Dict, Optional

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)

_raising = False
_stop_signum: Optional[int] = None  # the first stop signal while held, until handed over
_previous: Dict[int, object] = {}


class StartupStop(BaseException):
    """A stop signal arrived before the service took the signals over. A BaseException, so that
    no ``except Exception`` on the way (an import's fallback, a source's retry) swallows it."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(signal.Signals(signum).name)

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name


def _on_stop(signum: int, _frame) -> None:
    global _stop_signum
    if _raising:
        if _stop_signum is None:
            _stop_signum = signum
        # Raised each time, not once: the last one may have been dropped (module docstring).
        raise StartupStop(_stop_signum)


def check() -> None:
    """Raise StartupStop if a stop signal came while held (a safe point between start-up steps)."""
    if _raising and _stop_signum is not None:
        raise StartupStop(_stop_signum)


class _StopAtImport:
    """First on ``sys.meta_path`` while held: every import is a safe point (``check()``); it
    finds nothing itself."""

    @staticmethod
    def find_spec(_name, _path=None, _target=None):
        check()
        return None


_FINDER = _StopAtImport()
_previous_unraisablehook = sys.unraisablehook


def _unraisable(args) -> None:
    """``sys.unraisablehook`` while held: a dropped StartupStop is recorded already and raised
    again at the next safe point, so Python's "Exception ignored in ..." traceback about it
    would only alarm; anything else is printed as before."""
    if isinstance(args.exc_value, StartupStop):
        return
    _previous_unraisablehook(args)


def _on_status(_signum: int, _frame) -> None:
    """SIGUSR1 (``systemctl reload``) before there is a status to log: nothing to do, and
    Python's default action would end the process."""


def hold() -> None:
    """From now on a stop signal raises StartupStop and SIGUSR1 is passed over (first thing in
    ``pose-daemon run``)."""
    global _raising, _previous_unraisablehook
    for signum in STOP_SIGNALS:
        _previous.setdefault(signum, signal.signal(signum, _on_stop))
    _previous.setdefault(signal.SIGUSR1, signal.signal(signal.SIGUSR1, _on_status))
    if _FINDER not in sys.meta_path:
        sys.meta_path.insert(0, _FINDER)
    if sys.unraisablehook is not _unraisable:
        _previous_unraisablehook, sys.unraisablehook = sys.unraisablehook, _unraisable
    _raising = True


def handed_over() -> Optional[int]:
    """The service handles the stop signals now; these handlers, if put back, ignore them.
    Returns the stop signal that came while held and was not acted on, if any (then stop)."""
    global _raising, _stop_signum
    pending = _stop_signum if _raising else None
    _raising = False
    _stop_signum = None
    if _FINDER in sys.meta_path:
        sys.meta_path.remove(_FINDER)
    if sys.unraisablehook is _unraisable:
        sys.unraisablehook = _previous_unraisablehook
    return pending


def release() -> None:
    """Back to the handlers from before ``hold()`` (Python's: KeyboardInterrupt, default)."""
    handed_over()
    for signum, handler in _previous.items():
        signal.signal(signum, handler)  # type: ignore[arg-type]
    _previous.clear()


def finish(stop: StartupStop) -> int:
    """STOPPING=1 to systemd and one line on stderr for a stop during start-up; exit status 0."""
    handed_over()  # what still comes is ignored while the process ends
    from .sdnotify import SdNotifier

    notifier = SdNotifier()
    notifier.notify("STOPPING=1", f"STATUS=stopping: {stop.name} during start-up")
    notifier.close()
    print(f"pose-daemon: stopping: {stop.name} during start-up", file=sys.stderr)
    return 0
