"""The per-frame stage: a frame in, a FrameResult out (detect -> estimate -> choose -> gate),
for one marker (marker.py) or a marker map (map.py)."""
