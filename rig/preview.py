"""``lfrig camera preview``: a live view in the browser, for focusing, framing and exposure.

A grabber thread takes frames from the camera (:class:`rig.protocols.Camera`) at up to ``fps_max``
frames per second; for each it makes

- a JPEG for display: scaled to 8 bits against the camera's full scale (:func:`rig.snap.full_scale`),
  shrunk by an integer factor to at most ``view_max_px`` on its longer side, with the clipped pixels
  painted (red: a channel at the top of the range; blue: a channel at 0);
- the readouts: size, min/max, clipped fractions (:func:`rig.snap.frame_stats`), the focus measure
  (:func:`rig.snap.focus_measure`) on the chosen region, and a 256-bin histogram per channel.

A small HTTP server (standard library, one thread per client) serves the page ``/``, the MJPEG stream
``/stream.mjpg`` (``multipart/x-mixed-replace``), the latest frame ``/frame.jpg`` (for polling), the
readouts ``/stats.json``, and takes the focus region as ``POST /roi`` (JSON ``{"roi": [x0, y0, w, h]}``
in frame pixels, or ``{"roi": null}`` for the whole frame). It listens on 127.0.0.1 only unless told
otherwise, and then answers only requests addressed to 127.0.0.1 or localhost (a ``Host`` header of
another name is refused, so a web page cannot reach it by pointing its own name at 127.0.0.1): over SSH, forward the port (``ssh -L 8000:127.0.0.1:8000 bench-pc``) and open
``http://127.0.0.1:8000/`` on your machine.

Ctrl-C (SIGINT) stops the server and the grabber, closes the camera and frees the port.
"""

from __future__ import annotations

import errno
import json
import logging
import sys
import threading
import time
from dataclasses import asdict
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np

from rig.errors import RigError
from rig.snap import focus_measure, frame_stats, full_scale

log = logging.getLogger(__name__)

LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")
PAGE = Path(__file__).with_name("preview.html")
BOUNDARY = "lfrigframe"


def display_frame(image: np.ndarray, *, top: int, shrink: int) -> np.ndarray:
    """``(H, W)`` or ``(H, W, 3)`` frame -> ``(H // shrink, W // shrink, 3)`` uint8 RGB for display, with
    pixels that have a channel at ``top`` (or above) painted red and a channel at 0 painted blue."""
    view = image[::shrink, ::shrink]
    high = view >= top
    low = view == 0
    if view.ndim == 3:
        high, low = high.any(axis=2), low.any(axis=2)
    scaled = np.clip(view.astype(np.float32) * (255.0 / top), 0, 255).astype(np.uint8)
    rgb = np.repeat(scaled[:, :, None], 3, axis=2) if scaled.ndim == 2 else scaled[:, :, :3].copy()
    rgb[low] = (0, 64, 255)
    rgb[high] = (255, 0, 0)
    return rgb


def histogram(image: np.ndarray, *, top: int) -> list[list[int]]:
    """256-bin histograms, one per channel (grey: one), of the frame scaled to 0..255 against ``top``."""
    scaled = np.clip(image.astype(np.float64) * (256.0 / (top + 1)), 0, 255).astype(np.uint8)
    channels = [scaled] if scaled.ndim == 2 else [scaled[:, :, c] for c in range(scaled.shape[2])]
    return [np.bincount(c.ravel(), minlength=256).tolist() for c in channels]


def local_host_header(value: str | None) -> bool:
    """Whether an HTTP ``Host`` header names this machine's loopback (any port: an SSH forward may
    use another). Pages from other sites that resolve their name to 127.0.0.1 (DNS rebinding) send
    their own name and are refused."""
    if not value:
        return False
    host = value.strip().lower()
    if host.startswith("["):
        host = host[1:].partition("]")[0]
    else:
        host = host.rpartition(":")[0] if ":" in host else host
    return host in LOCAL_HOSTS


def check_roi(roi: Any, *, width: int, height: int) -> tuple[int, int, int, int] | None:
    """A focus region ``[x0, y0, w, h]`` in frame pixels, clipped to the frame; ``None``: the whole frame."""
    if roi is None:
        return None
    if (not isinstance(roi, (list, tuple)) or len(roi) != 4
            or not all(isinstance(v, (int, float)) and np.isfinite(v) for v in roi)):
        raise ValueError(f"roi must be [x0, y0, width, height] in pixels or null; got {roi!r}")
    x0, y0, w, h = (int(round(v)) for v in roi)
    x0, y0 = max(0, min(x0, width - 1)), max(0, min(y0, height - 1))
    w, h = max(1, min(w, width - x0)), max(1, min(h, height - y0))
    return (x0, y0, w, h)


