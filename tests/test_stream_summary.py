"""The typed run summaries of kinefuse.streaming are also the mappings the CLI writes as JSON."""

from __future__ import annotations

import json

from kinefuse.streaming import ReplaySummary, StreamSummary

KEYS = ["outputs", "frames", "counters", "events", "latency_ms", "streams", "missing",
        "output_stream", "interrupted"]  # fmt: skip


def _stream(**kw):
    base = dict(outputs=3, frames=3, counters={"late": 0}, events=[], latency_ms={"n": 0},
                streams=["a"], missing=[], output_stream="fused", interrupted=False)  # fmt: skip
    return StreamSummary(**{**base, **kw})


def test_stream_summary_is_a_mapping_with_the_json_keys_in_order():
    s = _stream()
    assert list(s) == KEYS and len(s) == len(KEYS)
    assert s["outputs"] == s.outputs == 3 and s.get("view_url") is None and "engine" not in s
    assert json.loads(json.dumps(s.to_dict())) == dict(s)
    full = _stream(view_url="http://127.0.0.1:1/", view={"sent": 1}, out="x.npz", engine=object())
    assert list(full) == [*KEYS, "view_url", "view", "out", "engine"]


def test_replay_summary_is_a_mapping():
    r = ReplaySummary(streams=["a"], samples={"a": 2}, duration_s=1.0, recording_s=0.5,
                      interrupted=False)  # fmt: skip
    assert dict(r) == {"streams": ["a"], "samples": {"a": 2}, "duration_s": 1.0,
                       "recording_s": 0.5, "interrupted": False}  # fmt: skip
    assert r["recording_s"] == r.recording_s
