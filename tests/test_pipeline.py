"""The threaded pipeline: newest frame wins, the latency budget, slow outputs, source faults, status."""

from __future__ import annotations

import functools
import gc
import threading
import time

import pytest
from pipeline_fakes import FakeOutput, FakeProcessor, FakeSource, outputs_of

from pose_daemon.pipeline import LatencyWindow, NewestSlot, Pipeline
from pose_daemon.service import IdleCollector


def _run(pipeline: Pipeline, timeout_s: float = 10.0) -> None:
    """Start, wait for the end of the stream, stop, and close the outputs (they write what
    they queued)."""
    pipeline.start()
    assert pipeline.wait(timeout_s), "pipeline did not finish"
    pipeline.stop()
    for output in pipeline.outputs:
        output.close()


@pytest.mark.pi
def test_newest_slot_replaces_and_counts():
    slot = NewestSlot()
    assert slot.put("a", 0, 1.0) is False
    assert slot.put("b", 0, 2.0) is True
    assert slot.get(0.01) == ("b", 0, 2.0)
    assert slot.get(0.01) is None
    slot.put("c", 1, 3.0)
    slot.close()
    assert not slot.closed  # closed, but a frame still waits
    assert slot.get(0.01) == ("c", 1, 3.0)
    assert slot.closed and slot.get(0.01) is None


@pytest.mark.pi
def test_latency_window_percentiles_and_bounded_size():
    w = LatencyWindow(size=100)
    for i in range(1, 101):
        w.add("total", i / 1000.0)
    p50, p95, mx = w.summary_ms("total")
    assert p50 == pytest.approx(50.5) and p95 == pytest.approx(95.05) and mx == pytest.approx(100.0)
    for _ in range(100):
        w.add("total", 0.001)  # the ring keeps the newest 100 only
    assert w.summary_ms("total") == pytest.approx((1.0, 1.0, 1.0))
    assert w.summary_ms("detect") is None


def test_newest_frame_wins_and_every_replaced_frame_is_counted():
    source = FakeSource(frames=150, period_s=0.0005)
    proc = FakeProcessor(delay=lambda s: 0.006)
    # Room in the output's queue for every frame: with the default 4, an output thread held
    # up 24 ms on a loaded machine lost the oldest (queue_full: frames 0, 5, 10 once so).
    p = Pipeline(source, proc, outputs_of(functools.partial(FakeOutput, queue_size=150)), latency_budget_s=5.0)
    (out,) = p.outputs
    _run(p)
    snap = p.stats.snapshot()
    assert snap["captured"] == 150
    assert snap["drops"].get("replaced", 0) > 50  # processing is ~10x slower than capture
    assert snap["processed"] + snap["drops"]["replaced"] == 150
    assert proc.seen == sorted(proc.seen) and len(set(proc.seen)) == len(proc.seen)
    assert proc.seen[-1] == 149  # the newest frame is never the one dropped
    assert [g[0] for g in out.got] == proc.seen
    assert source.closes == 1


def test_budget_drops_late_frames_before_and_after_processing():
    gate = threading.Semaphore(0)
    old = {3, 7, 11}  # captured 0.5 s ago: late before processing
    slow = {5, 9}  # processing takes longer than the budget
    source = FakeSource(frames=15, old_seqs=old, gate=gate)
    proc = FakeProcessor(delay=lambda s: 0.15 if s in slow else 0.0, gate=gate)
    p = Pipeline(source, proc, outputs_of(FakeOutput), latency_budget_s=0.1)
    (out,) = p.outputs
    assert out.max_age_s == 0.1  # the output is built with the pipeline's budget
    _run(p)
    snap = p.stats.snapshot()
    # Old frames are dropped before processing; the results of slow frames by the output,
    # whose age check is the last step before the bytes are written.
    assert snap["drops"] == {"late": 3}
    assert out.stats()["dropped"] == {"late": 2}
    assert sorted(proc.seen) == sorted(set(range(15)) - old)
    assert [g[0] for g in out.got] == sorted(set(range(15)) - old - slow)
    # Nothing left later than the budget: latency_s is capture -> handed to the outputs.
    assert all(0.0 <= g[2] <= 0.1 for g in out.got)
    line = p.status_line()
    assert "frames 12, drops late 3;" in line
    assert "fake 10 sent (link closed, dropped late=2)" in line


