"""``pose-daemon bench detector``: the corner detector against OpenCV's ArUco detector + IPPE.

On the same rendered 640x480 frames, in one run: detection rate, corner error, pose error,
false detections on marker-free frames, and time per frame (detect + estimate) for a
tracked marker and for a whole-frame search, with the Pi 2 equivalent (x20).
"""

from .blur import BLUR_SWEEP, run_blur_sweep
from .clutter import run_clutter
from .run import print_report, run_bench, run_sweep_bench
from .scenes import CLUTTER_SCENES, clutter_background
from .viewsweep import run_view_sweep

__all__ = [
    "BLUR_SWEEP",
    "CLUTTER_SCENES",
    "clutter_background",
    "print_report",
    "run_blur_sweep",
    "run_bench",
    "run_clutter",
    "run_sweep_bench",
    "run_view_sweep",
]
