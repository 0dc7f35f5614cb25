"""The live view's server on its own (no LSL): loopback only, fan-out of the newest frame,
a stalled or departed viewer never holds the publisher up."""

from __future__ import annotations

import http.client
import json
import logging
import socket
import struct
import threading
import urllib.request
from types import SimpleNamespace

import numpy as np
import pytest

from kinefuse.streaming.liveview import HOST, LiveView


def _frame(i: int):
    pos = np.full((2, 3), 0.01 * i)
    pos[1, 2] = np.nan  # a missing coordinate travels as null
    return SimpleNamespace(index=i, t_s=i / 30, position_m=pos, source=np.array([0, -1]))


class _Events:
    """A server-sent events client (raw socket) reading ``data:`` messages on a thread."""

    def __init__(self, port: int):
        self.sock = socket.create_connection((HOST, port), timeout=10)
        self.sock.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        self.fp = self.sock.makefile("rb")
        status = self.fp.readline()
        assert status.split()[1] == b"200", status
        headers = {}
        while (line := self.fp.readline().strip()) != b"":
            k, v = line.split(b":", 1)
            headers[k.strip().lower()] = v.strip()
        assert headers[b"content-type"] == b"text/event-stream"
        self.messages: list[dict] = []
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self):
        try:
            for line in self.fp:
                if line.startswith(b"data: "):
                    self.messages.append(json.loads(line[6:]))
        except (OSError, ValueError):
            pass

    def wait_for(self, index: int, timeout: float = 10.0) -> bool:
        pause = threading.Event()
        for _ in range(int(timeout / 0.05)):
            if self.messages and self.messages[-1]["index"] >= index:
                return True
            pause.wait(0.05)
        return False

    def close(self):
        self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()


def _status(view) -> dict:
    with urllib.request.urlopen(view.url + "status", timeout=5) as r:
        return json.loads(r.read())


def test_liveview_serves_loopback_only_and_fans_out_the_newest_frame():
    view = LiveView(["a", "b"], [("a", "b"), ("a", "unknown")], port=0)
    try:
        host, port = view._server.server_address[:2]
        assert host == "127.0.0.1" and view.url == f"http://127.0.0.1:{port}/"
        with urllib.request.urlopen(view.url, timeout=5) as r:
            page = r.read().decode("utf-8")
        assert "kinefuseLive(" in page and '"edges": [[0, 1]]' in page
        assert "<script src" not in page
        with pytest.raises(urllib.error.HTTPError):
            urllib.request.urlopen(view.url + "nothing", timeout=5)

        # a viewer that connects and never reads: the publisher must not wait for it
        stalled = socket.create_connection((HOST, port), timeout=5)
        stalled.sendall(b"GET /events HTTP/1.1\r\nHost: x\r\n\r\n")
        first, second = _Events(port), _Events(port)
        done = threading.Event()

        def publish_many(a, b):
            for i in range(a, b):
                view.publish(_frame(i), [0.001, 0.002])
            done.set()

        threading.Thread(target=publish_many, args=(0, 3000), daemon=True).start()
        assert done.wait(30), "publish blocked"
        assert first.wait_for(2999) and second.wait_for(2999)  # the newest frame arrives
        m = first.messages[-1]
        assert m["pos"][5] is None and m["src"] == [0, -1] and m["latency_ms"] == 2.0
        assert m["latency_p50_ms"] == pytest.approx(1.5)
        indices = [x["index"] for x in first.messages]
        assert indices == sorted(set(indices))  # newest-first fan-out: never repeated, in order
        assert _status(view)["viewers"] == 3

        first.close()  # one viewer leaves; the other keeps receiving
        done.clear()
        threading.Thread(target=publish_many, args=(3000, 3100), daemon=True).start()
        assert done.wait(30) and second.wait_for(3099)
        # the server notices the closed socket on its next send or read: allow a loaded machine
        # (the suite on 2 workers, 2 cores) 30 s rather than 5 s to get there
        for _ in range(600):
            if _status(view)["viewers"] == 2:
                break
            threading.Event().wait(0.05)
        assert _status(view)["viewers"] == 2
        assert view.published == 3100
        stalled.close()
        second.close()
    finally:
        view.close()


def test_liveview_port_taken_names_it():
    view = LiveView(["a"], [], port=0)
    try:
        port = view._server.server_address[1]
        with pytest.raises(OSError, match=f"127.0.0.1:{port}"):
            LiveView(["a"], [], port=port)
    finally:
        view.close()