def test_slow_output_never_blocks_capture_processing_or_other_outputs():
    release = threading.Event()
    source = FakeSource(frames=200, period_s=0.001)
    proc = FakeProcessor()
    # A queue deep enough that the fast output keeps up on a loaded machine.
    p = Pipeline(
        source,
        proc,
        outputs_of(
            functools.partial(FakeOutput, "fast", queue_size=32),
            functools.partial(FakeOutput, "slow", block=release, queue_size=32),
        ),
        latency_budget_s=5.0,
    )
    fast, slow = p.outputs
    p.start()
    deadline = time.monotonic() + 10
    while p.stats.snapshot()["processed"] + p.stats.snapshot()["drops"].get("replaced", 0) < 200:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    time.sleep(0.05)
    snap = p.stats.snapshot()
    processed = snap["processed"]
    assert len(fast.got) == processed
    assert slow.got == []
    # One result is stuck in the blocked write, 32 wait in the queue, the rest were dropped.
    assert slow.stats()["dropped"] == {"queue_full": processed - 1 - 32}
    assert snap["drops"].get("replaced", 0) + processed == 200 and set(snap["drops"]) <= {"replaced"}
    release.set()
    assert p.wait(5.0)
    p.stop()
    slow.close()
    fast.close()
    assert len(slow.got) == 33
    assert p.stats.snapshot()["written"] == {"fast": processed, "slow": 33}


def test_failing_output_is_counted_and_the_others_go_on():
    gate = threading.Semaphore(0)
    p = Pipeline(
        FakeSource(frames=10, gate=gate),
        FakeProcessor(gate=gate),
        outputs_of(
            functools.partial(FakeOutput, "bad", fail=lambda s: s % 2 == 0, queue_size=16),
            functools.partial(FakeOutput, "good", queue_size=16),
        ),
        latency_budget_s=5.0,
    )
    bad, good = p.outputs
    _run(p)
    assert [g[0] for g in good.got] == list(range(10))
    assert [g[0] for g in bad.got] == [1, 3, 5, 7, 9]
    assert p.stats.snapshot()["drops"] == {}
    assert bad.stats()["dropped"] == {"error": 5}
    line = p.status_line()
    assert "bad 5 sent (link closed, dropped error=5, errors 5 (last: OSError: write failed at frame 8))" in line
    assert "good 10 sent (link closed)" in line


class _RaisingOutput(FakeOutput):
    """Breaks the Output promise: ``submit`` raises for even frames."""

    def submit(self, result) -> None:
        if result.seq % 2 == 0:
            raise RuntimeError(f"bug at frame {result.seq}")
        super().submit(result)


def test_an_output_whose_submit_raises_is_counted_and_the_others_go_on():
    gate = threading.Semaphore(0)
    p = Pipeline(
        FakeSource(frames=10, gate=gate),
        FakeProcessor(gate=gate),
        outputs_of(
            functools.partial(_RaisingOutput, "bad", queue_size=16),
            functools.partial(FakeOutput, "good", queue_size=16),
        ),
        latency_budget_s=5.0,
    )
    bad, good = p.outputs
    _run(p)
    assert [g[0] for g in good.got] == list(range(10))
    assert [g[0] for g in bad.got] == [1, 3, 5, 7, 9]
    assert p.stats.snapshot()["drops"] == {"failed[bad]": 5}
    assert "drops failed[bad] 5;" in p.status_line()


