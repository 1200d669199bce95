#!/usr/bin/env python3
"""Draw docs/marker-top.png: which printed edge of a marker is its top (corners 0 -> 1).

Three panels, each cut from the sheet `pose-daemon marker` prints (tools/marker_sheet) and
labelled where OpenCV's detector puts corners 0-3 on it: an ArUco marker (DICT_4X4_50 id 7),
an AprilTag as `pose-daemon marker` prints it (DICT_APRILTAG_36h11 id 7), and the same tag as
the official AprilTag images draw it (that print turned 180 deg).

Usage: python scripts/make_marker_top_figure.py [OUT.png]   (default: docs/marker-top.png)
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from pose_daemon.detect import aruco_compat
from pose_daemon.tools.marker_sheet import layout, to_image

PANEL_PX = 200
DPI = 300.0


def _panel(dictionary: str, marker_id: int, turn_180: bool, title: str) -> np.ndarray:
    sheet = layout("aruco", 0.04, dictionary=dictionary, marker_id=marker_id)
    page = to_image(sheet, DPI)
    found = aruco_compat.ArucoMarkerFinder(aruco_compat.get_dictionary(dictionary)).detect(page)
    corners = next(c for c, i in zip(*found) if int(i) == marker_id).reshape(4, 2)
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    pad = 0.3 * float((hi - lo).max())
    x0, y0 = np.maximum(lo - pad, 0).astype(int)
    x1, y1 = np.minimum(hi + pad, [page.shape[1], page.shape[0]]).astype(int)
    crop = page[y0:y1, x0:x1]
    scale = PANEL_PX / crop.shape[1]
    img = cv2.resize(crop, (PANEL_PX, int(round(crop.shape[0] * scale))), interpolation=cv2.INTER_AREA)
    pts = (corners - [x0, y0]) * scale
    if turn_180:
        img = img[::-1, ::-1]
        pts = np.array([img.shape[1] - 1, img.shape[0] - 1]) - pts
    out = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_GRAY2BGR)
    red, blue = (40, 40, 220), (200, 90, 20)
    p = pts.astype(int)
    cv2.line(out, tuple(p[0]), tuple(p[1]), red, 4)  # the top edge: corners 0 -> 1
    centre = pts.mean(axis=0)
    for k, q in enumerate(pts):
        d = (q - centre) / np.linalg.norm(q - centre)
        pos = (q + d * 18 + [-6, 6]).astype(int)
        cv2.circle(out, tuple(q.astype(int)), 5, blue, -1)
        cv2.putText(out, str(k), tuple(pos), cv2.FONT_HERSHEY_SIMPLEX, 0.6, blue, 2, cv2.LINE_AA)
    band = np.full((46, out.shape[1], 3), 255, np.uint8)
    for row, text in enumerate(title.split("\n")):
        cv2.putText(band, text, (6, 18 + 20 * row), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([band, out])


def main() -> int:
    default = Path(__file__).resolve().parent.parent / "docs" / "marker-top.png"
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else default
    panels = [
        _panel("DICT_4X4_50", 7, False, "ArUco DICT_4X4_50 id 7\n(pose-daemon marker)"),
        _panel("DICT_APRILTAG_36h11", 7, False, "AprilTag 36h11 id 7\n(pose-daemon marker)"),
        _panel("DICT_APRILTAG_36h11", 7, True, "AprilTag 36h11 id 7\n(official image, FRC)"),
    ]
    h = max(p.shape[0] for p in panels)
    panels = [np.vstack([p, np.full((h - p.shape[0], p.shape[1], 3), 255, np.uint8)]) for p in panels]
    gap = np.full((h, 12, 3), 255, np.uint8)
    figure = np.hstack([panels[0], gap, panels[1], gap, panels[2]])
    ok, png = cv2.imencode(".png", figure, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise SystemExit("cannot encode the figure")
    out.write_bytes(png.tobytes())
    print(f"wrote {out} ({len(png)} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