def test_liveview_shows_the_joint_angles_it_is_given(tmp_path):
    """With angle joints (kinefuse stream --chain, segment frames), each message carries the
    angles (deg, 0.1 deg, NaN as null) and the page shows them in a table that follows the
    newest frame; without, neither the field nor the table exists."""
    from _chromium import browser

    view = LiveView(["knee_l", "ankle_l"], [("knee_l", "ankle_l")], port=0,
                    angle_joints=("knee_l",))  # fmt: skip
    plain = LiveView(["a", "b"], [], port=0)
    try:
        events, plain_events = (
            _Events(view._server.server_address[1]),
            _Events(plain._server.server_address[1]),
        )
        angles = np.array([[45.04, np.nan, -3.26]])
        view.publish(SimpleNamespace(**vars(_frame(1)), angles_deg=angles))
        plain.publish(_frame(1))
        assert events.wait_for(1) and plain_events.wait_for(1)
        assert events.messages[-1]["ang"] == [45.0, None, -3.3]
        assert "ang" not in plain_events.messages[-1]
        events.close()
        plain_events.close()
        with browser() as (ctx, log):
            page = ctx.new_page()
            page.goto(view.url)
            page.wait_for_function("window.kfViewer && kfViewer.ready", timeout=30_000)
            for i in range(2, 40):  # until the page has drawn one (the newest frame wins)
                a = np.array([[float(i), 1.5, np.nan]])
                view.publish(SimpleNamespace(**vars(_frame(i)), angles_deg=a))
                page.wait_for_timeout(50)
            page.wait_for_function("kfViewer.framesDrawn > 0", timeout=10_000)
            page.wait_for_function(
                "document.querySelector('#kf-joint-angles td:nth-child(2)').textContent == '39.0'",
                timeout=10_000,
            )
            cells = page.locator("#kf-joint-angles td").all_inner_texts()
            assert cells == ["knee_l", "39.0", "1.5", "–"], cells
            page.goto(plain.url)
            page.wait_for_function("window.kfViewer && kfViewer.ready", timeout=30_000)
            assert page.locator("#kf-joint-angles").count() == 0
            assert log["errors"] == [] and log["blocked"] == []
    finally:
        view.close()
        plain.close()


def _reset(port: int, request: bytes = b"", read: int = 0) -> None:
    """Connect, send ``request``, read ``read`` bytes, then reset the connection (SO_LINGER 0
    sends RST, as a browser tab killed mid-load or ``curl URL | head -c 300`` do)."""
    s = socket.create_connection((HOST, port), timeout=5)
    if request:
        s.sendall(request)
    got = b""
    while len(got) < read and (chunk := s.recv(read - len(got))):
        got += chunk
    s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    s.close()


def _requests_handled(timeout_s: float = 30.0) -> bool:
    """Wait until no request thread of a live view is running (each ends with its connection)."""
    for _ in range(int(timeout_s / 0.05)):
        if not any("process_request" in t.name for t in threading.enumerate()):
            return True
        threading.Event().wait(0.05)
    return False


def test_liveview_ignores_clients_that_reset_and_reports_other_errors_in_one_line(capsys, caplog):
    """A viewer going away (connection reset, broken pipe) is normal: nothing on stderr, no
    traceback; another failure of a request is one warning line, not socketserver's traceback."""
    view = LiveView(["a", "b"], [("a", "b")], port=0)
    try:
        port = view._server.server_address[1]
        view.publish(_frame(1))
        _reset(port)  # before sending a request
        _reset(port, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n", read=300)  # mid-page
        _reset(port, b"GET /status HTTP/1.1\r\nHost: x\r\n\r\n", read=1)  # kept alive, then reset
        _reset(port, b"GET /events HTTP/1.1\r\nHost: x\r\n\r\n", read=1)  # a viewer leaves
        assert _requests_handled()
        assert _status(view)["viewers"] == 0
        err = capsys.readouterr().err
        assert "Traceback" not in err and "Exception occurred" not in err, err
        assert not [r for r in caplog.records if r.levelno >= logging.WARNING]

        def broken_page():
            raise RuntimeError("page broke")

        view._page = broken_page  # any other error: reported, in one line
        with caplog.at_level(logging.WARNING, logger="kinefuse.streaming"):
            with pytest.raises((urllib.error.URLError, ConnectionError, http.client.HTTPException)):
                urllib.request.urlopen(view.url, timeout=5)
            assert _requests_handled()
        err = capsys.readouterr().err
        assert "Traceback" not in err and "Exception occurred" not in err, err
        lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
        assert len(lines) == 1 and "RuntimeError: page broke" in lines[0], lines
        assert "\n" not in lines[0]
    finally:
        view.close()