def test_source_failure_mid_run_reopens_with_backoff_and_resets_the_track():
    gate = threading.Semaphore(0)
    source = FakeSource(frames=20, gate=gate, fail_at={6, 7})
    proc = FakeProcessor(gate=gate)
    p = Pipeline(
        source,
        proc,
        outputs_of(functools.partial(FakeOutput, queue_size=16)),
        latency_budget_s=5.0,
        source_retry_s=0.2,
        source_retry_max_s=0.3,
    )
    (out,) = p.outputs
    t0 = time.monotonic()
    p.start()
    states = set()
    while not p.finished.is_set() and time.monotonic() - t0 < 10:
        states.add(p.source_state)
        time.sleep(0.01)
    elapsed = time.monotonic() - t0
    p.stop()
    out.close()
    assert [g[0] for g in out.got] == list(range(20))
    assert source.opens == 3 and source.closes == 3
    assert p.stats.snapshot()["source_failures"] == 2
    assert proc.resets == 1  # frames after the reopened source start a new track
    assert "failed (camera unplugged at read 6), reopening in 0.2 s" in states
    assert "failed (camera unplugged at read 7), reopening in 0.3 s" in states  # doubled, capped
    assert elapsed >= 0.5
    assert "source ended" in p.status_line()


@pytest.mark.pi
def test_status_line_counts():
    gate = threading.Semaphore(0)
    source = FakeSource(frames=10, gate=gate)
    proc = FakeProcessor(detect=lambda s: s % 2 == 0, gate=gate)
    p = Pipeline(source, proc, outputs_of(functools.partial(FakeOutput, "jsonl", queue_size=16)), latency_budget_s=5.0)
    (out,) = p.outputs
    _run(p)
    line = p.status_line()
    assert "detected 50% (5/10)" in line
    assert "frames 10, drops none" in line
    assert "jsonl 10 sent" in line
    for stage in ("capture", "queue", "detect", "estimate", "output", "total"):
        assert f" {stage} " in line or f": {stage} " in line
    # The window restarts after a line: rates start again from zero.
    again = p.status_line()
    assert "detected 0% (0/0)" in again and "latency ms p50/p95/max: no frames" in again
    assert [g[3] for g in out.got] == [s % 2 == 0 for s in range(10)]


def test_stop_is_prompt_even_with_a_blocked_output():
    block = threading.Event()
    p = Pipeline(
        FakeSource(frames=10**6, period_s=0.001),
        FakeProcessor(),
        outputs_of(functools.partial(FakeOutput, "stuck", block=block)),
        latency_budget_s=5.0,
    )
    (stuck,) = p.outputs
    p.start()
    assert p.first_frame.wait(5.0)
    time.sleep(0.05)  # the output is now stuck in a write
    t0 = time.monotonic()
    clean = p.stop(timeout_s=0.5)
    assert time.monotonic() - t0 < 0.7
    assert clean  # capture and processing never wait on an output
    t0 = time.monotonic()
    stuck.close(timeout_s=0.3)  # the stuck output's thread is left behind, as a daemon thread
    assert time.monotonic() - t0 < 0.5
    assert stuck.stats()["link"] != "closed"
    block.set()


def test_outputs_that_write_in_their_own_thread_report_bytes_written_latency():
    gate = threading.Semaphore(0)
    written = []
    p = Pipeline(
        FakeSource(frames=5, gate=gate),
        FakeProcessor(gate=gate),
        outputs_of(functools.partial(FakeOutput, "queued", write_s=0.02, queue_size=5)),
        latency_budget_s=60.0,
        on_written=lambda name, r, t: written.append((name, r.seq, t)),
    )
    (out,) = p.outputs
    # The output is built with the budget, one no loaded machine reaches: none is dropped late;
    # and with room for all 5 results: with the default 4, a loaded machine's output thread
    # that had not yet taken frame 0 when frame 4 came lost it (queue_full, oldest first).
    assert out.max_age_s == 60.0
    _run(p)
    assert [w[1] for w in written] == [0, 1, 2, 3, 4] and {w[0] for w in written} == {"queued"}
    assert p.stats.snapshot()["written"] == {"queued": 5}
    # Latency runs to the moment the output wrote, not to the hand-over.
    for (_, seq, t_written), (seq2, t_capture, _, _) in zip(written, out.got):
        assert seq == seq2 and t_written - t_capture >= 0.02
    p50, _, _ = p.stats.window.summary_ms("output")
    assert p50 >= 20.0


