"""``kinefuse stream --view``: a web page on 127.0.0.1 showing the fused skeleton as it streams.

:class:`LiveView` runs a :class:`http.server.ThreadingHTTPServer` in a daemon thread, bound to
the loopback interface only (``127.0.0.1``; there is no option for another interface). It
serves

* ``/`` the page: the report's 3-D viewer (:mod:`kinefuse.evaluation.viewer`, three.js inlined,
  nothing loaded from a network) in live mode, each joint coloured by its source, the current
  latency and a count of the frames received;
* ``/events`` the frames as server-sent events (one JSON object per message: ``index``,
  ``t_s``, ``pos`` (J*3, m, null = missing), ``src`` (J codes), ``latency_ms``,
  ``latency_p50_ms``);
* ``/status`` a JSON snapshot (viewers connected, frames published, frames sent).

The stream never waits for a viewer: :meth:`LiveView.publish` only replaces the latest frame
under a lock and wakes the viewer threads; each viewer is sent the newest frame when it is
ready (a slow viewer skips frames, it never delays the stream). Any number of viewers may
watch; a viewer that closes its page ends only its own thread. A client that goes away
(connection reset, broken pipe) is normal and ignored quietly; any other failure of a request is
logged as one warning line (``kinefuse.streaming``), never as a traceback on the terminal.
"""

from __future__ import annotations

import html
import json
import logging
import math
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np

from kinefuse.conventions import SOURCE_NAMES
from kinefuse.evaluation.viewer import SOURCE_COLORS, viewer_assets

__all__ = ["HOST", "LiveView"]

log = logging.getLogger("kinefuse.streaming")

#: The only interface the live view binds to.
HOST = "127.0.0.1"

_KEEPALIVE_S = 10.0

#: What a client that went away raises on its connection (normal: not reported).
_CLIENT_GONE = (BrokenPipeError, ConnectionResetError, ConnectionAbortedError)


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def handle_error(self, request, client_address):
        """Called by socketserver inside ``except``: replaces its traceback on stderr."""
        exc = sys.exc_info()[1]
        peer = ":".join(str(p) for p in client_address[:2])
        if isinstance(exc, _CLIENT_GONE):
            log.debug("live view: client %s went away (%s)", peer, type(exc).__name__)
            return
        log.warning("live view: request from %s failed: %s: %s", peer, type(exc).__name__,
                    " ".join(str(exc).split()))  # fmt: skip


