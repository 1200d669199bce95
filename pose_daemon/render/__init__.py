"""The renderer: camera frames of a marker or a whole map at a known pose, with a real camera's
effects, and the trajectories the synthetic source follows."""

from .effects import Effects, make_background
from .poses import (
    TRAJECTORIES,
    TRAJECTORY_MOUNTS,
    Trajectory,
    TruePose,
    facing_pose,
    inside_image,
    random_pose,
    trajectory,
)
from .scene import (
    RenderedFrame,
    aruco_texture,
    prepare_marker,
    render_empty,
    render_frame,
    render_marker,
    render_plane,
)
from .texture import marker_texture_grid

__all__ = [
    "Effects",
    "RenderedFrame",
    "TruePose",
    "render_marker",
    "render_plane",
    "render_empty",
    "render_frame",
    "aruco_texture",
    "prepare_marker",
    "make_background",
    "marker_texture_grid",
    "trajectory",
    "Trajectory",
    "random_pose",
    "facing_pose",
    "inside_image",
    "TRAJECTORIES",
    "TRAJECTORY_MOUNTS",
]
