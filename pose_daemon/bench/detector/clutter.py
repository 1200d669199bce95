"""The clutter rows of ``pose-daemon bench detector``: whole-frame searches on cluttered scenes,
with the marker and without (false detections), pose-daemon and the anchor on the same frames."""

from __future__ import annotations

from typing import List, Optional

import numpy as np

from ...camera import Camera, Marker
from ...render import random_pose, render_empty, render_frame
from .common import DICTIONARY, MARKER_ID, MARKER_SIZE_M, Tally, align_labels, fmt, opencv_anchor, score, timed
from .scenes import CLUTTER_SCENES, clutter_background, clutter_effects

#: Search threads of the clutter rows: the daemon's default on a Pi 2 (4 cores), whatever
#: this machine has; the anchor, OpenCV's detector, uses its own threads on every core.
CLUTTER_SEARCH_THREADS = 2


def run_clutter(n_frames: int, seed: int, camera: Camera, repeat: int) -> List[dict]:
    """Whole-frame search on cluttered scenes (``CLUTTER_SCENES``), pose-daemon and the anchor
    (OpenCV's ArucoDetector with sub-pixel refinement) interleaved on the same frames.

    Per scene and marker type: ``n_frames`` frames with the marker (a random pose in front
    of the clutter) and as many of the clutter alone (false detections). Times are the
    detection alone (no pose), each the fastest of ``repeat`` runs."""
    from ...detect import MarkerDetector
    from ...detect.square import FULL_PASS_EVERY

    markers = {
        "square": Marker(MARKER_SIZE_M, MARKER_SIZE_M),
        "aruco": Marker(MARKER_SIZE_M, MARKER_SIZE_M, type="aruco", dictionary=DICTIONARY, id=MARKER_ID),
    }
    anchor_finder = opencv_anchor()
    rows = []
    for s_index, scene in enumerate(CLUTTER_SCENES):
        for kind, marker in markers.items():
            detector = MarkerDetector(marker, search_threads=CLUTTER_SEARCH_THREADS)
            # The marker-free frames go to a detector of their own, one after the other, as a
            # camera that sees no marker for a while: a run of fruitless searches has the
            # full-size pass in one of every FULL_PASS_EVERY, OpenCV's detector (ArUco) in one
            # of every aruco.OPENCV_EVERY, so their mean counts both; the full-size pass is
            # traced on the second thread.
            empty_detector = MarkerDetector(marker, search_threads=CLUTTER_SEARCH_THREADS)
            # The marker coming into view after a run of marker-free frames, in each phase of
            # the full-size pass's turns alike: frames until found (ArUco: a plain square is
            # found in a board's or the rectangles' marker-free frames, so they are no run).
            arrival = MarkerDetector(marker, search_threads=CLUTTER_SEARCH_THREADS)
            arrival_frames: List[Optional[int]] = []
            ours, anchor = Tally(f"{scene}, {kind} (pose-daemon)"), Tally(f"{scene}, aruco (anchor)")
            pose_rng = np.random.default_rng([seed, 10, s_index])
            for i in range(n_frames):
                scene_rng = np.random.default_rng([seed, 11, s_index, i])
                effects = clutter_effects(scene_rng)
                background = clutter_background(scene, scene_rng, camera.width, camera.height)
                rvec, tvec = random_pose(pose_rng, camera, marker, distance_m=(0.5, 3.0), max_tilt_deg=60.0)
                image, truth = render_frame(
                    camera,
                    marker,
                    rvec,
                    tvec,
                    effects=effects,
                    rng=np.random.default_rng([seed, 12, s_index, i]),
                    background=background,
                )
                empty = render_empty(
                    camera, effects=effects, rng=np.random.default_rng([seed, 13, s_index, i]), background=background
                )

                def ours_full(image=image, detector=detector):
                    detector.reset()
                    return detector.detect(image)

                def anchor_full(image=image):
                    found, ids = anchor_finder.detect(image)
                    return next((c.astype(np.float64) for c, m in zip(found, ids) if int(m) == MARKER_ID), None)

                # Interleaved: ours, the anchor, on the same frame, then the marker-free one.
                corners, (seconds, cpu) = timed(ours_full, repeat)
                ours.t_full_s.append(seconds)
                ours.cpu_full_s.append(cpu)
                if corners is not None and kind == "square":
                    corners = align_labels(corners, truth)
                score(ours, corners, truth, rvec, tvec, None)
                if kind == "aruco":
                    corners, (seconds, cpu) = timed(anchor_full, repeat)
                    anchor.t_full_s.append(seconds)
                    anchor.cpu_full_s.append(cpu)
                    score(anchor, corners, truth, rvec, tvec, None)
                # Every repeat does the same work: the count of fruitless searches is put back.
                count = empty_detector._finder.fruitless_searches

                def rewind(count=count, finder=empty_detector._finder):
                    finder.fruitless_searches = count

                def ours_empty(empty=empty, d=empty_detector):
                    if d.tracking:  # after a false detection: this is another scene
                        d.reset()
                    return d.detect(empty)

                found, (seconds, cpu) = timed(ours_empty, repeat, before=rewind)
                ours.t_tracked_s.append(seconds)  # here: the marker-free frame's search
                ours.cpu_tracked_s.append(cpu)
                ours.empty_frames += 1
                ours.false_detections += found is not None
                if kind == "aruco":
                    found, (seconds, cpu) = timed(lambda empty=empty: anchor_full(empty), repeat)
                    anchor.t_tracked_s.append(seconds)
                    anchor.cpu_tracked_s.append(cpu)
                    anchor.empty_frames += 1
                    anchor.false_detections += found is not None
                if kind == "aruco":
                    arrival.reset()
                    for _ in range(i % FULL_PASS_EVERY + 1):
                        arrival.detect(empty)

                    def is_marker(found, truth=truth) -> bool:
                        return found is not None and float(np.abs(found - truth).max()) <= 5.0

                    arrival_frames.append(
                        next((k + 1 for k in range(FULL_PASS_EVERY) if is_marker(arrival.detect(image))), None)
                    )
            row = _clutter_row(scene, kind, ours, anchor if kind == "aruco" else None)
            if arrival_frames:
                row["arrival_first_frame_rate"] = sum(k == 1 for k in arrival_frames) / len(arrival_frames)
                row["arrival_within_rate"] = sum(k is not None for k in arrival_frames) / len(arrival_frames)
                row["arrival_within_frames"] = FULL_PASS_EVERY
            rows.append(row)
    return rows