class _GarbageProcessor(FakeProcessor):
    """Makes 60 reference cycles per frame and records collections that run inside ``process``."""

    def __init__(self, gate: threading.Semaphore) -> None:
        super().__init__(gate=gate)
        self.inside = False
        self.collections_inside = 0

    def process(self, frame):
        self.inside = True
        try:
            for _ in range(60):
                cycle: list = []
                cycle.append(cycle)
            return super().process(frame)
        finally:
            self.inside = False


def _garbage_run(collect_when_idle: bool):
    # The gate: the source makes frame k + 1 only once frame k was processed, so that a slow
    # first collection on a loaded machine cannot get a frame replaced (newest wins). With the
    # idle collector, only once the pipeline went idle after frame k and ran it: on a loaded
    # machine the processing thread, held up after a frame, could otherwise find the next one
    # already waiting, go without an idle gap for frames on end and let the automatic
    # collector (which stays on for a pipeline with no idle time) run inside one.
    gate = threading.Semaphore(0)
    proc = _GarbageProcessor(threading.Semaphore(0) if collect_when_idle else gate)
    collector = IdleCollector() if collect_when_idle else None

    def idle() -> None:
        assert collector is not None
        collector.run()
        gate.release()

    def note(phase, info):
        if phase == "start" and proc.inside:
            proc.collections_inside += 1

    threshold = gc.get_threshold()
    gc.unfreeze()  # what an earlier daemon in this process froze
    frozen_before = gc.get_freeze_count()
    gc.set_threshold(400, 10, 10)
    gc.callbacks.append(note)
    try:
        p = Pipeline(
            FakeSource(frames=30, period_s=0.01, gate=gate),
            proc,
            outputs_of(FakeOutput),
            latency_budget_s=5.0,
            on_idle=idle if collector is not None else None,
        )
        (out,) = p.outputs
        _run(p)
        frozen = gc.get_freeze_count() - frozen_before
    finally:
        gc.callbacks.remove(note)
        gc.set_threshold(*threshold)
        gc.unfreeze()
    assert p.stats.snapshot()["processed"] == 30 and len(out.got) == 30
    return collector, proc, frozen


def test_garbage_is_collected_between_frames_not_inside_them():
    collector, proc, frozen = _garbage_run(collect_when_idle=True)
    assert collector.frozen and frozen > 1000  # start-up objects frozen after frame 0
    assert sum(collector.collections) >= 3  # 60+ new objects a frame, collected from 200
    assert proc.collections_inside == 0
    # Without it, the automatic collector runs at 400 objects, often in the middle of a frame.
    collector, proc, frozen = _garbage_run(collect_when_idle=False)
    assert collector is None and frozen == 0
    assert proc.collections_inside > 0


def test_status_line_works_out_percentiles_without_holding_the_counters(monkeypatch):
    import pose_daemon.pipeline as pipeline_module
    from pose_daemon.pipeline import PipelineStats

    stats = PipelineStats(time.monotonic)
    for k in range(1, 101):
        stats.window.add("detect", k / 1000.0)
    held = []
    real = pipeline_module.summarize_ms

    def summarize(values_s):
        held.append(stats._lock.locked())  # a frame's processed_frame() would wait on it
        return real(values_s)

    monkeypatch.setattr(pipeline_module, "summarize_ms", summarize)
    line = stats.status_line("ok", ["out 0 sent"])
    assert held and not any(held)
    assert "latency ms p50/p95/max: detect 50.5/95.0/100.0;" in line
    assert line.endswith("frames 0, drops none; source ok; out 0 sent")
    # Reset: the next line starts a new window.
    assert "latency ms p50/p95/max: no frames" in stats.status_line("ok", [])
