"""Drawing helpers for annotated frames: detected corners, the marker's axes, the pose as text,
and for the live preview the rejected planar solution, the marker's id and why there is no pose."""

from __future__ import annotations

from typing import List, Optional, Sequence, Tuple

import cv2
import numpy as np

from .camera import Camera, Marker
from .geometry import R_from_rvec

_SHIFT = 4  # sub-pixel drawing: coordinates in 1/16 px
_ONE = 1 << _SHIFT
CORNER_COLOURS = ((0, 0, 255), (0, 255, 0), (255, 0, 0), (0, 255, 255))  # TL TR BR BL (BGR)
OUTLINE_COLOUR = (0, 255, 0)  # the detected quadrilateral (BGR)
AXIS_COLOURS = ((0, 0, 255), (0, 255, 0), (255, 0, 0))  # x red, y green, z blue
REJECTED_COLOUR = (255, 0, 255)  # the other planar solution's axes: magenta
WARNING_COLOUR = (0, 165, 255)  # warning text: orange
SEARCH_COLOUR = (255, 255, 0)  # the detector's search regions: cyan


def to_bgr(image: np.ndarray) -> np.ndarray:
    """A colour copy of a grey (or already colour) frame to draw on."""
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return image.copy()


def _pt(p) -> Tuple[int, int]:
    # Pixel centres at integers (interface.md): no half-pixel shift.
    return int(round(float(p[0]) * _ONE)), int(round(float(p[1]) * _ONE))


def draw_corners(
    image: np.ndarray, corners_px: np.ndarray, colour=(0, 255, 0), radius_px: float = 4.0, label: bool = True
) -> np.ndarray:
    """The quadrilateral through ``corners_px`` (4, 2), each corner ringed in its own colour
    (TL red, TR green, BR blue, BL yellow) and labelled. Draws in place on a BGR image."""
    c = np.asarray(corners_px, dtype=np.float64).reshape(4, 2)
    pts = np.array([_pt(p) for p in c], np.int32).reshape(-1, 1, 2)
    cv2.polylines(image, [pts], True, colour, 1, cv2.LINE_AA, shift=_SHIFT)
    for i, (p, name) in enumerate(zip(c, ("TL", "TR", "BR", "BL"))):
        cv2.circle(image, _pt(p), int(radius_px * _ONE), CORNER_COLOURS[i], 1, cv2.LINE_AA, shift=_SHIFT)
        if label:
            cv2.putText(
                image,
                name,
                (int(p[0]) + 5, int(p[1]) - 5),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.35,
                CORNER_COLOURS[i],
                1,
                cv2.LINE_AA,
            )
    return image


def draw_axes(
    image: np.ndarray,
    camera: Camera,
    rvec,
    tvec,
    length_m: float,
    colours: Optional[Sequence[Tuple[int, int, int]]] = None,
    thickness: int = 2,
) -> np.ndarray:
    """The marker frame's axes at pose (rvec, tvec): x red, y green, z blue (out of the marker),
    each ``length_m`` long, projected through the lens (``colours``: one colour per axis
    instead). Draws in place on a BGR image."""
    R = R_from_rvec(np.asarray(rvec, dtype=np.float64).reshape(3))
    t = np.asarray(tvec, dtype=np.float64).reshape(3)
    pts_marker = np.array([[0, 0, 0], [length_m, 0, 0], [0, length_m, 0], [0, 0, length_m]], np.float64)
    pts_cam = pts_marker @ R.T + t
    if np.any(pts_cam[:, 2] <= 1e-6):
        return image  # an axis would reach behind the camera: nothing sensible to draw
    px = camera.project(pts_cam)
    for end, colour in zip(px[1:], colours or AXIS_COLOURS):
        cv2.line(image, _pt(px[0]), _pt(end), colour, thickness, cv2.LINE_AA, shift=_SHIFT)
    return image


_TEXT_SCALE = 0.45
# The text box's margin around the text, pixels (draw_text); a wrapped row keeps it inside the frame.
_TEXT_PAD = 3


def _text_width(text: str) -> int:
    return cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, _TEXT_SCALE, 1)[0][0]


def wrap_text(line: str, width_px: int) -> List[str]:
    """``line`` cut into rows no wider than ``width_px`` at spaces (a word wider than that is cut
    where it must), so that a long warning stays on the frame."""
    rows: List[str] = []
    current = ""
    for word in line.split(" "):
        candidate = f"{current} {word}" if current else word
        if _text_width(candidate) <= width_px or not candidate:
            current = candidate
            continue
        if current:
            rows.append(current)
        while _text_width(word) > width_px and len(word) > 1:
            cut = 1
            while cut < len(word) and _text_width(word[: cut + 1]) <= width_px:
                cut += 1
            rows.append(word[:cut])
            word = word[cut:]
        current = word
    rows.append(current)
    return rows


def text_rows(image: np.ndarray, lines: Sequence[str], x_px: int = 8) -> List[str]:
    """The rows ``draw_text`` draws ``lines`` in at ``x_px``: each wrapped to the frame's width."""
    width_px = max(1, image.shape[1] - x_px - 2 * _TEXT_PAD - 1)
    return [row for line in lines for row in wrap_text(line, width_px)]


def draw_text(
    image: np.ndarray, lines: Sequence[str], origin_px: Tuple[int, int] = (8, 18), colour=(255, 255, 255)
) -> np.ndarray:
    """Lines of text on a dark box (readable on any background), top-left first; a line wider
    than the frame is wrapped (``text_rows``)."""
    x, y = origin_px
    for line in text_rows(image, lines, x):
        (w, h), base = cv2.getTextSize(line, cv2.FONT_HERSHEY_SIMPLEX, _TEXT_SCALE, 1)
        cv2.rectangle(image, (x - _TEXT_PAD, y - h - 3), (x + w + _TEXT_PAD, y + base + 1), (0, 0, 0), -1)
        cv2.putText(image, line, (x, y), cv2.FONT_HERSHEY_SIMPLEX, _TEXT_SCALE, colour, 1, cv2.LINE_AA)
        y += h + base + 6
    return image


