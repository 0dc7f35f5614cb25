"""Ctrl-C during `kinefuse replay`: every sample pushed is counted, and the handler is restored.

The replay runs on fake outlets and a fake clock (this process never loads pylsl: liblsl reads
its machine-local configuration once per process; tests/test_lsl.py runs real streams in
children)."""

from __future__ import annotations

import os
import signal
import time
from types import SimpleNamespace

import pytest

from kinefuse.streaming import replay as replay_mod


class _Outlet:
    """Counts its pushes; the ``sigint_at``-th push of all outlets sends this process SIGINT
    from inside ``push_sample`` (between the push and the replay's count of it)."""

    total = 0
    sigint_at: int | None = None

    def __init__(self):
        self.n = 0

    def push_sample(self, value, timestamp):
        self.n += 1
        _Outlet.total += 1
        if _Outlet.total == _Outlet.sigint_at:
            os.kill(os.getpid(), signal.SIGINT)


@pytest.fixture
def fake_lsl(monkeypatch):
    outlets = {}

    def make_outlet(name, *args, **kwargs):
        outlets[name] = _Outlet()
        return outlets[name]

    monkeypatch.setattr(replay_mod, "make_outlet", make_outlet)
    monkeypatch.setattr(
        replay_mod, "import_pylsl", lambda: SimpleNamespace(local_clock=time.monotonic)
    )
    monkeypatch.setattr(_Outlet, "total", 0)
    return outlets


@pytest.mark.parametrize("sigint_at", [1, 57, 400])
def test_ctrl_c_mid_push_counts_every_pushed_sample(fake_lsl, monkeypatch, sigint_at):
    """SIGINT inside a push: that sample was sent, so the summary counts it (raised there as a
    KeyboardInterrupt, the count missed it and a consumer held one sample more than the
    replay said it published); publishing stops at the next sample."""
    monkeypatch.setattr(_Outlet, "sigint_at", sigint_at)
    rec = replay_mod.demo_recording(stop_s=3.0)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal
    try:
        summary = replay_mod.run_replay(rec, rate=1e4, name_prefix="t", linger_s=0.0)
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
    finally:
        signal.signal(signal.SIGINT, before)
    assert summary.interrupted
    assert summary.samples == {name: o.n for name, o in fake_lsl.items()}
    assert sum(summary.samples.values()) == sigint_at  # stopped before the next sample


def test_ctrl_c_ignored_in_a_background_job_publishes_everything(fake_lsl, monkeypatch):
    """A replay started with SIGINT ignored (nohup, a background job) keeps ignoring it."""
    monkeypatch.setattr(_Outlet, "sigint_at", 57)
    rec = replay_mod.demo_recording(stop_s=3.0)
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        summary = replay_mod.run_replay(rec, rate=1e4, name_prefix="t", linger_s=0.0)
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)
    assert not summary.interrupted
    assert summary.samples == {name: o.n for name, o in fake_lsl.items()}
    assert sum(summary.samples.values()) > 57
