"""MapDecoder: a quadrilateral's cells read once and matched against every id of a marker map
(the whole-frame search of MapDetector decodes each dark quadrilateral with it)."""

from __future__ import annotations

from typing import List, Optional, Tuple

import cv2
import numpy as np

from . import aruco_compat
from .square import UNIT_SQUARE, SquareOptions, median_of, sample_canonical, side_lengths


class MapDecoder:
    """Reads a quadrilateral's cells once and finds which map id (and rotation) it is."""

    def __init__(self, dictionary, ids: List[int], options: SquareOptions) -> None:
        self.options = options
        n = int(dictionary.markerSize)
        self.n_bits = n
        cells = n + 2
        centres = (np.arange(cells) + 0.5) / cells
        uu, vv = np.meshgrid(centres, centres)
        self.cell_uv = np.column_stack([uu.ravel(), vv.ravel()])
        s = np.linspace(0.1, 0.9, 7)
        ring = np.concatenate(
            [
                np.column_stack([s, np.full_like(s, -0.08)]),
                np.column_stack([np.full_like(s, 1.08), s]),
                np.column_stack([s, np.full_like(s, 1.08)]),
                np.column_stack([np.full_like(s, -0.08), s]),
            ]
        )
        self.uv = np.concatenate([self.cell_uv, ring])
        border = np.ones((cells, cells), dtype=bool)
        border[1:-1, 1:-1] = False
        self.border = border.ravel()
        self.inner = ~self.border
        self.max_bit_errors = int(getattr(dictionary, "maxCorrectionBits", 0))
        perms = []
        for k in range(4):
            H = cv2.getPerspectiveTransform(UNIT_SQUARE, np.roll(UNIT_SQUARE, -k, axis=0))
            uv = cv2.perspectiveTransform(self.cell_uv.reshape(-1, 1, 2), H).reshape(-1, 2)
            idx = np.floor(uv * cells).astype(int).clip(0, cells - 1)
            perms.append(idx[:, 1] * cells + idx[:, 0])
        self.perms = np.array(perms)
        expected = []
        for marker_id in ids:
            grid = np.zeros((cells, cells), dtype=bool)
            grid[1:-1, 1:-1] = aruco_compat.marker_bits(dictionary, marker_id).astype(bool)
            expected.append(grid.ravel()[self.inner])
        self.ids = np.array(ids, dtype=np.int64)
        self.expected = np.array(expected)  # (n_ids, n*n)

    def decode(self, gray: np.ndarray, fit) -> Optional[Tuple[int, int]]:
        """(id, k) with the corners rolled by k starting at the marker's top-left, or None."""
        o = self.options
        if fit.residual_px > o.max_edge_residual_px or fit.valid_fraction < 0.6:
            return None
        if fit.contrast < o.min_contrast or side_lengths(fit.corners).min() < o.min_side_px:
            return None
        values = sample_canonical(gray, fit.corners, self.uv)
        n_cells = len(self.cell_uv)
        cells, ring = values[:n_cells], values[n_cells:]
        ring = ring[np.isfinite(ring)]
        if not np.isfinite(cells).all() or len(ring) < 10:
            return None
        dark, light = median_of(cells[self.border]), median_of(ring)
        if light - dark < o.min_contrast:
            return None
        white = cells > 0.5 * (dark + light)
        if np.count_nonzero(white[self.border]) > 1:
            return None
        read = white[self.perms][:, self.inner]  # (4, n*n): the grid as each rotation reads it
        errors = (read[:, None, :] != self.expected[None, :, :]).sum(axis=2)  # (4, n_ids)
        k, j = np.unravel_index(int(np.argmin(errors)), errors.shape)
        if errors[k, j] > self.max_bit_errors:
            return None
        return int(self.ids[j]), int(k)