def _clutter_row(scene: str, kind: str, ours: Tally, anchor: Optional[Tally]) -> dict:
    s = ours.summary()
    row = {
        "scene": scene,
        "marker": kind,
        "frames": s["frames"],
        "detection_rate": s["detection_rate"],
        "wrong_detections": s["wrong_detections"],
        "corner_rms_px": s["corner_rms_px"],
        "false_detections": s["false_detections"],
        "empty_frames": s["empty_frames"],
        "time_median_ms": s["time_full_median_ms"],
        "time_empty_median_ms": s["time_tracked_median_ms"],
        "time_empty_mean_ms": 1e3 * float(np.mean(ours.t_tracked_s)) if ours.t_tracked_s else None,
        "cpu_median_ms": s["cpu_full_median_ms"],
    }
    if anchor is not None:
        a = anchor.summary()
        row.update(
            {
                "anchor_detection_rate": a["detection_rate"],
                "anchor_wrong_detections": a["wrong_detections"],
                "anchor_corner_rms_px": a["corner_rms_px"],
                "anchor_false_detections": a["false_detections"],
                "anchor_time_median_ms": a["time_full_median_ms"],
                "anchor_time_empty_median_ms": a["time_tracked_median_ms"],
                "anchor_time_empty_mean_ms": 1e3 * float(np.mean(anchor.t_tracked_s)) if anchor.t_tracked_s else None,
                "anchor_cpu_median_ms": a["cpu_full_median_ms"],
            }
        )
        # Ratio of medians per frame pair: both timed on the same frames, one after the other.
        row["time_ratio_median"] = float(np.median(np.array(ours.t_full_s) / np.array(anchor.t_full_s)))
        row["time_empty_ratio_median"] = float(np.median(np.array(ours.t_tracked_s) / np.array(anchor.t_tracked_s)))
        # A run of marker-free searches takes its steps in turns: the mean is what it costs.
        row["time_empty_ratio_of_means"] = float(np.mean(ours.t_tracked_s) / np.mean(anchor.t_tracked_s))
        # Processor time of all threads: the anchor spreads its detector over idle cores, so on
        # a loaded machine its wall time gains a second thread's share of the processors.
        row["cpu_empty_ratio_median"] = float(
            np.median(np.array(ours.cpu_tracked_s) / np.maximum(np.array(anchor.cpu_tracked_s), 1e-6))
        )
    return row