def pose_lines(result) -> Sequence[str]:
    """Text for one FrameResult: frame, time, and the pose or the reason there is none."""
    head = f"frame {result.seq}  t {result.t_capture_s:.3f} s"
    pose = result.pose
    if pose is None:
        return [head, f"no pose: {result.error or 'no marker'}"]
    x, y, z = (float(v) for v in pose.camera_position)
    return [
        head,
        f"camera in marker frame: x {x:+.3f}  y {y:+.3f}  z {z:+.3f} m",
        f"alpha {pose.alpha_deg:+.1f}  beta {pose.beta_deg:+.1f}  gamma {pose.gamma_deg:+.1f} deg",
        f"reprojection {pose.reprojection_error_px:.2f} px",
    ]


def annotate(
    image: np.ndarray, result, camera: Camera, marker: Marker, true_corners_px: Optional[np.ndarray] = None
) -> np.ndarray:
    """A BGR copy of ``image`` with the detected corners, the marker's axes (half its width)
    and the pose text of ``result`` (a FrameResult); true corners, when known, as grey rings."""
    out = to_bgr(image)
    if true_corners_px is not None:
        for p in np.asarray(true_corners_px, dtype=np.float64).reshape(4, 2):
            cv2.circle(out, _pt(p), 6 * _ONE, (160, 160, 160), 1, cv2.LINE_AA, shift=_SHIFT)
    if result.corners is not None:
        draw_corners(out, result.corners)
    if result.pose is not None:
        draw_axes(out, camera, result.pose.rvec, result.pose.tvec, 0.5 * min(marker.width, marker.height))
    return draw_text(out, pose_lines(result))


def marker_label(marker: Marker) -> str:
    """What the marker is: "ArUco DICT_4X4_50 id 7" or "square 0.20 x 0.20 m"."""
    if marker.type == "aruco":
        return f"ArUco {marker.dictionary} id {marker.id}"
    return f"square {marker.width:.2f} x {marker.height:.2f} m"


def annotate_live(
    image: np.ndarray,
    result,
    camera: Camera,
    marker: Marker,
    *,
    detector_step: Optional[str] = None,
    search=None,
    warnings: Sequence[str] = (),
) -> np.ndarray:
    """The live preview's frame: ``annotate`` plus the rejected planar solution's axes (thin,
    magenta, with its ambiguity ratio), the marker's id at its centre, the detector step that
    found it (follow / roi / full), where the detector searched (``search``, a SearchRecord:
    a thin cyan rectangle per region labelled by step, and a cyan note at the top right when
    the whole frame was searched or its search deferred by the time cap) and the warnings
    (orange) at the bottom."""
    out = annotate(image, result, camera, marker)
    if search is not None:
        draw_search(out, search)
    length = 0.5 * min(marker.width, marker.height)
    pose = result.pose
    if pose is not None and pose.alternative is not None:
        alt = pose.alternative
        draw_axes(out, camera, alt.rvec, alt.tvec, length, colours=(REJECTED_COLOUR,) * 3, thickness=1)
    if result.corners is not None:
        c = np.asarray(result.corners, dtype=np.float64).reshape(4, 2)
        centre = c.mean(axis=0)
        text = marker_label(marker) if marker.type == "aruco" else "square"
        if detector_step:
            text += f" ({detector_step})"
        cv2.putText(
            out,
            text,
            (int(centre[0]) + 6, int(centre[1]) + 14),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.4,
            OUTLINE_COLOUR,
            1,
            cv2.LINE_AA,
        )
    # Bottom-up: the warnings (orange), above them the rejected solution's note (magenta).
    notes = [(text, WARNING_COLOUR) for text in list(warnings)[:3]]
    if pose is not None and pose.alternative is not None:
        notes.insert(0, (f"rejected solution (magenta): ambiguity {pose.ambiguity_ratio:.2f}", REJECTED_COLOUR))
    rows = [(row, colour) for text, colour in notes for row in text_rows(out, [text])]
    y = out.shape[0] - 8 - 19 * (len(rows) - 1)
    for row, colour in rows:
        draw_text(out, [row], origin_px=(8, y), colour=colour)
        y += 19
    return out


def draw_search(image: np.ndarray, search) -> np.ndarray:
    """The detector's search regions (a SearchRecord) in place on a BGR image: a 1 px cyan
    rectangle per region (its outline on the region's outermost pixels), labelled by step,
    and "full search" / "full search deferred (time cap)" at the top right."""
    h, w = image.shape[:2]
    for step, (x0, y0, x1, y1) in search.regions:
        x0, y0 = max(0, x0), max(0, y0)
        x1, y1 = min(w, x1) - 1, min(h, y1) - 1
        if x1 < x0 or y1 < y0:
            continue
        cv2.rectangle(image, (x0, y0), (x1, y1), SEARCH_COLOUR, 1)
        y_text = y0 - 3 if y0 >= 12 else min(h - 2, y1 + 12)
        cv2.putText(image, step, (x0 + 2, y_text), cv2.FONT_HERSHEY_SIMPLEX, 0.35, SEARCH_COLOUR, 1, cv2.LINE_AA)
    if search.full is not None:
        text = "full search" if search.full == "done" else "full search deferred (time cap)"
        (tw, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
        draw_text(image, [text], origin_px=(max(8, w - tw - 8), 18), colour=SEARCH_COLOUR)
    return image
