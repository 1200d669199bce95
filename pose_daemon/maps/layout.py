"""``pose-daemon map import``'s library half: a WPILib / PhotonVision AprilTag field layout
(JSON) written as a map file ([map] + [[map.markers]], every number exact)."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Optional, TextIO

from ..errors import UserError
from ..map_layout import LAYOUT_DICTIONARY, LayoutError, layout_tables, read_layout_file
from ..marker_map import MapError, MarkerMap, markers_from_tables


def layout_map(layout: Path, size_m: float, dictionary: str = LAYOUT_DICTIONARY) -> MarkerMap:
    """The layout's tags as a MarkerMap (placement floor: the field's z is up); UserError naming
    the file and the entry."""
    from ..detect import aruco_compat

    if not (math.isfinite(size_m) and 0.0 < size_m <= 100.0):
        raise UserError(f"--size: expected the tags' size in (0, 100] metres, got {size_m}")
    try:
        n_ids = aruco_compat.dictionary_size(aruco_compat.get_dictionary(dictionary))
    except ValueError:
        raise UserError(
            f"--dictionary: expected an OpenCV ArUco or AprilTag dictionary name such as "
            f'"DICT_APRILTAG_36h11", got {dictionary!r}'
        ) from None
    try:
        tables = layout_tables(read_layout_file(layout), size_m, dictionary)
        markers = markers_from_tables(tables, n_ids, dictionary, prefix="tags")
    except LayoutError as exc:
        raise UserError(f"{layout}: {exc}") from None
    except MapError as err:
        raise UserError(f"{layout}: {err.where} {err.key}: expected {err.expected}, got {err.got!r}") from None
    return MarkerMap(dictionary, markers, "floor")


def import_layout(
    layout: Path,
    out: Path,
    size_m: float,
    dictionary: str = LAYOUT_DICTIONARY,
    stream: Optional[TextIO] = None,
) -> MarkerMap:
    """``pose-daemon map import``: read ``layout``, write ``out``, say what was written."""
    from .survey import check_out

    stream = stream if stream is not None else sys.stdout
    check_out(out)
    marker_map = layout_map(layout, size_m, dictionary)
    lines = [
        f"# pose-daemon map import {layout.name}: {len(marker_map.markers)} tags of {size_m:g} m, {dictionary};",
        "# the map frame is the layout's field frame (x along the field, y left, z up)",
    ]
    lines += marker_map.to_toml_lines(exact=True)
    try:
        out.write_text("\n".join(lines))
    except OSError as exc:
        raise UserError(f"cannot write {out}: {exc.strerror or exc}") from None
    ids = ", ".join(str(i) for i in marker_map.ids)
    print(f"wrote {out}: {len(marker_map.markers)} tags ({ids}), {size_m:g} m, {dictionary}", file=stream)
    return marker_map
