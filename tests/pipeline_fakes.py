"""Fakes for pipeline and service tests: a scripted frame source, processor and output."""

from __future__ import annotations

import threading
import time
from typing import Callable, List, Optional, Set

import numpy as np

from pose_daemon.capture.base import Frame
from pose_daemon.errors import EndOfStream, SourceError
from pose_daemon.outputs.base import Output, OutputFactory
from pose_daemon.outputs.worker import QueuedOutput
from pose_daemon.pose.types import Pose
from pose_daemon.result import FrameResult

IMAGE = np.zeros((48, 64), np.uint8)


def make_pose(z_m: float = 1.0) -> Pose:
    return Pose(
        rvec=np.zeros(3),
        tvec=np.array([0.0, 0.0, z_m]),
        R=np.eye(3),
        alpha_deg=0.0,
        beta_deg=0.0,
        gamma_deg=0.0,
        reprojection_error_px=0.1,
    )


class FakeSource:
    """``frames`` frames, one every ``period_s``; ``fail_at`` read numbers raise SourceError;
    ``old_seqs`` get a capture time ``age_s`` in the past; ``gate``: wait for it between frames."""

    def __init__(
        self,
        frames: int,
        period_s: float = 0.0,
        *,
        fail_at: Set[int] = frozenset(),
        old_seqs: Set[int] = frozenset(),
        age_s: float = 0.5,
        gate: Optional[threading.Semaphore] = None,
        stall: Optional[tuple] = None,
    ) -> None:
        self.frames = frames
        self.period_s = period_s
        self.fail_at = set(fail_at)
        self.old_seqs = set(old_seqs)
        self.age_s = age_s
        self.gate = gate
        self.stall = stall  # (seq, seconds): sleep before producing that frame
        self.opens = 0
        self.closes = 0
        self.reads = 0
        self.seq = 0
        self.is_open = False
        self._passed_gate = False

    def open(self) -> None:
        self.opens += 1
        self.is_open = True

    def close(self) -> None:
        self.closes += 1
        self.is_open = False

    def read(self) -> Frame:
        assert self.is_open
        self.reads += 1
        if self.seq >= self.frames:
            raise EndOfStream()
        if self.gate is not None and self.seq > 0 and not self._passed_gate:
            if self.seq - 1 in self.old_seqs:
                # The pipeline drops an old frame unprocessed, so nothing opens the gate: give
                # the processing thread time to take it from the slot.
                time.sleep(0.08)
            else:
                assert self.gate.acquire(timeout=5.0)
            self._passed_gate = True
        if self.reads in self.fail_at:
            raise SourceError(f"camera unplugged at read {self.reads}")
        self._passed_gate = False
        if self.stall is not None and self.seq == self.stall[0]:
            time.sleep(self.stall[1])
        if self.period_s:
            time.sleep(self.period_s)
        seq = self.seq
        self.seq += 1
        t = time.monotonic()
        if seq in self.old_seqs:
            t -= self.age_s
        return Frame(IMAGE, t, seq)


class FakeProcessor:
    """Detects on frames where ``detect(seq)``; sleeps ``delay(seq)`` seconds; releases ``gate``."""

    def __init__(
        self,
        detect: Callable[[int], bool] = lambda s: True,
        delay: Callable[[int], float] = lambda s: 0.0,
        gate: Optional[threading.Semaphore] = None,
    ) -> None:
        self.detect = detect
        self.delay = delay
        self.gate = gate
        self.seen: List[int] = []
        self.resets = 0

    def reset(self) -> None:
        self.resets += 1

    def process(self, frame: Frame) -> FrameResult:
        self.seen.append(frame.seq)
        d = self.delay(frame.seq)
        if d:
            time.sleep(d)
        result = FrameResult(seq=frame.seq, t_capture_s=frame.t_capture_s)
        result.stage_s["detect"] = 0.0005
        if self.detect(frame.seq):
            result.corners = np.zeros((4, 2))
            result.pose = make_pose()
            result.stage_s["estimate"] = 0.0002
        else:
            result.error = "no marker"
        if self.gate is not None:
            self.gate.release()
        return result


class FakeOutput(QueuedOutput):
    """An output of the one output layer (QueuedOutput: its queue, thread, age check and hooks)
    that records (seq, t_capture_s, latency_s, ok) of each result it writes. ``block``: each
    write waits for it; ``fail(seq)``: that write raises; ``write_s``: each write takes this
    long; ``only_ok``: like MAVLink, nothing is written without a pose."""

    def __init__(
        self,
        name: str = "fake",
        *,
        block: Optional[threading.Event] = None,
        fail: Callable[[int], bool] = lambda s: False,
        write_s: float = 0.0,
        only_ok: bool = False,
        **kwargs,
    ) -> None:
        self.name = name
        self.block = block
        self.fail = fail
        self.write_s = write_s
        self.only_ok = only_ok
        self.got: List[tuple] = []
        self.closed = False
        super().__init__(**kwargs)

    def _open(self) -> None:
        self.closed = False

    def _close_link(self) -> None:
        self.closed = True

    def _write(self, result: FrameResult) -> int:
        if self.only_ok and not result.ok:
            self._drop("no_pose")
            return 0
        if self.block is not None:
            self.block.wait()
        if self.fail(result.seq):
            raise OSError(f"write failed at frame {result.seq}")
        if self.write_s:
            time.sleep(self.write_s)
        self.got.append((result.seq, result.t_capture_s, result.latency_s, result.ok))
        return 1


def outputs_of(*make: Callable[..., Output]) -> OutputFactory:
    """The OutputFactory for Pipeline/Service: each ``make(**hooks)`` builds one output, e.g.
    ``outputs_of(FakeOutput, functools.partial(FakeOutput, "slow", block=event))``."""

    def build(**hooks) -> List[Output]:
        return [m(**hooks) for m in make]

    return build
