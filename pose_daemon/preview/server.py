"""PreviewServer: the preview's HTTP server (standard library only), in its own threads.

One thread accepts connections (``ThreadingHTTPServer``), one per request serves it. A
viewer of /stream.mjpg gets the newest annotated frame at most ``max_fps`` times a second;
frames it had no time for are skipped (newest wins, counted), the JPEG of a frame is made
once for every viewer, and a viewer that stops reading is dropped once a send has waited
SEND_TIMEOUT_S. Nothing is annotated or encoded while nobody watches.
"""

from __future__ import annotations

import collections
import ipaddress
import json
import logging
import math
import select
import socket
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, Callable, Deque, Dict, List, Optional, Tuple
from urllib.parse import parse_qs, urlsplit

import cv2

from ..attitude import attitude_connection
from ..errors import PoseDaemonError
from ..pipeline import STAGES, summarize_ms
from .page import PAGE_HTML
from .recorder import MAX_SECONDS, Recorder, save_snapshot, unique_path, utc_stamp
from .tap import FrameTap, Tapped
from .warnings import Context, evaluate

log = logging.getLogger("pose_daemon.preview")

# A viewer whose socket takes no bytes for this long is dropped.
SEND_TIMEOUT_S = 2.0
# Kernel send buffer of a stream connection: bounds what a stalled viewer holds (a few frames).
STREAM_SNDBUF = 128 * 1024
JPEG_QUALITY = 80
# Seconds of poses in /history.json (the page's plot).
HISTORY_S = 10.0
# A POST must carry this header: a page of another site cannot add it without the browser
# first asking (CORS preflight), which this server never grants.
ACTION_HEADER = "X-Pose-Daemon"


class PreviewError(PoseDaemonError):
    """The preview cannot listen where it was told to."""


