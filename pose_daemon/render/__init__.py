"""The renderer: camera frames of a marker or a whole map at a known pose, with a real camera's
effects, and the trajectories the synthetic source follows."""

from .scene import (
    TRAJECTORIES,
    TRAJECTORY_MOUNTS,
    Effects,
    RenderedFrame,
    Trajectory,
    TruePose,
    aruco_texture,
    make_background,
    marker_texture_grid,
    random_pose,
    render_empty,
    render_frame,
    render_marker,
    render_plane,
    trajectory,
)

__all__ = [
    "Effects",
    "RenderedFrame",
    "TruePose",
    "render_marker",
    "render_plane",
    "render_empty",
    "render_frame",
    "aruco_texture",
    "make_background",
    "marker_texture_grid",
    "trajectory",
    "Trajectory",
    "random_pose",
    "TRAJECTORIES",
    "TRAJECTORY_MOUNTS",
]
