"""The live preview: a small web page served by the daemon (``[preview]`` in the config).

    GET /              the page (self-contained: inline script and style, works offline)
    GET /stream.mjpg   multipart MJPEG of annotated frames, at most ``max_fps``
    GET /snapshot.jpg  one annotated frame
    GET /status.json   {"status": {the status line's figures, warnings, ...}, "last": {per-frame JSON}}
    GET /history.json  the last seconds of poses (the page's plot)
    POST /snapshot     save the current frame (PNG) into ``data_dir``/snapshots
    POST /record?seconds=N   record N seconds (the recording format) into ``data_dir``/recordings

It costs the pipeline one reference handoff per frame (FrameTap); frames are annotated and
JPEG-encoded only while a viewer is connected, in the server's threads.
"""

from .server import PreviewError, PreviewServer
from .tap import FrameTap
from .warnings import RULES, Warning

__all__ = ["FrameTap", "PreviewError", "PreviewServer", "RULES", "Warning"]
