"""Pose outputs: MAVLink, plain serial lines, JSON lines."""
