"""The nested landing pad: a large marker with a small one inside its white centre, as one map,
and its printable sheet."""

from __future__ import annotations

import math
from typing import Optional

from ..detect import aruco_compat
from ..errors import UserError
from ..marker_map import MapMarker, MarkerMap
from ..tools.marker_sheet import DEFAULT_DICTIONARY, Sheet, Text, aruco_cells, layout, white_runs

__all__ = ["landing_pad", "pad_layout"]


def landing_pad(
    dictionary: str = "DICT_4X4_50",
    outer_m: float = 0.6,
    inner_m: Optional[float] = None,
    outer_id: Optional[int] = None,
    inner_id: Optional[int] = None,
) -> MarkerMap:
    """A nested pad centred on the map origin (the landing point): a large marker whose four
    centre bits are white, and a small marker inside that white square.

    The small one fits inside the white centre with the large marker's cell centres left
    white (its side is 0.6 of a cell); it carries the pose near the ground, the large one
    from altitude, and both are one map, so there is no switch.
    """
    d = aruco_compat.get_dictionary(dictionary)
    n = int(d.markerSize)
    if n % 2:
        raise ValueError(f"a nested pad needs an even marker size (4x4, 6x6 ...), {dictionary} has {n}x{n} bits")
    cells = n + 2
    cell_m = outer_m / cells
    if inner_m is None:
        inner_m = round(0.6 * cell_m, 6)  # leaves the outer marker's cell centres white
    if not inner_m <= 0.6 * cell_m + 1e-12:
        raise ValueError(f"the inner marker must be at most 0.6 of an outer cell ({0.6 * cell_m:.3f} m)")
    c0, c1 = n // 2 - 1, n // 2 + 1
    candidates = [
        i for i in range(aruco_compat.dictionary_size(d)) if aruco_compat.marker_bits(d, i)[c0:c1, c0:c1].all()
    ]
    if outer_id is None:
        if not candidates:
            raise ValueError(f"no marker of {dictionary} has its centre bits white")
        outer_id = candidates[0]
    elif outer_id not in candidates:
        raise ValueError(
            f"marker {outer_id} of {dictionary} does not have its four centre bits white; "
            f"choose one of {candidates[:10]}"
        )
    if inner_id is None:
        inner_id = next(i for i in range(aruco_compat.dictionary_size(d)) if i != outer_id)
    if inner_id == outer_id:
        raise ValueError("the inner and the outer marker need different ids")
    return MarkerMap(
        dictionary, (MapMarker(int(outer_id), float(outer_m)), MapMarker(int(inner_id), float(inner_m))), "floor"
    )


def pad_layout(
    size_m: float, *, dictionary: Optional[str] = None, outer_id: Optional[int] = None, paper: str = "a4"
) -> Sheet:
    """The nested landing pad (marker_map.landing_pad) on one sheet: the outer marker as
    ``layout`` places it, the inner marker drawn inside its white centre; ``config`` holds the
    matching [map] lines. UserError when the outer marker does not fit on the paper."""
    dictionary = (dictionary or DEFAULT_DICTIONARY).strip().upper()
    if not (isinstance(size_m, (int, float)) and math.isfinite(size_m) and size_m > 0):
        raise UserError(f"--size must be a positive number of metres, got {size_m}")
    try:
        pad = landing_pad(dictionary, outer_m=float(size_m), outer_id=outer_id)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    outer, inner = pad.markers
    sheet = layout("aruco", outer.size_m, dictionary=dictionary, marker_id=outer.id, paper=paper)
    x0, y0, side_mm, _ = sheet.marker_rect
    inner_mm = inner.size_m * 1000.0
    ix, iy = x0 + (side_mm - inner_mm) / 2.0, y0 + (side_mm - inner_mm) / 2.0
    cells = aruco_cells(dictionary, inner.id)
    cell_mm = inner_mm / cells.shape[0]
    sheet.fills.append((0.0, [(ix, iy, inner_mm, inner_mm)]))
    sheet.fills.append(
        (1.0, [(ix + c * cell_mm, iy + r * cell_mm, n * cell_mm, cell_mm) for r, c, n in white_runs(cells)])
    )
    # The caption's [marker] lines become a pointer to the [map] lines (printed with the sheet).
    mono = [t for t in sheet.texts if t.mono]
    for t in mono:
        sheet.texts.remove(t)
    if mono:
        sheet.texts.append(
            Text(
                mono[0].x_mm,
                mono[0].y_mm,
                f"landing pad: outer id {outer.id} ({outer.size_m * 1000:g} mm), inner id "
                f"{inner.id} ({inner.size_m * 1000:.4g} mm), centres together; [map] lines "
                "printed by pose-daemon marker --pad",
                size_pt=7.0,
            )
        )
    sheet.config = pad.to_toml_lines()
    while sheet.config and not sheet.config[-1]:
        sheet.config.pop()
    return sheet
