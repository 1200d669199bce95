"""Camera calibration from views of a chessboard or ChArUco board (``pose-daemon calibrate``):
board.py describes, finds and draws the board; collect.py gathers the views and their coverage;
fit.py runs OpenCV's calibrateCamera robustly and reports; camera_section.py writes the
[camera] section; run.py is the command's flow."""

from .board import (
    BOARD_KINDS,
    BOARD_SYNTAX,
    BoardDetector,
    BoardSpec,
    BoardView,
    board_image,
    board_image_size_m,
    parse_board,
)
from .camera_section import CAMERA_KEYS, camera_toml, camera_values, update_camera_text, update_config_file
from .collect import (
    COVERAGE_GRID,
    STATUS_INTERVAL_S,
    Coverage,
    ViewSelector,
    view_signature,
    views_from_path,
    views_from_source,
    views_live,
)
from .fit import (
    CORNER_FACTOR,
    CORNER_FLOOR_PX,
    MIN_VIEWS,
    OUTLIER_FACTOR,
    OUTLIER_FLOOR_PX,
    ROBUST_ROUNDS,
    VIEW_REJECT_SHARE,
    CalibrationResult,
    calibrate_views,
    distortion_difference_px,
    refuse_too_few,
    report,
)
from .response import SHOULDER_GRID, ResponseMeasurement, fit_response, measure_response
from .run import DEFAULT_MIN_COVERAGE, run_calibration

__all__ = [
    "BOARD_KINDS",
    "BOARD_SYNTAX",
    "BoardDetector",
    "BoardSpec",
    "BoardView",
    "CAMERA_KEYS",
    "CORNER_FACTOR",
    "CORNER_FLOOR_PX",
    "COVERAGE_GRID",
    "CalibrationResult",
    "Coverage",
    "DEFAULT_MIN_COVERAGE",
    "MIN_VIEWS",
    "OUTLIER_FACTOR",
    "OUTLIER_FLOOR_PX",
    "ROBUST_ROUNDS",
    "ResponseMeasurement",
    "SHOULDER_GRID",
    "STATUS_INTERVAL_S",
    "VIEW_REJECT_SHARE",
    "ViewSelector",
    "board_image",
    "board_image_size_m",
    "calibrate_views",
    "camera_toml",
    "camera_values",
    "distortion_difference_px",
    "fit_response",
    "measure_response",
    "parse_board",
    "refuse_too_few",
    "report",
    "run_calibration",
    "update_camera_text",
    "update_config_file",
    "view_signature",
    "views_from_path",
    "views_from_source",
    "views_live",
]