def print_clutter(rows: List[dict], n_frames: int) -> None:
    print()
    print(
        f"whole-frame search in clutter: {n_frames} frames per scene and marker type with the marker,"
        f" as many without (false); detection alone, fastest of the repeats, median;"
        f" {CLUTTER_SEARCH_THREADS} search threads (the default on a 4-core Pi 2); anchor ="
        f" OpenCV ArucoDetector + CORNER_REFINE_SUBPIX (its own threads), interleaved on the same frames"
    )
    within = next((r["arrival_within_frames"] for r in rows if "arrival_within_frames" in r), "-")
    anchor_header = (
        f"{'anchor det.':>12}{'anchor':>10}{'no marker':>11}{'mean':>10}{'ratio':>8}{'no marker':>10}{'mean':>7}"
        f"{'CPU':>7}"
    )
    header = (
        f"{'scene, marker':<22}{'detected':>9}{'wrong':>6}{'false':>7}{'time':>10}{'no marker':>11}{'mean':>10}"
        f"{anchor_header}{'arrival':>10}"
    )
    print(header)
    print("-" * len(header))
    for r in rows:
        rate = fmt(None if r["detection_rate"] is None else 100 * r["detection_rate"], ".0f", "%")
        line = (
            f"{r['scene'] + ', ' + r['marker']:<22}{rate:>9}{r['wrong_detections']:>6}"
            f"{r['false_detections']:>3}/{r['empty_frames']:<3}{fmt(r['time_median_ms'], '.2f', ' ms'):>10}"
            f"{fmt(r['time_empty_median_ms'], '.2f', ' ms'):>11}{fmt(r['time_empty_mean_ms'], '.2f', ' ms'):>10}"
        )
        if "anchor_time_median_ms" in r:
            a_rate = fmt(None if r["anchor_detection_rate"] is None else 100 * r["anchor_detection_rate"], ".0f", "%")
            line += (
                f"{a_rate:>12}{fmt(r['anchor_time_median_ms'], '.2f', ' ms'):>10}"
                f"{fmt(r['anchor_time_empty_median_ms'], '.2f', ' ms'):>11}"
                f"{fmt(r['anchor_time_empty_mean_ms'], '.2f', ' ms'):>10}"
                f"{fmt(r['time_ratio_median'], '.2f', 'x'):>8}{fmt(r['time_empty_ratio_median'], '.2f', 'x'):>10}"
                f"{fmt(r['time_empty_ratio_of_means'], '.2f', 'x'):>7}"
                f"{fmt(r['cpu_empty_ratio_median'], '.2f', 'x'):>7}"
            )
        else:
            line += " " * len(anchor_header)
        if "arrival_within_rate" in r:
            line += f"{100 * r['arrival_first_frame_rate']:>5.0f}/{100 * r['arrival_within_rate']:.0f}%"
        else:
            line += f"{'-':>10}"
        print(line)
    print(
        "ratio: median over frames of pose-daemon's time / the anchor's on the same frame (with the marker;"
        " no marker: the marker-free frames, in a row, so that the mean counts OpenCV's step of the search;"
        " mean: the ratio of the mean times; CPU: the median by processor time of all threads); arrival"
        " (aruco): the marker coming into view after marker-free frames (in each phase of the full-size"
        f" pass's turns alike), found in its first frame / within {within} frames"
    )