class LiveView:
    """Serve the live skeleton page on ``http://127.0.0.1:PORT/``.

    Parameters
    ----------
    joints : sequence of str, length J
        Joint names of the published frames.
    edges : sequence of (str, str)
        Bones as joint-name pairs (pairs naming other joints are skipped).
    port : int
        TCP port on 127.0.0.1; 0 picks a free one (see :attr:`url`).
    title : str
    source_names : mapping int -> str
        Names of the source codes (streaming adds ``4`` = predict).
    angle_joints : sequence of str
        Joints whose angles the outputs carry (``EngineOutput.angles_deg``): shown as a table
        of flexion, adduction and internal rotation (deg).

    Raises
    ------
    OSError
        The port is taken (the message names it).
    """

    def __init__(self, joints, edges, *, port: int = 0, title: str = "kinefuse stream",
                 source_names=None, angle_joints=()):  # fmt: skip
        self.joints = tuple(joints)
        self.angle_joints = tuple(angle_joints)
        index = {n: i for i, n in enumerate(self.joints)}
        self.edges = [[index[a], index[b]] for a, b in edges if a in index and b in index]
        self.title = title
        self.source_names = dict(SOURCE_NAMES if source_names is None else source_names)
        self._cond = threading.Condition()
        self._latest: bytes | None = None
        self._seq = 0
        self._closed = False
        self._bounds: tuple[list[float], float] | None = None
        self.viewers = 0
        self.sent = 0
        self.published = 0
        try:
            self._server = _Server((HOST, int(port)), self._handler())
        except OSError as exc:
            raise OSError(
                f"live view: cannot listen on {HOST}:{port}: {exc.strerror or exc}"
            ) from exc
        self._thread = threading.Thread(
            target=self._server.serve_forever, kwargs={"poll_interval": 0.2},
            name="kinefuse-liveview", daemon=True,
        )  # fmt: skip
        self._thread.start()

    @property
    def url(self) -> str:
        """The page's address (always on 127.0.0.1)."""
        return f"http://{HOST}:{self._server.server_address[1]}/"

    def publish(self, output, latencies_s=None) -> None:
        """Make ``output`` (an :class:`~kinefuse.streaming.engine.EngineOutput`) the latest frame.

        Parameters
        ----------
        output : EngineOutput
            ``index``, ``t_s``, ``position_m`` (J, 3), ``source`` (J,), ``angles_deg``.
        latencies_s : sequence of float, optional
            Recent output latencies, s (the last is shown as the current one, with the
            median of the last 100).
        """
        pos = np.asarray(output.position_m, dtype=float).reshape(-1)
        lat = lat50 = None
        if latencies_s is not None and len(latencies_s):
            recent = list(latencies_s)[-100:]
            lat, lat50 = 1e3 * float(recent[-1]), 1e3 * float(np.median(recent))
        if self._bounds is None and np.any(np.isfinite(pos)):
            p = pos.reshape(-1, 3)
            p = p[np.all(np.isfinite(p), axis=1)]
            lo, hi = p.min(0), p.max(0)
            c = 0.5 * (lo + hi)
            self._bounds = ([float(c[0]), float(c[1]), float(c[2]), float(lo[2])],
                            max(float(np.max(hi - lo)) / 2, 0.6))  # fmt: skip
        msg = {
            "index": int(output.index),
            "t_s": float(output.t_s),
            "pos": [round(v, 4) if math.isfinite(v) else None for v in pos.tolist()],
            "src": [int(c) for c in np.asarray(output.source).reshape(-1)],
            "latency_ms": lat,
            "latency_p50_ms": lat50,
        }
        if self.angle_joints and output.angles_deg is not None:
            a = np.asarray(output.angles_deg, dtype=float).reshape(-1).tolist()
            msg["ang"] = [round(v, 1) if math.isfinite(v) else None for v in a]
        data = b"data: " + json.dumps(msg, separators=(",", ":")).encode() + b"\n\n"
        with self._cond:
            self._latest = data
            self._seq += 1
            self.published += 1
            self._cond.notify_all()

    def close(self) -> None:
        """Stop serving (viewer threads end within a second)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._server.shutdown()
        self._server.server_close()

    # ------------------------------------------------------------------ HTTP
    def _page(self) -> bytes:
        script, css = viewer_assets()
        center, radius = self._bounds or ([0.0, 0.0, 0.0, -1.0], 1.0)
        meta = {
            "auto_aim": self._bounds is None,
            "joints": list(self.joints),
            "angle_joints": list(self.angle_joints),
            "edges": self.edges,
            "color": "#332288",
            "center": center,
            "radius": radius,
            "events_url": "/events",
            "source_names": {str(c): n for c, n in self.source_names.items()},
            "source_colors": {str(c): SOURCE_COLORS.get(c, "#777777") for c in self.source_names},
        }
        e = html.escape
        meta_js = json.dumps(meta).replace("</", "<\\/")
        body = (
            '<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
            f"<title>{e(self.title)}</title><style>"
            "body{font:14px/1.45 system-ui,sans-serif;margin:16px 24px;color:#1d2330}"
            "table.results{border-collapse:collapse}table.results td{padding:1px 8px;"
            "border-bottom:1px solid #d9dee7}"
            f"{css}</style></head><body><h1>{e(self.title)}: live</h1>"
            '<div id="kf-viewer" class="kf-viewer"><div class="kf-main"><div class="kf-stage">'
            '</div><div class="kf-controls"></div></div><div class="kf-side"></div></div>'
            '<p class="note">Closing this page never affects the stream. Drag to orbit, scroll to '
            "zoom.</p>"
            f"<script>{script}</script><script>kinefuseLive({meta_js});</script></body></html>"
        )
        return body.encode("utf-8")

    def _handler(self):
        view = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, fmt, *args):  # no access log on the terminal
                log.debug("live view: " + fmt, *args)

            def _send(self, code, ctype, data: bytes):
                self.send_response(code)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(data)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(data)

            def do_GET(self):
                path = self.path.split("?", 1)[0]
                try:
                    if path in ("/", "/index.html"):
                        self._send(200, "text/html; charset=utf-8", view._page())
                    elif path == "/status":
                        status = {"viewers": view.viewers, "published": view.published,
                                  "sent": view.sent}  # fmt: skip
                        self._send(200, "application/json", json.dumps(status).encode())
                    elif path == "/events":
                        self._events()
                    else:
                        self._send(404, "text/plain; charset=utf-8", b"not found\n")
                except _CLIENT_GONE:
                    self.close_connection = True  # the viewer went away: only this thread ends

            def _events(self):
                self.send_response(200)
                self.send_header("Content-Type", "text/event-stream")
                self.send_header("Cache-Control", "no-store")
                self.send_header("Connection", "close")
                self.end_headers()
                self.close_connection = True
                seen = -1
                with view._cond:
                    view.viewers += 1
                try:
                    self.wfile.write(b"retry: 1000\n\n")
                    self.wfile.flush()
                    while True:
                        with view._cond:
                            if view._seq == seen and not view._closed:
                                view._cond.wait(_KEEPALIVE_S)
                            if view._closed:
                                return
                            data, seq = view._latest, view._seq
                        if data is None or seq == seen:
                            self.wfile.write(b": keep-alive\n\n")
                        else:
                            self.wfile.write(data)
                            with view._cond:
                                view.sent += 1
                            seen = seq
                        self.wfile.flush()
                finally:
                    with view._cond:
                        view.viewers -= 1

        return Handler