class _HTTPServer(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True
    preview: PreviewServer

    def __init__(self, address: Tuple[str, int], handler, family: int) -> None:
        self.address_family = family
        super().__init__(address, handler)


class PreviewServer:
    """Serves the page and its data for ``pipeline`` (a Pipeline) fed by ``tap`` (a FrameTap).

    ``cfg``: the Config ([preview], [camera], [marker], [detector]); ``clock``: monotonic seconds.
    """

    def __init__(self, cfg, pipeline, tap: FrameTap, *, clock: Callable[[], float] = time.monotonic) -> None:
        if cfg.preview is None:
            raise ValueError("PreviewServer needs a [preview] section")
        self.cfg = cfg
        self.pcfg = cfg.preview
        self.pipeline = pipeline
        self.tap = tap
        self.clock = clock
        self.camera = cfg.camera.model()
        self.marker = cfg.marker.model()
        self.data_dir = Path(self.pcfg.data_dir)
        self._period_s = 1.0 / self.pcfg.max_fps
        self._stopping = threading.Event()
        self._lock = threading.Lock()
        # Viewers' stream loops still running: stop() waits for them, so counts read after it
        # are final (a frame encoded is also counted sent, or its write failed).
        self._streams_done = threading.Condition(self._lock)
        self._streams = 0
        self._encode_lock = threading.Lock()
        self._encoded: Optional[Tuple[Tapped, bytes]] = None
        self._warnings_cache: Tuple[float, List[Any]] = (-1e18, [])
        self._samples: Deque[Tuple[float, Dict[str, Any]]] = collections.deque()
        self._t_progress: Optional[float] = None
        self._processed_seen = -1
        self._t_start = clock()
        self.recorder: Optional[Recorder] = None
        self.counts = {
            "viewers": 0,
            "frames_sent": 0,
            "frames_skipped": 0,
            "viewers_dropped": 0,
            "encoded": 0,
            "snapshots": 0,
            "recordings": 0,
        }
        # CPU time (thread time) the viewers' threads spent annotating, encoding and sending.
        self.stream_cpu_s = 0.0
        self.encode_s: Optional[float] = None
        host, port = self.pcfg.address
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
            family, _, _, _, sockaddr = infos[0]
            self._httpd = _HTTPServer(sockaddr[:2], _Handler, family)
        except OSError as exc:
            raise PreviewError(f"preview: cannot listen on {self.pcfg.listen}: {exc.strerror or exc}") from None
        self._httpd.preview = self
        self._thread = threading.Thread(
            target=self._httpd.serve_forever, kwargs={"poll_interval": 0.1}, name="preview-http", daemon=True
        )

    # ----------------------------------------------------------------- control

    @property
    def port(self) -> int:
        return int(self._httpd.server_address[1])

    @property
    def url(self) -> str:
        host = self._httpd.server_address[0]
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port}/"

    def start(self) -> None:
        self._thread.start()
        log.info("preview on %s (max %g fps, %d px wide)", self.url, self.pcfg.max_fps, self.pcfg.max_width)

    def stop(self, timeout_s: float = 0.5) -> None:
        """Stop serving; a recording is finished. Waits up to ``timeout_s`` for the viewers'
        stream loops to end (within a frame period, or the write under way)."""
        self._stopping.set()
        self.tap.wake()
        if self._thread.is_alive():
            self._httpd.shutdown()
        self._httpd.server_close()
        self._thread.join(timeout_s)
        with self._streams_done:
            self._streams_done.wait_for(lambda: self._streams == 0, timeout_s)
        rec = self.recorder
        if rec is not None:
            rec.stop()
            rec.join(timeout_s)
            self.tap.recorder = None

    @property
    def stopping(self) -> bool:
        return self._stopping.is_set()

    def count(self, what: str, n: int = 1) -> None:
        with self._lock:
            self.counts[what] += n

    # ----------------------------------------------------------------- frames

    def jpeg(self, item: Tapped) -> bytes:
        """The annotated JPEG of ``item``, made once however many viewers want it."""
        with self._encode_lock:
            cached = self._encoded
            if cached is not None and cached[0] is item:
                return cached[1]
            t0 = time.perf_counter()
            data = self._render(item)
            self.encode_s = time.perf_counter() - t0
            self._encoded = (item, data)
            self.count("encoded")
            return data

    def _render(self, item: Tapped) -> bytes:
        from ..draw import annotate_live

        texts = [w.text for w in self.warnings()]
        image = annotate_live(
            item.frame.image,
            item.result,
            self.camera,
            self.marker,
            detector_step=item.detector_step,
            search=item.search,
            warnings=texts,
        )
        h, w = image.shape[:2]
        if w > self.pcfg.max_width:
            scale = self.pcfg.max_width / w
            image = cv2.resize(image, (self.pcfg.max_width, max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise OSError("JPEG encoding failed")
        return buf.tobytes()

    # ----------------------------------------------------------------- figures

    def _outputs(self) -> List[Dict[str, Any]]:
        rows = []
        for out in self.pipeline.outputs:
            row: Dict[str, Any] = {"name": out.name, "state": self.pipeline.output_state(out)}
            stats = getattr(out, "stats", None)
            if callable(stats):
                try:
                    s = stats()
                except Exception as exc:  # an output's status must not break the page
                    s = {"link": f"stats failed: {exc}"}
                for key in ("link", "link_up", "sent", "dropped", "autopilot"):
                    if key in s:
                        row[key] = s[key]
            cfg = getattr(out, "cfg", None)  # the output's config table (MAVLink: wait_heartbeat)
            for key in ("wait_heartbeat", "connection"):
                if hasattr(cfg, key):
                    row[key] = getattr(cfg, key)
            if "autopilot" in row or hasattr(out, "autopilot_system"):
                row["autopilot"] = getattr(out, "autopilot_system", row.get("autopilot"))
            rows.append(row)
        return rows

    def _sample(self, now: float) -> Tuple[Dict[str, Any], Dict[str, Any], float]:
        """Totals now, and those of a few seconds ago (for rates and recent drops)."""
        snap = self.pipeline.stats.snapshot()
        with self._lock:
            if snap["processed"] != self._processed_seen:
                self._processed_seen = snap["processed"]
                self._t_progress = now
            if not self._samples or now - self._samples[-1][0] >= 0.5:
                self._samples.append((now, snap))
            while len(self._samples) > 2 and now - self._samples[1][0] >= 5.0:
                self._samples.popleft()
            t_old, old = self._samples[0]
        return snap, old, now - t_old

    def warnings(self) -> List[Any]:
        """The current warnings (worked out at most 4 times a second)."""
        now = self.clock()
        t, cached = self._warnings_cache
        if now - t < 0.25:
            return cached
        snap, old, _ = self._sample(now)
        recent = {k: v - old["drops"].get(k, 0) for k, v in snap["drops"].items()}
        ctx = Context(
            last=self.tap.latest,
            history=list(self.tap.history),
            source_state=self.pipeline.source_state,
            since_frame_s=None if self._t_progress is None else now - self._t_progress,
            recent_drops={k: v for k, v in recent.items() if v > 0},
            outputs=self._outputs(),
            min_side_px=self.cfg.detector.min_side_px,
            attitude_expected=attitude_connection(self.cfg) is not None,
            config_warnings=self.cfg.start_warnings(),
        )
        found = evaluate(ctx)
        self._warnings_cache = (now, found)
        return found

    def status(self) -> Dict[str, Any]:
        """The /status.json object: {"status": {...}, "last": per-frame JSON or None}."""
        now = self.clock()
        snap, _old, _dt = self._sample(now)  # the sample also notes progress (warnings)
        item = self.tap.latest
        history = list(self.tap.history)  # one C-level copy: the tap appends meanwhile
        recent = [r for r in history if item is not None and item.result.t_capture_s - r.t_capture_s <= 2.0]
        fps = None
        if len(recent) >= 2:
            span = recent[-1].t_capture_s - recent[0].t_capture_s
            fps = (len(recent) - 1) / span if span > 0 else None
        latency = {}
        for stage in STAGES:
            s = summarize_ms(self.pipeline.stats.window.values_s(stage))
            if s is not None:
                latency[stage] = [round(v, 3) for v in s]
        rec = self.recorder
        with self._lock:
            counts = dict(self.counts)
        line, rates = self.pipeline.status(reset=False)
        status = {
            "line": line,
            "fps": None if fps is None else round(fps, 2),
            # The status line's own figure (one owner): the two never disagree.
            "camera_fps": round(rates["camera_fps"], 2),
            "detected_pct": round(100.0 * sum(r.ok for r in recent) / len(recent), 1) if recent else None,
            "captured": snap["captured"],
            "frames": snap["processed"],
            "detected": snap["detected"],
            "drops": snap["drops"],
            "source": self.pipeline.source_state,
            "latency_ms": latency,
            "outputs": self._outputs(),
            "detector_step": item.detector_step if item is not None else None,
            "warnings": [w.to_dict() for w in self.warnings()],
            "preview": {
                **counts,
                "encode_ms": None if self.encode_s is None else round(self.encode_s * 1e3, 2),
                "stream_cpu_s": round(self.stream_cpu_s, 3),
                "max_fps": self.pcfg.max_fps,
                "max_width": self.pcfg.max_width,
            },
            "recording": rec.status() if rec is not None else None,
            "marker": {
                "type": self.marker.type,
                "id": self.marker.id,
                "dictionary": self.marker.dictionary,
                "width": self.marker.width,
                "height": self.marker.height,
            },
            "uptime_s": round(now - self._t_start, 1),
        }
        return {"status": status, "last": item.result.to_json_dict() if item is not None else None}

    def history(self) -> Dict[str, Any]:
        """The last HISTORY_S seconds of poses: t (s, relative to the newest frame), position
        (camera in marker frame, m) and the paper's angles (deg); null where no pose."""
        results = list(self.tap.history)
        if not results:
            return {"t": [], "x": [], "y": [], "z": [], "alpha": [], "beta": [], "gamma": []}
        t_end = results[-1].t_capture_s
        results = [r for r in results if t_end - r.t_capture_s <= HISTORY_S]
        out: Dict[str, List[Optional[float]]] = {k: [] for k in ("t", "x", "y", "z", "alpha", "beta", "gamma")}
        for r in results:
            out["t"].append(round(r.t_capture_s - t_end, 4))
            if r.pose is None:
                for k in ("x", "y", "z", "alpha", "beta", "gamma"):
                    out[k].append(None)
                continue
            pos = r.pose.camera_position
            for k, v in zip(("x", "y", "z"), pos):
                out[k].append(round(float(v), 4))
            for k in ("alpha", "beta", "gamma"):
                v = float(getattr(r.pose, f"{k}_deg"))
                out[k].append(round(v, 3) if math.isfinite(v) else None)
        return out

    # ----------------------------------------------------------------- actions

    def snapshot(self) -> Dict[str, Any]:
        item = self.tap.latest
        if item is None:
            raise _HttpError(HTTPStatus.CONFLICT, "no frame yet")
        try:
            path = save_snapshot(item.frame, self.data_dir / "snapshots")
        except OSError as exc:
            raise _HttpError(HTTPStatus.INTERNAL_SERVER_ERROR, f"cannot save the snapshot: {exc}") from None
        self.count("snapshots")
        log.info("preview: snapshot %s", path)
        return {"saved": str(path), "frame": item.seq}

    def record(self, seconds: float) -> Dict[str, Any]:
        if not (math.isfinite(seconds) and 0 < seconds <= MAX_SECONDS):
            raise _HttpError(HTTPStatus.BAD_REQUEST, f"seconds must be in (0, {MAX_SECONDS:g}]")
        with self._lock:
            rec = self.recorder
            if rec is not None and not rec.done.is_set():
                raise _HttpError(HTTPStatus.CONFLICT, f"already recording into {rec.path}")
            folder = self.data_dir / "recordings"
            path = unique_path(folder, f"rec-{utc_stamp()}")
            try:
                rec = Recorder(
                    path, self.camera, self.marker, seconds, source=self.cfg.camera.source, fps=self.cfg.camera.fps
                )
            except (OSError, PoseDaemonError) as exc:
                raise _HttpError(HTTPStatus.INTERNAL_SERVER_ERROR, f"cannot record: {exc}") from None
            self.recorder = rec
            self.counts["recordings"] += 1
        self.tap.recorder = rec
        log.info("preview: recording %g s into %s", seconds, path)
        return {"recording": str(path), "seconds": seconds}

    # ----------------------------------------------------------------- stream

    def stream(self, write: Callable[[bytes], Any], gone: Callable[[], bool] = lambda: False) -> None:
        """Feed one viewer until it goes away (``gone()``, or a write fails) or the server stops."""
        with self._lock:
            self._streams += 1
        try:
            self._feed(write, gone)
        finally:
            with self._streams_done:
                self._streams -= 1
                self._streams_done.notify_all()

    def _feed(self, write: Callable[[bytes], Any], gone: Callable[[], bool]) -> None:
        last: Optional[Tapped] = None
        next_s = self.clock()
        while not self.stopping and not gone():
            wait_s = next_s - self.clock()
            if wait_s > 0 and self._stopping.wait(wait_s):
                return
            item = self.tap.wait_newer(last, timeout_s=0.5)
            if item is None:
                continue
            if last is not None and item.seq > last.seq + 1:
                self.count("frames_skipped", item.seq - last.seq - 1)
            cpu0 = time.thread_time()
            data = self.jpeg(item)
            write(
                b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: "
                + str(len(data)).encode()
                + b"\r\n\r\n"
                + data
                + b"\r\n"
            )
            with self._lock:
                self.counts["frames_sent"] += 1
                self.stream_cpu_s += time.thread_time() - cpu0
            last = item
            next_s = max(next_s + self._period_s, self.clock() - self._period_s)


def host_allowed(host_header: Optional[str], listen_host: str) -> bool:
    """Whether a request's Host names this server as only a local or LAN client would: an IP
    address, "localhost", the configured host or an mDNS name (*.local). A web page whose
    domain was made to resolve to this address (DNS rebinding) sends its own domain instead,
    and must not see the camera or press the buttons."""
    if not host_header:
        return False
    host = host_header.strip().lower()
    if host.startswith("["):
        host = host[1:].split("]", 1)[0]
    elif host.count(":") == 1:
        host = host.split(":", 1)[0]
    try:
        ipaddress.ip_address(host)
        return True
    except ValueError:
        pass
    return host in ("localhost", listen_host.lower()) or host.endswith((".local", ".localhost"))


class _HttpError(Exception):
    def __init__(self, code: HTTPStatus, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


class _Handler(BaseHTTPRequestHandler):
    server: _HTTPServer
    server_version = "pose-daemon-preview"
    protocol_version = "HTTP/1.0"

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the base class's name
        log.debug("preview %s: %s", self.address_string(), format % args)

    def _send(self, code: int, body: bytes, content_type: str) -> None:
        self.send_response(code)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _json(self, obj: Any, code: int = 200) -> None:
        self._send(code, json.dumps(obj, allow_nan=False).encode(), "application/json")

    def _error(self, err: _HttpError) -> None:
        self._json({"error": err.message}, int(err.code))

    def _check_host(self, preview: PreviewServer) -> None:
        if not host_allowed(self.headers.get("Host"), preview.pcfg.address[0]):
            raise _HttpError(
                HTTPStatus.FORBIDDEN,
                f"unexpected Host {self.headers.get('Host')!r}: use the address the daemon listens on",
            )

    def do_GET(self) -> None:  # noqa: N802 - http.server's name
        preview = self.server.preview
        path = urlsplit(self.path).path
        self.connection.settimeout(SEND_TIMEOUT_S)
        try:
            self._check_host(preview)
            if path in ("/", "/index.html"):
                self._send(200, PAGE_HTML.encode(), "text/html; charset=utf-8")
            elif path == "/status.json":
                self._json(preview.status())
            elif path == "/history.json":
                self._json(preview.history())
            elif path == "/snapshot.jpg":
                item = preview.tap.latest
                if item is None:
                    raise _HttpError(HTTPStatus.SERVICE_UNAVAILABLE, "no frame yet")
                self._send(200, preview.jpeg(item), "image/jpeg")
            elif path == "/stream.mjpg":
                self._stream(preview)
            else:
                raise _HttpError(HTTPStatus.NOT_FOUND, f"no such page: {path}")
        except _HttpError as err:
            self._error(err)
        except (socket.timeout, ConnectionError, BrokenPipeError):
            pass  # the viewer went away or stopped reading

    def do_POST(self) -> None:  # noqa: N802
        preview = self.server.preview
        url = urlsplit(self.path)
        self.connection.settimeout(SEND_TIMEOUT_S)
        try:
            self._check_host(preview)
            if self.headers.get(ACTION_HEADER) != "1":
                raise _HttpError(HTTPStatus.FORBIDDEN, f"actions need the header {ACTION_HEADER}: 1")
            if url.path == "/snapshot":
                self._json(preview.snapshot())
            elif url.path == "/record":
                query = parse_qs(url.query)
                try:
                    seconds = float(query.get("seconds", [""])[0])
                except ValueError:
                    raise _HttpError(HTTPStatus.BAD_REQUEST, "record?seconds=N with a number N") from None
                self._json(preview.record(seconds))
            else:
                raise _HttpError(HTTPStatus.NOT_FOUND, f"no such action: {url.path}")
        except _HttpError as err:
            self._error(err)
        except (socket.timeout, ConnectionError, BrokenPipeError):
            pass

    def _peer_closed(self) -> bool:
        """True once the viewer closed its end (seen without a write: no frame may come)."""
        try:
            readable, _, _ = select.select([self.connection], [], [], 0)
            return bool(readable) and self.connection.recv(1, socket.MSG_PEEK) == b""
        except (OSError, ValueError):
            return True

    def _stream(self, preview: PreviewServer) -> None:
        self.connection.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, STREAM_SNDBUF)
        self.send_response(200)
        self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        preview.count("viewers")
        try:
            preview.stream(self.wfile.write, self._peer_closed)
        except socket.timeout:
            preview.count("viewers_dropped")
            log.info("preview: dropped a viewer that stopped reading (%s)", self.address_string())
        finally:
            preview.count("viewers", -1)


__all__ = ["PreviewError", "PreviewServer", "SEND_TIMEOUT_S"]
