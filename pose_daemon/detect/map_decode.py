"""MapDecoder: a quadrilateral's cells read once and matched against every id of a marker map
(the whole-frame search of MapDetector decodes each dark quadrilateral with it)."""

from __future__ import annotations

from typing import List, Optional, Tuple

import numpy as np

from . import aruco_compat
from .aruco import CellGrid
from .square import SquareOptions


class MapDecoder:
    """Reads a quadrilateral's cells once and finds which map id (and rotation) it is."""

    def __init__(self, dictionary, ids: List[int], options: SquareOptions) -> None:
        self.options = options
        n = int(dictionary.markerSize)
        self.n_bits = n
        self.grid = CellGrid(n)
        self.max_bit_errors = int(getattr(dictionary, "maxCorrectionBits", 0))
        cells = n + 2
        inner = self.grid.inner
        expected = []
        for marker_id in ids:
            code = np.zeros((cells, cells), dtype=bool)
            code[1:-1, 1:-1] = aruco_compat.marker_bits(dictionary, marker_id).astype(bool)
            expected.append(code.ravel()[inner])
        self.ids = np.array(ids, dtype=np.int64)
        self.expected = np.array(expected)  # (n_ids, n*n)

    def decode(self, gray: np.ndarray, fit) -> Optional[Tuple[int, int]]:
        """(id, k) with the corners rolled by k starting at the marker's top-left, or None."""
        grid = self.grid
        white = grid.read_fit(gray, fit, self.options)
        if white is None:
            return None
        read = white[grid.perms][:, grid.inner]  # (4, n*n): the grid as each rotation reads it
        errors = (read[:, None, :] != self.expected[None, :, :]).sum(axis=2)  # (4, n_ids)
        k, j = np.unravel_index(int(np.argmin(errors)), errors.shape)
        if errors[k, j] > self.max_bit_errors:
            return None
        return int(self.ids[j]), int(k)
