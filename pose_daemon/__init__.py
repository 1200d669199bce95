"""pose-daemon: camera pose from the four corners of a known rectangle, for robots and drones.

The stable Python API (see docs/python-api.md): Camera, Marker, estimate_pose, estimate_pose_batch,
EstimationError, Pose, MarkerDetector.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from .camera import Camera, Marker
    from .pose.types import EstimationError, Pose

__version__ = "0.1.0"

__all__ = [
    "Camera",
    "Marker",
    "Pose",
    "EstimationError",
    "estimate_pose",
    "estimate_pose_batch",
    "MarkerDetector",
    "__version__",
]


def __getattr__(name: str) -> Any:
    # Imported on first use so that `pose-daemon --help` and tools stay light, and so that
    # `pose-daemon run` holds its stop signals before numpy and OpenCV load (startup.py).
    if name in ("Camera", "Marker"):
        from . import camera

        return getattr(camera, name)
    if name in ("EstimationError", "Pose"):
        from .pose import types

        return getattr(types, name)
    if name == "estimate_pose":
        from .pose.estimator import estimate_pose

        return estimate_pose
    if name == "estimate_pose_batch":
        from .pose.batch import estimate_pose_batch

        return estimate_pose_batch
    if name == "MarkerDetector":
        from .detect import MarkerDetector

        return MarkerDetector
    raise AttributeError(f"module 'pose_daemon' has no attribute {name!r}")
