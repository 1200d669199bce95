"""Whole-frame search in clutter: the marker found, nothing false, and the per-frame time cap
(with a clock the test controls) leaving the rest of the search to the next frame."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from detect_helpers import ARUCO, CAM, SQUARE, aligned, facing_pose, render

from pose_daemon import MarkerDetector
from pose_daemon.bench.detector import CLUTTER_SCENES, clutter_background
from pose_daemon.detect import aruco_compat
from pose_daemon.detect.aruco import OPENCV_EVERY
from pose_daemon.detect.multi import MapDetector
from pose_daemon.detect.quads import find_quads
from pose_daemon.detect.square import FULL_PASS_EVERY
from pose_daemon.marker_map import MapMarker, MarkerMap
from pose_daemon.render import Effects, random_pose, render_empty


def _scene(kind: str, i: int, with_marker: bool = True, distance_m=(0.5, 1.5)):
    rng = np.random.default_rng([7, i, CLUTTER_SCENES.index(kind)])
    background = clutter_background(kind, rng, CAM.width, CAM.height)
    if not with_marker:
        return render_empty(CAM, effects=Effects(), rng=rng, background=background), None
    rvec, tvec = random_pose(rng, CAM, ARUCO, distance_m=distance_m, max_tilt_deg=50)
    return render(ARUCO, rvec, tvec, seed=i, background=background)


@pytest.mark.parametrize("kind", CLUTTER_SCENES)
def test_aruco_marker_found_in_clutter_and_nothing_without_it(kind: str) -> None:
    for i in range(3):
        image, truth = _scene(kind, i)
        corners = MarkerDetector(ARUCO).detect(image)
        assert corners is not None, f"{kind} frame {i}: marker not found"
        assert float(np.abs(corners - truth).max()) < 0.5
        empty, _ = _scene(kind, i, with_marker=False)
        assert MarkerDetector(ARUCO).detect(empty) is None, f"{kind} frame {i}: false detection"


class StepClock:
    """A clock the test controls: every reading advances it by ``step_s``."""

    def __init__(self, step_s: float) -> None:
        self.t_s, self.step_s, self.readings = 0.0, step_s, 0

    def __call__(self) -> float:
        self.readings += 1
        self.t_s += self.step_s
        return self.t_s


def _decoys(background: np.ndarray, cell_px: int = 7) -> np.ndarray:
    """``background`` with four copies of the marker in its corners, each with two wrong
    bits: read from the rough outline they may be the marker (one more bit error is allowed
    there), after the edge fit they are not. Larger than a far marker, so searched first."""
    dictionary = aruco_compat.get_dictionary(ARUCO.dictionary)
    code = aruco_compat.marker_image(dictionary, ARUCO.id, 6).astype(np.float32)
    code[1, 1], code[3, 4] = 255.0 - code[1, 1], 255.0 - code[3, 4]
    big = 30.0 + np.kron(code, np.ones((cell_px, cell_px), np.float32)) * (205.0 / 255.0)
    side = big.shape[0]
    out = background.copy()
    for x, y in ((10, 10), (CAM.width - side - 2 * cell_px - 10, 10), (10, CAM.height - side - 2 * cell_px - 10)):
        out[y : y + side + 2 * cell_px, x : x + side + 2 * cell_px] = 235.0  # quiet zone
        out[y + cell_px : y + cell_px + side, x + cell_px : x + cell_px + side] = big
    return out


def test_time_cap_leaves_the_rest_of_the_search_to_the_next_frame() -> None:
    """Every clock reading costs 1 ms, the cap is 0.5 ms: a frame examines one candidate
    and stops; the search goes on next frame and reaches the (small, far) marker, after
    decoys that each take a frame of their own (a rough outline's code read, then the fit)."""
    rng = np.random.default_rng([7, 1, CLUTTER_SCENES.index("board")])
    background = _decoys(clutter_background("board", rng, CAM.width, CAM.height))
    rvec, tvec = random_pose(rng, CAM, ARUCO, distance_m=(2.5, 3.2), max_tilt_deg=50)
    image, truth = render(ARUCO, rvec, tvec, seed=1, background=background)
    uncapped = MarkerDetector(ARUCO)
    assert uncapped.detect(image) is not None
    capped = MarkerDetector(ARUCO, search_budget_ms=0.5, clock=StepClock(1e-3))
    results = []
    for _ in range(200):
        found = capped.detect(image)
        results.append(found)
        if found is not None:
            break
        assert capped.last_search_deferred and capped.last_stage is None
        assert capped.last_search.full == "deferred" and capped.last_search.stage is None
    assert results[-1] is not None and float(np.abs(results[-1] - truth).max()) < 0.5
    assert capped.search_deferrals == len(results) - 1 >= 2
    assert not capped.last_search_deferred
    # Once tracked the marker is followed: no whole-frame search, nothing deferred.
    before = capped.search_deferrals
    assert capped.detect(image) is not None and capped.last_stage == "follow"
    assert capped.search_deferrals == before


def test_time_cap_on_marker_free_frames_cycles_through_every_step() -> None:
    """Without the marker a capped search never stalls on one step: each search runs its
    steps (the half-size pass; in turns the full-size pass and OpenCV's detector) and starts
    over."""
    empty, _ = _scene("text", 1, with_marker=False)
    capped = MarkerDetector(ARUCO, search_budget_ms=0.5, clock=StepClock(1e-3))
    finder = capped._finder
    stopped_in, searches = set(), 0
    for _ in range(1000):
        assert capped.detect(empty) is None
        if capped._cursor == (0, 0):
            searches += 1
            if searches == OPENCV_EVERY + 1:
                break
        else:  # the search goes on next frame, with the same steps (nothing ended)
            stopped_in.add(finder.stages(empty, None)[capped._cursor[0]])
    assert searches == OPENCV_EVERY + 1
    assert stopped_in >= {("quads", 1), ("opencv", 1)}  # both costly steps reached
    assert finder.fruitless_searches == OPENCV_EVERY + 1
    assert capped.search_deferrals >= 3


def test_opencv_step_runs_in_one_of_every_few_fruitless_searches() -> None:
    """OpenCV's detector is the whole-frame search's safety net: it runs in the first search
    of a run and in one of every OPENCV_EVERY searches that find nothing after it (counted
    by the finder), and a found marker starts the count again."""
    empty, _ = _scene("carpet", 0, with_marker=False)
    image, _ = _scene("carpet", 0)
    detector = MarkerDetector(ARUCO)
    finder = detector._finder
    ran = []
    real = finder._search_opencv

    def spy(*args, **kwargs):
        ran.append(finder.fruitless_searches)
        return real(*args, **kwargs)

    finder._search_opencv = spy
    for _ in range(2 * OPENCV_EVERY):
        assert detector.detect(empty) is None
    assert ran == [0, OPENCV_EVERY - 1, 2 * OPENCV_EVERY - 1]
    detector.reset()
    assert detector.detect(image) is not None and finder.fruitless_searches == 0


def test_no_cap_never_defers_and_an_ample_cap_gives_the_same_corners() -> None:
    image, _ = _scene("carpet", 2)
    free = MarkerDetector(ARUCO)
    ample = MarkerDetector(ARUCO, search_budget_ms=1e6, clock=StepClock(1e-3))
    a, b = free.detect(image), ample.detect(image)
    assert a is not None and np.array_equal(a, b)
    assert free.search_deferrals == 0 and ample.search_deferrals == 0


@pytest.mark.parametrize(
    "bad, message",
    [
        ({"search_budget_ms": 0.0}, "search_budget_ms must be a number > 0 or None"),
        ({"search_budget_ms": "fast"}, "search_budget_ms must be a number > 0 or None"),
        ({"clock": 3.0}, "clock must be a callable"),
        ({"search_threads": 0}, "search_threads must be an integer in \\[1, 64\\] or None"),
    ],
)
def test_bad_cap_options_raise(bad, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        MarkerDetector(ARUCO, **bad)


@pytest.mark.parametrize("kind", ["text", "board"])
def test_opencv_step_on_a_second_core_gives_the_same_results(kind: str) -> None:
    one, two = MarkerDetector(ARUCO, search_threads=1), MarkerDetector(ARUCO, search_threads=2)
    for i in range(2):
        for with_marker in (True, False):
            image, _ = _scene(kind, i, with_marker=with_marker)
            one.reset()
            two.reset()
            a, b = one.detect(image), two.detect(image)
            assert (a is None) == (b is None) == (not with_marker)
            if a is not None:
                assert np.array_equal(a, b)
    # A capped search may leave the early OpenCV run behind: the next frame still comes right.
    capped = MarkerDetector(ARUCO, search_threads=2, search_budget_ms=1.5, clock=StepClock(1e-3))
    empty, _ = _scene(kind, 0, with_marker=False)
    image, truth = _scene(kind, 0)
    for _ in range(5):
        assert capped.detect(empty) is None
    for _ in range(100):
        found = capped.detect(image)
        if found is not None:
            break
    assert found is not None and float(np.abs(found - truth).max()) < 0.5


@pytest.mark.parametrize("marker", [ARUCO, SQUARE], ids=["aruco", "square"])
def test_full_size_pass_traced_on_the_worker_after_a_fruitless_search(marker) -> None:
    """With 2 search threads the full-size pass's threshold and tracing run on the worker
    while the half-size pass runs, but only once a whole-frame search found nothing (the
    first search after a lost track usually ends in its half-size pass); the outlines, and
    so the results, are the ones the search would trace itself."""
    one, two = MarkerDetector(marker, search_threads=1), MarkerDetector(marker, search_threads=2)
    finder = two._finder
    traced_on = []
    real = finder._trace

    def spy(gray, stage, roi, block):
        traced_on.append((threading.current_thread().name.startswith("pose-daemon-search"), stage))
        return real(gray, stage, roi, block)

    finder._trace = spy
    found_by = []
    # A run of marker-free frames, the marker in the search that has the full-size pass
    # again (FULL_PASS_EVERY fruitless ones after the first), then a frame without it.
    with_marker = [False] * (2 * FULL_PASS_EVERY) + [True, False]
    for i, marker_in_view in enumerate(with_marker):
        rng = np.random.default_rng([9, i])
        background = clutter_background("text", rng, CAM.width, CAM.height)
        if marker_in_view:
            rvec, tvec = random_pose(rng, CAM, marker, distance_m=(0.5, 1.5), max_tilt_deg=50)
            image, _ = render(marker, rvec, tvec, seed=i, background=background)
        else:
            image = render_empty(CAM, effects=Effects(), rng=rng, background=background)
        traced_on.clear()
        a, b = one.detect(image), two.detect(image)
        early = finder._early_outlines  # a search that ended early may leave it running
        if early is not None:
            early[0].result()
        if marker_in_view:
            one.reset()
            two.reset()
        assert (a is None) == (b is None) == (not marker_in_view)
        assert a is None or np.array_equal(a, b)
        found_by.append(sorted(traced_on))
    # The run's 1st search: no fruitless one before it, both passes traced here; then the
    # half-size pass only until the full-size pass's turn, which is traced on the worker; the
    # marker (found in the half-size pass): started there all the same; after the search that
    # found it, both passes here again.
    here = [(False, ("quads", 1)), (False, ("quads", 2))]
    half = [(False, ("quads", 2))]
    worker = [(False, ("quads", 2)), (True, ("quads", 1))]
    turn = [here] + [half] * (FULL_PASS_EVERY - 1) + [worker]
    assert found_by == turn + [half] * (FULL_PASS_EVERY - 1) + [worker, here]


@pytest.mark.parametrize("marker", [ARUCO, SQUARE], ids=["aruco", "square"])
def test_a_run_of_fruitless_searches_takes_the_costly_steps_in_turns(marker) -> None:
    """Every search of a marker-free run has the half-size pass; the run's first has every
    step; after it the full-size pass comes in every FULL_PASS_EVERY-th, OpenCV's step
    (ArUco) in every OPENCV_EVERY-th, never in the same search; a reset starts a new run."""
    empty, _ = _scene("text", 1, with_marker=False)
    detector = MarkerDetector(marker)
    finder = detector._finder
    plans = []
    for _ in range(2 * OPENCV_EVERY):
        plans.append(finder.stages(empty, None))
        assert detector.detect(empty) is None
    half, full, opencv = ("quads", 2), ("quads", 1), ("opencv", 1)
    for count, plan in enumerate(plans):
        expected = [half]
        if count % FULL_PASS_EVERY == 0:
            expected.append(full)
        if marker.type == "aruco" and (count == 0 or count % OPENCV_EVERY == OPENCV_EVERY - 1):
            expected.append(opencv)
        assert plan == expected, count
        assert count == 0 or not (full in plan and opencv in plan)
    detector.reset()
    assert finder.stages(empty, None) == [half, full] + ([opencv] if marker.type == "aruco" else [])
    # A region search (a lost track's) has every step, whatever the run.
    assert detector.detect(empty) is None
    roi_plan = finder.stages(empty, (0, 0, 100, 100))
    assert roi_plan == [full] + ([opencv] if marker.type == "aruco" else [])


@pytest.mark.parametrize("marker", [ARUCO, SQUARE], ids=["aruco", "square"])
def test_a_far_marker_coming_into_view_in_a_run_is_found_within_its_turn(marker) -> None:
    """A marker only the full-size pass of our own sees (far: 15 px across) that comes into
    view during a marker-free run, in any phase of the full-size pass's turns (OpenCV's step,
    one in OPENCV_EVERY, does not come in them), is found within FULL_PASS_EVERY frames, in
    the search that has the full-size pass; a marker the half-size pass sees, in its first."""
    assert OPENCV_EVERY > FULL_PASS_EVERY
    near, _ = render(marker, *facing_pose(10.0, 0.8), seed=1)
    far, truth = render(marker, *facing_pose(10.0, 3.0, 40.0), seed=1)
    finder = MarkerDetector(marker)._finder
    for downscale, sees in ((2, False), (1, True)):
        outlines = finder.stage_items(far, ("quads", downscale), None, 25)
        assert any(finder.process(far, ("quads", downscale), q, None, []) for q in outlines) == sees
    empty = render_empty(CAM, effects=Effects(), rng=np.random.default_rng(3))
    for phase in range(1, FULL_PASS_EVERY + 1):
        for image, within in ((far, FULL_PASS_EVERY), (near, 1)):
            detector = MarkerDetector(marker)
            for _ in range(phase):
                assert detector.detect(empty) is None
            found, frames = None, 0
            while found is None and frames < FULL_PASS_EVERY:
                turn = detector._finder.fruitless_searches % FULL_PASS_EVERY == 0
                found = detector.detect(image)
                frames += 1
            assert found is not None and frames <= within, (phase, frames)
            if image is far:
                assert turn and float(np.abs(aligned(found, truth) - truth).max()) < 0.5


def test_opencv_step_on_a_whole_frame_keeps_every_marker_the_size_check_would() -> None:
    """On a whole frame OpenCV's step skips candidates too short to pass the minimum side
    (perimeter floor 4 * (min_side_px - 2)), so a marker just above that side is still
    found as with the region search's floor, and the textured frame's many tiny outlines
    are not read."""
    finder = MarkerDetector(ARUCO)._finder
    rate = finder._frame_finders.get(np.zeros((480, 640), np.uint8)).parameters.minMarkerPerimeterRate
    assert rate == pytest.approx(4.0 * (10.0 - 2.0) / 640.0)
    # A map's whole-frame search has the same floor.
    mapper = MapDetector(MarkerMap(ARUCO.dictionary, (MapMarker(ARUCO.id, ARUCO.width, (0.0, 0.0, 0.0)),), "floor"))
    checked = 0
    for i in range(12):
        rng = np.random.default_rng([8, i])
        rvec, tvec = random_pose(rng, CAM, ARUCO, distance_m=(3.4, 4.4), max_tilt_deg=30)
        image, truth = render(ARUCO, rvec, tvec, seed=i)
        whole = finder._search_opencv(image, None)
        region = finder._search_opencv(image, (0, 0, CAM.width, CAM.height))
        assert len(whole) == len(region)
        for w, r in zip(whole, region):
            assert np.array_equal(w.corners, r.corners)
        in_map = mapper._search_opencv(image, {})
        assert list(in_map) == [ARUCO.id] * len(whole)
        if whole:
            assert np.array_equal(in_map[ARUCO.id], whole[0].corners)
        checked += len(whole)
    assert checked >= 6


def test_config_search_budget_reaches_the_detector_and_zero_means_no_cap() -> None:
    from pose_daemon.config import parse_config
    from pose_daemon.processing.marker import FrameProcessor

    def detector_for(text: str):
        cfg = parse_config(text, "c.toml")
        return FrameProcessor.from_config(cfg).detector

    assert detector_for('[marker]\ntype = "aruco"\ndictionary = "DICT_4X4_50"\nid = 7\n').search_budget_s is None
    capped = detector_for(
        '[marker]\ntype = "aruco"\ndictionary = "DICT_4X4_50"\nid = 7\n[detector]\nsearch_budget_ms = 40\n'
    )
    assert capped.search_budget_s == pytest.approx(0.040)
    with pytest.raises(Exception, match=r"search_budget_ms: expected a number in \[0, 10000\]"):
        parse_config("[detector]\nsearch_budget_ms = -1\n", "c.toml")


def test_code_read_of_many_outlines_at_once_gives_each_ones_verdict() -> None:
    """The whole-frame search reads the rough outlines' codes in one pass (could_be_many):
    the same verdict as one at a time (could_be), on boards and print, marker or not."""
    finder = MarkerDetector(ARUCO)._finder
    verdicts, batched = [], 0
    for kind in ("board", "text"):
        for with_marker in (True, False):
            image, _ = _scene(kind, 0, with_marker=with_marker)
            for downscale in (2, 1):
                quads = find_quads(image, min_side_px=10, block_px=25, offset_gray=10.0, downscale=downscale)
                batched += len(quads) >= 3
                many = finder.could_be_many(image, np.array(quads)).tolist()
                assert many == [finder.could_be(image, q) for q in quads]
                assert finder.could_be_many(image, np.array(quads[:2])).tolist() == many[:2]
                verdicts += many
    assert batched >= 4 and any(verdicts) and not all(verdicts)


def test_hollow_outlines_are_rejected_before_an_edge_fit_and_the_solid_square_is_found() -> None:
    """A plain square marker is one ink: outlines with a light middle (print's O and D, dark
    frames) are dropped by the quick look before any edge fit (they had cost a fit each,
    most of a square search on a page of print), and the solid square is still found."""
    image = np.full((CAM.height, CAM.width), 215.0, np.float32)
    for k, (x, y) in enumerate(((20, 20), (120, 30), (220, 20), (40, 140), (150, 150))):
        side, stroke = 40 + 4 * k, 5 + k
        image[y : y + side, x : x + side] = 35.0
        image[y + stroke : y + side - stroke, x + stroke : x + side - stroke] = 215.0
    image, _ = render(SQUARE, *facing_pose(20.0, 1.2, 15.0, shift_m=(0.48, 0.34)), seed=3, background=image)
    detector = MarkerDetector(SQUARE, search_threads=1)
    fits = []
    real = detector._finder.refine
    detector._finder.refine = lambda gray, quad, **kw: fits.append(quad) or real(gray, quad, **kw)
    corners = detector.detect(image)
    assert corners is not None
    # The marker's own outline (both passes may fit it), nothing of the five frames.
    centres = np.array([q.mean(axis=0) for q in fits])
    assert len(fits) <= 2 and np.all(np.linalg.norm(centres - corners.mean(axis=0), axis=1) < 3.0)


def test_work_started_early_is_taken_only_by_the_search_that_started_it() -> None:
    """A camera may hand each frame over in the same array, refilled. Outlines traced on the
    worker for one search (left over when its half-size pass found the marker) must not
    stand in for the next frame's full-size pass."""
    near, _ = render(ARUCO, *facing_pose(10.0, 0.8), seed=1)
    far, truth = render(ARUCO, *facing_pose(25.0, 3.6, 20.0, shift_m=(0.9, 0.6)), seed=2)  # full-size pass only
    alone = MarkerDetector(ARUCO, search_threads=1)
    expected = alone.detect(far)
    assert expected is not None and alone.last_search.stage == "full"
    detector = MarkerDetector(ARUCO, search_threads=2)
    empty = render_empty(CAM, effects=Effects(), rng=np.random.default_rng(3))
    for _ in range(FULL_PASS_EVERY):  # fruitless searches: the next one has the full-size pass,
        assert detector.detect(empty) is None  # and its work starts early
    frame = near.copy()
    assert detector.detect(frame) is not None  # found in its half-size pass
    early = detector._finder._early_outlines
    assert early is not None
    early[0].result()  # the full-size pass traced for the near frame, never taken
    detector.reset()
    frame[...] = far  # the next frame, in the same array
    found = detector.detect(frame)
    assert found is not None and np.array_equal(found, expected)
    assert float(np.abs(found - truth).max()) < 0.5
