"""Marker maps off the vehicle: surveying a map from a walk-through (survey.py, build.py),
checking it, the nested landing pad, and printing a map on sheets (tiles.py).

The map model the daemon flies with is marker_map.py; its detection and solve are
detect/multi.py and pose/map_solve.py, and the per-frame stage processing/map.py.
"""