class Preview:
    """The grabber and the shared latest frame; :meth:`serve` runs the HTTP server until Ctrl-C."""

    def __init__(self, camera: Any, *, roi: tuple[int, int, int, int] | None = None, fps_max: float = 10.0,
                 view_max_px: int = 1024, jpeg_quality: int = 85, any_host: bool = False) -> None:
        self.camera = camera
        self.any_host = any_host  # answer requests whatever their Host header (--allow-remote)
        self.roi = roi
        self.fps_max = fps_max
        self.view_max_px = view_max_px
        self.jpeg_quality = jpeg_quality
        self.stop_event = threading.Event()
        self._cond = threading.Condition()
        self.frame_number = 0
        self.jpeg: bytes | None = None
        self.stats: dict[str, Any] = {"frame": 0}
        self.error: str | None = None
        self._thread = threading.Thread(target=self._grab_loop, name="preview-grabber", daemon=True)

    # -- the grabber
    def _grab_loop(self) -> None:
        settings = self.camera.settings()
        period = 1.0 / self.fps_max
        while not self.stop_event.is_set():
            started = time.monotonic()
            try:
                image = self.camera.trigger()
            except Exception as error:  # shown on the page and ends the preview with a one-line error
                with self._cond:
                    self.error = f"the camera stopped delivering frames: {error}"
                    self._cond.notify_all()
                return
            self._publish(image, settings)
            self.stop_event.wait(max(0.0, period - (time.monotonic() - started)))

    def _publish(self, image: np.ndarray, settings: dict[str, Any]) -> None:
        top = full_scale(image, settings)
        height, width = image.shape[:2]
        shrink = max(1, -(-max(width, height) // self.view_max_px))
        view = display_frame(image, top=top, shrink=shrink)
        ok, encoded = cv2.imencode(".jpg", np.ascontiguousarray(view[:, :, ::-1]),
                                   [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            raise RigError("OpenCV could not encode the preview frame as JPEG")
        roi = check_roi(self.roi, width=width, height=height)
        stats = asdict(frame_stats(image, top=top))
        stats.update(frame=self.frame_number + 1, roi=roi, focus=focus_measure(image, top=top, roi=roi),
                     histogram=histogram(image, top=top), shrink=shrink, time=time.time())
        with self._cond:
            self.frame_number += 1
            self.jpeg = encoded.tobytes()
            self.stats = stats
            self._cond.notify_all()

    def next_frame(self, after: int, *, timeout_s: float = 1.0) -> tuple[int, bytes | None]:
        """Wait for a frame newer than number ``after``; returns ``(number, jpeg)`` (the old one on timeout)."""
        with self._cond:
            self._cond.wait_for(lambda: self.frame_number > after or self.stop_event.is_set() or self.error,
                                timeout=timeout_s)
            return self.frame_number, self.jpeg

    def set_roi(self, roi: Any) -> tuple[int, int, int, int] | None:
        width, height = self.stats.get("width"), self.stats.get("height")
        if width is None:
            raise ValueError("no frame yet; try again")
        self.roi = check_roi(roi, width=width, height=height)
        return self.roi

    # -- the server
    def bind(self, *, host: str, port: int) -> ThreadingHTTPServer:
        """The HTTP server on ``host:port`` (``port`` 0: a free one), or a one-line :class:`RigError`."""
        preview = self

        class Handler(_Handler):
            owner = preview

        class Server(_Server):
            owner = preview

        try:
            server = Server((host, port), Handler)
        except OSError as error:
            if error.errno == errno.EADDRINUSE:
                raise RigError(f"--port {port}: already in use on {host}; choose another port "
                               "(--port 0 picks a free one)") from None
            if error.errno in (errno.EADDRNOTAVAIL, errno.EACCES):
                raise RigError(f"--host {host} --port {port}: cannot listen there ({error.strerror}); "
                               "use 127.0.0.1 and a port above 1023") from None
            raise
        server.daemon_threads = True
        return server

    def serve(self, server: ThreadingHTTPServer, *, on_ready: Callable[[str], None] = print) -> None:
        """Grab and serve until Ctrl-C or a camera error; always stops the grabber and frees the port
        (the camera is closed by its owner)."""
        self._thread.start()
        host, port = server.server_address[:2]
        watcher = threading.Thread(target=self._stop_on_error, args=(server,), daemon=True)
        watcher.start()
        try:
            on_ready(f"http://{host}:{port}/")
            server.serve_forever(poll_interval=0.2)
        finally:
            self.stop_event.set()
            with self._cond:
                self._cond.notify_all()
            server.server_close()
            self._thread.join(timeout=10.0)
        if self.error:
            raise RigError(self.error)

    def _stop_on_error(self, server: ThreadingHTTPServer) -> None:
        with self._cond:
            self._cond.wait_for(lambda: self.error is not None or self.stop_event.is_set())
        if self.error is not None:
            server.shutdown()


class _Server(ThreadingHTTPServer):
    """The preview's HTTP server: a request that fails because its viewer went away, or while the
    preview stops, is not an error worth a traceback on the terminal (socketserver prints one)."""

    owner: Preview

    def handle_error(self, request: Any, client_address: Any) -> None:
        error = sys.exc_info()[1]
        if self.owner.stop_event.is_set() or isinstance(error, (ConnectionError, TimeoutError)):
            return
        log.warning("preview: a request from %s failed: %s", client_address[0], error)


class _Handler(BaseHTTPRequestHandler):
    owner: Preview
    server_version = "lfrig-preview"

    def log_message(self, format: str, *args: Any) -> None:  # no access log on the terminal
        pass

    def _send(self, body: bytes, content_type: str, status: HTTPStatus = HTTPStatus.OK) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _refused(self) -> bool:
        if self.owner.any_host or local_host_header(self.headers.get("Host")):
            return False
        self._send(b"this preview answers requests for 127.0.0.1 or localhost only", "text/plain", HTTPStatus.FORBIDDEN)
        return True

    def do_GET(self) -> None:  # noqa: N802 (http.server's name)
        if self._refused():
            return
        path = self.path.split("?", 1)[0]
        owner = self.owner
        if path == "/":
            self._send(PAGE.read_bytes(), "text/html; charset=utf-8")
        elif path == "/stats.json":
            with owner._cond:
                stats = dict(owner.stats, error=owner.error)
            self._send(json.dumps(stats).encode(), "application/json")
        elif path == "/frame.jpg":
            _, jpeg = owner.next_frame(0, timeout_s=5.0)
            if jpeg is None:
                self._send(b"no frame yet", "text/plain", HTTPStatus.SERVICE_UNAVAILABLE)
            else:
                self._send(jpeg, "image/jpeg")
        elif path == "/stream.mjpg":
            self._stream()
        elif path == "/favicon.ico":
            self._send(b"", "image/x-icon", HTTPStatus.NO_CONTENT)
        else:
            self._send(b"not found", "text/plain", HTTPStatus.NOT_FOUND)

    def _stream(self) -> None:
        owner = self.owner
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        seen = 0
        try:
            while not owner.stop_event.is_set() and owner.error is None:
                number, jpeg = owner.next_frame(seen)
                if jpeg is None or number == seen:
                    continue
                seen = number
                self.wfile.write(f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n\r\n".encode())
                self.wfile.write(jpeg)
                self.wfile.write(b"\r\n")
                self.wfile.flush()
        except (BrokenPipeError, ConnectionResetError):
            pass  # the browser went away

    def do_POST(self) -> None:  # noqa: N802
        if self._refused():
            return
        if self.path != "/roi":
            self._send(b"not found", "text/plain", HTTPStatus.NOT_FOUND)
            return
        try:
            length = int(self.headers.get("Content-Length", "0"))
            if not 0 < length <= 4096:
                raise ValueError("send a JSON body of at most 4096 bytes")
            roi = self.owner.set_roi(json.loads(self.rfile.read(length)).get("roi"))
        except (ValueError, AttributeError) as error:
            self._send(json.dumps({"error": str(error)}).encode(), "application/json", HTTPStatus.BAD_REQUEST)
            return
        self._send(json.dumps({"roi": roi}).encode(), "application/json")
