"""The scenes of ``pose-daemon bench detector``: the main rows' varied backgrounds and lighting,
and the cluttered backgrounds that make a whole-frame search hard."""

from __future__ import annotations

import cv2
import numpy as np

from ...render import Effects


def scene_effects(rng: np.random.Generator):

    # Varied scenes: mostly textured backgrounds, some plain; lighting from even to strong.
    plain = rng.random() < 0.25
    return Effects(
        blur_px=0.8,
        noise_gray=2.0,
        background="plain" if plain else "texture",
        plain_gray=float(rng.uniform(60.0, 200.0)),
        lighting_gradient=float(rng.uniform(0.0, 0.6)),
    )


CLUTTER_SCENES = ("carpet", "board", "text", "rectangles")


def clutter_background(kind: str, rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """A cluttered background (height, width) float32 grey levels, the hard cases of a
    whole-frame search: "carpet" (strong blotchy texture, dark blobs everywhere), "board"
    (a board of many dark squares, seen in perspective), "text" (a page of dark print) and
    "rectangles" (many dark rectangles on light surrounds: posters, notes, windows)."""
    if kind == "carpet":
        field = np.zeros((height, width), np.float32)
        for cells, weight in ((6, 0.6), (20, 1.0), (60, 0.8), (160, 0.5)):
            grid = rng.random((max(2, cells * height // width), cells), dtype=np.float32)
            field += weight * cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC)
        field = (field - field.mean()) / max(float(field.std()), 1e-6)
        # A steep curve: dark blobs with sharp-ish rims on a light pile, and the speckle between.
        blob = 1.0 / (1.0 + np.exp(-3.0 * field))
        return (30.0 + 180.0 * blob).astype(np.float32)
    if kind == "board":
        out = np.full((height, width), float(rng.uniform(150, 200)), np.float32)
        n = int(rng.integers(6, 10))
        cell = float(rng.uniform(0.6, 0.9)) * min(width, height) / n
        board = np.full((int(n * cell) + 8, int(n * cell) + 8), 235.0, np.float32)
        for r in range(n):
            for c in range(n):
                y0, x0 = int(4 + r * cell), int(4 + c * cell)
                if (r + c) % 2 == 0:
                    board[y0 : int(4 + (r + 1) * cell), x0 : int(4 + (c + 1) * cell)] = 30.0
                else:
                    # A ChArUco board: a marker-like dark square in every white one.
                    m0, m1 = int(0.2 * cell), int(0.8 * cell)
                    board[y0 + m0 : y0 + m1, x0 + m0 : x0 + m1] = 30.0
                    k = max(1, int(0.12 * cell))
                    for _ in range(3):
                        py, px = rng.integers(m0 + k, m1 - 2 * k, 2)
                        board[y0 + py : y0 + py + k, x0 + px : x0 + px + k] = 235.0
        h, w = board.shape
        src = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float32)
        jitter = rng.uniform(-0.12, 0.12, (4, 2)) * [width, height]
        left, top = rng.uniform(0, width - w * 0.8), rng.uniform(0, height - h * 0.8)
        dst = (src * 0.9 + [left, top] + jitter).astype(np.float32)
        H = cv2.getPerspectiveTransform(src, dst)
        warped = cv2.warpPerspective(board, H, (width, height), flags=cv2.INTER_AREA, borderValue=-1.0)
        mask = warped >= 0
        out[mask] = warped[mask]
        return out
    if kind == "text":
        page = np.full((height, width), float(rng.uniform(190, 235)), np.uint8)
        y = int(rng.integers(12, 24))
        letters = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789.,;:-"
        while y < height:
            scale = float(rng.uniform(0.4, 1.3))
            thickness = int(rng.integers(1, 3))
            line = "".join(rng.choice(list(letters + "     "), size=60))
            font = int(rng.choice([cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX]))
            cv2.putText(
                page,
                line,
                (int(rng.integers(-20, 10)), y),
                font,
                scale,
                int(rng.uniform(10, 60)),
                thickness,
                cv2.LINE_AA,
            )
            y += int(30 * scale + rng.integers(4, 12))
        return page.astype(np.float32)
    if kind == "rectangles":
        out = np.full((height, width), float(rng.uniform(170, 230)), np.float32)
        for _ in range(int(rng.integers(25, 45))):
            w, h = rng.uniform(12, 90, 2)
            centre = (float(rng.uniform(0, width)), float(rng.uniform(0, height)))
            box = cv2.boxPoints((centre, (float(w), float(h)), float(rng.uniform(0, 90))))
            pts = np.round(box * 16).astype(np.int32)
            cv2.fillConvexPoly(out, pts, float(rng.uniform(15, 90)), cv2.LINE_AA, shift=4)
        return out
    raise ValueError(f"clutter scene must be one of {', '.join(CLUTTER_SCENES)}, got {kind!r}")


def clutter_effects(rng: np.random.Generator):

    return Effects(blur_px=0.8, noise_gray=2.0, lighting_gradient=float(rng.uniform(0.0, 0.4)))
