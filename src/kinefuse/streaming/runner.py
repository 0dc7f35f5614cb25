"""``run_stream``: the engine on live LSL inputs, publishing the fused joints (Ctrl-C stops).

Output files (``run_stream(out=...)``)
--------------------------------------
The outputs go to ``out`` with suffix ``.npz`` and the summary (:class:`StreamSummary`,
as JSON) next to it with suffix ``.json``; existing files are overwritten. Outputs, for T
outputs and the J ``joints``: ``t_s`` (T,) frame time on the LSL clock, s; ``position_m``
(T, J, 3), m; ``std_m`` (T, J, 3), m; ``source`` (T, J) int8 code; ``flags`` (T, J) uint8 bit
mask; ``joints`` (J,) str; with a calibrated chain's segment frames also ``angles_deg`` (T, A,
3), deg (flexion, adduction, internal rotation, ISB) and ``angle_joints`` (A,) str.

With ``record_inputs`` the accepted input samples are in the ``.npz`` too, so that the session
can be re-run offline with :func:`~kinefuse.streaming.offline.offline_causal`: for each of the
S engine segments ``imu_<segment>_t`` (N,), s, and ``imu_<segment>_q`` (N, 4),
``q_world_from_sensor`` wxyz, in arrival order; ``camera_t`` (F,), s, ``camera_position_m``
(F, Jc, 3), m (camera frame, NaN = not seen) and ``camera_available`` (F, Jc) bool for the
accepted camera frames, with ``camera_joints`` (Jc,) str (F = Jc = 0 without a camera);
``frame_t`` (K,), s, and ``frame_synthesized`` (K,) bool (no camera frame at that time) for
every processed frame; ``segments`` (S,) str, ``imu_rate_hz`` (S,) and ``camera_rate_hz``
(scalar), Hz: the nominal rates the engine was built with (:func:`build_engine`). All times are
on the local LSL clock after clock correction, as the engine saw them.

Inputs
------
Inputs are resolved by name (timeout ``resolve_timeout_s``); a missing IMU stream leaves its
joints predict-only and is looked for again in the loop; a camera stream is required unless
the configuration has ``camera_stream = ""``. The camera's nominal rate sets the output rate
(one output per camera frame). The engine is built and warmed up and the output stream
created before the inlets subscribe, right before the loop, so that the loop starts without a
backlog of samples. Each inlet is opened with ``recover=True``, so a stream re-created with
the same source id is reattached by liblsl; a lost stream without source id is resolved again
by name. Timestamps: see :mod:`kinefuse.streaming.lsl`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import sys
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.live import Live
from rich.table import Table

from kinefuse.conventions import SOURCE_NAMES
from kinefuse.exceptions import ConfigError, InputError
from kinefuse.kinematics import full_body
from kinefuse.pipelines.run.chain_file import segment_frames_from_chain, skeleton_from_chain
from kinefuse.pipelines.vision_params import VisionParams
from kinefuse.sim.camera import bone_edges
from kinefuse.streaming.config import (
    StreamConfig,
    import_pylsl,
    load_stream_config,
    stream_config_from_session,
)
from kinefuse.streaming.engine import Engine, EngineConfig
from kinefuse.streaming.engine_types import SummaryMapping
from kinefuse.streaming.liveview import LiveView
from kinefuse.streaming.loop import run_loop
from kinefuse.streaming.lsl import IMU_TYPE, FusedOutlet, Input, resolve_many, visible_streams
from kinefuse.streaming.paper_b import VisionAssistedProcessor
from kinefuse.streaming.processors import (
    SOURCE_NONE,
    SOURCE_PREDICT,
    IntegratedProcessor,
    KalmanFusionProcessor,
)

__all__ = ["StreamSummary", "build_engine", "run_loop", "run_stream", "stream_config", "warm_up"]

log = logging.getLogger("kinefuse.streaming")

_SOURCE_SHORT = {**SOURCE_NAMES, SOURCE_PREDICT: "predict", SOURCE_NONE: "none"}


def stream_config(session) -> StreamConfig:
    """A :class:`StreamConfig` from a path (TOML), a SessionConfig, a StreamConfig or None."""
    if session is None:
        return StreamConfig()
    if isinstance(session, StreamConfig):
        return session
    if isinstance(session, (str, Path)):
        return load_stream_config(session)
    if hasattr(session, "method") and hasattr(session, "skeleton"):
        return stream_config_from_session(session)
    raise ConfigError(
        f"expected a session path, SessionConfig or StreamConfig, got {type(session).__name__}"
    )


def build_engine(
    cfg: StreamConfig, *, camera: bool, camera_rate_hz: float, imu_rate_hz, record=False
):
    """The :class:`Engine` (skeleton, processor, timing) a :class:`StreamConfig` describes."""
    skeleton, root_position = engine_skeleton(cfg)
    if cfg.chain is not None and camera:
        raise ConfigError("--chain: a calibrated IMU chain runs without a camera")
    rate = camera_rate_hz if camera else cfg.output_rate_hz
    if cfg.processor == "paper-a":
        proc = IntegratedProcessor(1.0 / rate, q=cfg.q, r=cfg.r_imu, lag=cfg.lag)
    elif cfg.processor in ("elm-fir", "elm-kf"):
        if cfg.lag:
            raise ConfigError(
                f"[stream] lag = {cfg.lag}: the paper-B processor runs without lag; set lag = 0"
            )
        proc = VisionAssistedProcessor(
            cfg.processor, VisionParams(), dt_s=1.0 / rate, joints=cfg.joints
        )
    else:
        proc = KalmanFusionProcessor(
            1.0 / rate, q=cfg.q, r_imu=cfg.r_imu, r_camera=cfg.r_camera, lag=cfg.lag
        )
    ecfg = EngineConfig(
        skeleton, joints=cfg.joints, camera=camera, camera_rate_hz=camera_rate_hz,
        output_rate_hz=cfg.output_rate_hz, imu_rate_hz=imu_rate_hz, max_latency_s=cfg.max_latency_s,
        stale_after_s=cfg.stale_after_s, gap_factor=cfg.gap_factor, record=record,
        root_position_m=root_position,
        segment_frames=_chain_frames(cfg),
        offset_segments=(cfg.chain or {}).get("offset_segments"),
        heading_pose_s=(cfg.chain or {}).get("heading", {}).get("window_s"),
        heading_reference=(cfg.chain or {}).get("heading", {}).get("reference"),
        heading_pose_yaw_deg=(cfg.chain or {}).get("heading", {}).get("pose_yaw_deg"),
    )  # fmt: skip
    return Engine(ecfg, proc)


def engine_skeleton(cfg: StreamConfig) -> tuple:
    """``(skeleton, root_position_m)`` of the engine: the calibrated chain of ``cfg.chain``
    (sensor-frame axes, its root), else paper B's full body at the origin."""
    if cfg.chain is not None:
        return skeleton_from_chain(cfg.chain)
    return full_body(height_m=cfg.body_height_m, lengths=cfg.lengths_m or None), (0.0, 0.0, 0.0)


def _chain_frames(cfg: StreamConfig) -> dict | None:
    """The calibrated segment frames of ``cfg.chain`` (None without a chain)."""
    return segment_frames_from_chain(cfg.chain) if cfg.chain is not None else None


def warm_up(engine, seconds: float = 2.0) -> None:
    """Run a throwaway copy of ``engine`` on synthetic input (``engine`` itself is untouched).

    The first call of each compiled kernel in a process loads (or compiles) its machine code
    and the first pass through NumPy and the processor allocates: tens to hundreds of
    milliseconds that would otherwise land on the first live frames. The synthetic input is
    ``seconds`` of identity orientations at every segment's rate and, with a camera, frames
    in which the first camera joint is hidden for the second half (an outage onset, so that a
    bridging processor trains once).
    """
    cfg = dataclasses.replace(engine.config, record=False)
    if cfg.heading_pose_s is not None:  # the synthetic input is still: one second of it will do
        cfg = dataclasses.replace(cfg, heading_pose_s=min(cfg.heading_pose_s, seconds / 2))
    # the engine's own processor, returned to its state afterwards: a deep copy would hold
    # writable copies of the processor's read-only arrays, which numba compiles as another
    # specialisation (the copy would compile code the real processor never runs)
    proc = engine.processor
    saved = proc.checkpoint()
    if hasattr(proc, "warm_up"):
        proc.warm_up()
    scratch = Engine(cfg, proc)
    events = []
    for seg in cfg.segments:
        dt = cfg.imu_period_s(seg)
        events += [(k * dt, 0, seg) for k in range(int(seconds / dt) + 1)]
    if cfg.camera:
        dt = cfg.frame_period_s
        events += [(k * dt, 1, None) for k in range(int(seconds / dt) + 1)]
    events.sort(key=lambda e: (e[0], e[1]))
    q = np.array([1.0, 0.0, 0.0, 0.0])
    Jc = len(cfg.camera_joints) if cfg.camera else 0
    pos = np.zeros((Jc, 3))
    avail = np.ones(Jc, bool)
    level = log.level
    log.setLevel(logging.ERROR)  # a throwaway run: no events in the user's log
    try:
        for t, kind, seg in events:
            if kind == 0:
                scratch.push_imu(seg, t, q, now=t)
            else:
                if Jc and t >= seconds / 2:
                    avail[0] = False
                scratch.push_camera(t, pos + 0.01 * t, avail, now=t)
            scratch.poll(t)
        scratch.flush(seconds + 1.0)
    finally:
        log.setLevel(level)
        proc.restore(saved)


def _status_printer(console, cfg):
    # rendered by the loop itself (4 Hz, right after a push), not by rich's refresh thread:
    # a thread would compete with the loop for the GIL at random moments
    live = Live(console=console, auto_refresh=False, transient=False)
    live.start()
    last = {"t": time.monotonic(), "n": {}}

    def show(engine, latencies):
        now_m = time.monotonic()
        dt = max(now_m - last["t"], 1e-3)
        st = engine.stream_status()
        tab = Table(title=f"kinefuse stream -> {cfg.output_stream_name}", expand=False)
        for col in ("stream", "samples", "rate Hz", "age s", "state"):
            tab.add_column(col)
        for name, s in st.items():
            rate = (s["samples"] - last["n"].get(name, s["samples"])) / dt
            last["n"][name] = s["samples"]
            age = s["age_s"]
            tab.add_row(name, str(s["samples"]), f"{rate:.0f}", "-" if not math.isfinite(age) else f"{age:.2f}",
                        "[red]stale[/red]" if s["stale"] else "ok")  # fmt: skip
        last["t"] = now_m
        lat = np.asarray(latencies)
        lat_txt = (
            "-"
            if lat.size == 0
            else f"p50 {1e3 * np.median(lat):.3f} ms, p99 {1e3 * np.percentile(lat, 99):.3f} ms"
        )
        src = getattr(engine, "_last_sources", None)
        joints = " ".join(
            f"{j}:{_SOURCE_SHORT.get(int(c), '?')}" for j, c in zip(engine.config.joints, src, strict=True)
        ) if src is not None else "-"  # fmt: skip
        ang = getattr(engine, "_last_angles", None)
        if ang is not None:  # flexion, the number a clinician watches
            joints += "\nflexion " + " ".join(
                f"{j} {a:.0f}°" if math.isfinite(a) else f"{j} -"
                for j, a in zip(engine.config.angle_joints, ang[:, 0], strict=True)
            )
        h = engine.heading
        if h is not None and not h.aligned:  # 6-D sensors: nothing comes out before the pose
            joints = (f"[yellow]hold the calibration pose: stand still for {h.window_s:g} s "
                      "(6-D sensors: their headings come from it)[/yellow]")  # fmt: skip
        c = engine.counters
        tab.caption = (f"outputs {c['outputs']}  latency {lat_txt}\n{joints}\n"
                       f"late {c['late']} dup {c['duplicate']} reordered {c['reordered']} jumps {c['time_jump']} "
                       f"stale {c['stream_stale']} forced {c['forced_frames']} synthesized {c['synthesized_frames']}")  # fmt: skip
        live.update(tab, refresh=True)

    return live, show


@dataclass(frozen=True, eq=False)
class StreamSummary(SummaryMapping):
    """Outcome of :func:`run_stream`; also a read-only mapping of its JSON keys (``s["outputs"]``
    as ``s.outputs``), in the order of :meth:`to_dict`.

    Attributes
    ----------
    outputs, frames : int
        Outputs pushed; frames processed.
    counters : dict
        :attr:`Engine.counters` at the end.
    events : list of str
        The last 50 :class:`~kinefuse.streaming.engine.EngineEvent` s, as text.
    latency_ms : dict
        ``p50``, ``p99``, ``max`` (ms, None without timed outputs) and ``n`` over the live
        outputs (pull of the sample that completed the frame -> output pushed) and
        ``catch_up_outputs`` (outputs of the start-up backlog, not timed; see
        :func:`~kinefuse.streaming.loop.run_loop`).
    streams, missing : list of str
        Streams read; streams not found (still missing at the end).
    output_stream : str
    interrupted : bool
        Ctrl-C ended the run.
    angles_stream : str or None
        The joint-angle stream (a calibrated chain with segment frames).
    view_url, view : str, dict or None
        With ``view_port``: the live view's address and ``published``/``sent`` counts.
    out : str or None
        The ``.npz`` written (``out``).
    engine : Engine or None
        With ``return_engine``.
    """

    outputs: int
    frames: int
    counters: dict
    events: list
    latency_ms: dict
    streams: list
    missing: list
    output_stream: str
    interrupted: bool
    angles_stream: str | None = None
    view_url: str | None = None
    view: dict | None = None
    out: str | None = None
    engine: Engine | None = None

    _optional = ("angles_stream", "view_url", "view", "out", "engine")


@dataclass(frozen=True)
class _Inputs:
    """The LSL streams found for a :class:`StreamConfig`."""

    segments: tuple
    wanted: dict  # stream name -> segment
    found: dict  # stream name -> pylsl StreamInfo
    camera: str | None
    missing: list
    imu_rates: dict
    camera_rate_hz: float


def _resolve_inputs(cfg: StreamConfig) -> _Inputs:
    segments = EngineConfig(engine_skeleton(cfg)[0], joints=cfg.joints,
                            segment_frames=_chain_frames(cfg),
                            offset_segments=(cfg.chain or {}).get("offset_segments")).segments  # fmt: skip
    cam_name = cfg.camera_stream_name
    wanted = {cfg.imu_stream_name(seg): seg for seg in segments}
    found = resolve_many(([cam_name] if cam_name else []) + list(wanted), cfg.resolve_timeout_s)
    if cam_name and cam_name not in found:
        raise InputError(f"camera stream {cam_name!r} not found within {cfg.resolve_timeout_s:g} s "
                         "(set [stream] camera_stream = \"\" to run without a camera)"
                         + _seen_hint(cfg))  # fmt: skip
    if not any(name in found for name in wanted):
        raise InputError(_no_imu(cfg, segments) + _seen_hint(cfg))
    missing = [name for name in wanted if name not in found]
    for name in missing:
        log.warning("LSL stream %s not found: its joints stay predict-only until it appears", name)
    imu_rates = {s: 100.0 for s in segments}
    for name, seg in wanted.items():
        if name in found and found[name].nominal_srate() > 0:
            imu_rates[seg] = found[name].nominal_srate()
    cam_rate = (
        found[cam_name].nominal_srate()
        if cam_name and found[cam_name].nominal_srate() > 0
        else cfg.output_rate_hz
    )
    return _Inputs(segments, wanted, found, cam_name, missing, imu_rates, cam_rate)


def _open_inputs(cfg: StreamConfig, plan: _Inputs, outlet, wait_for_reader_s, lost_errors) -> list:
    """Subscribe to every stream found (all at once) and take first clock offsets; a stream
    that went away since it was resolved joins ``plan.missing`` (the camera: an error)."""
    inputs = []
    try:
        if wait_for_reader_s:
            outlet.outlet.wait_for_consumers(wait_for_reader_s)

        # the inlets subscribe only now, right before the loop: data buffered during warm-up
        # would arrive as a backlog older than stale_after_s, and every IMU stream would look
        # stale while the frames of that backlog are processed. All are opened at once (not
        # one after the other: the first would buffer data the last has not seen yet), the
        # camera listed last so that each loop pass reads the IMUs before the frame they
        # complete.
        def open_input(spec):
            kind, key, name = spec
            try:
                return Input.open(kind, key, name, info=plan.found[name], clock=cfg.clock)
            except lost_errors as exc:  # the stream went away since it was resolved
                return exc

        specs = [("imu", seg, name) for name, seg in plan.wanted.items() if name in plan.found]
        specs += [("camera", "camera", plan.camera)] if plan.camera else []
        with ThreadPoolExecutor(max_workers=len(specs)) as pool:
            opened = list(pool.map(open_input, specs))
        inputs += [r for r in opened if not isinstance(r, Exception)]
        for (kind, _, name), r in zip(specs, opened, strict=True):
            if not isinstance(r, Exception):
                continue
            if kind == "camera":
                raise InputError(f"camera stream {name!r} went away before it could be opened")
            log.warning("LSL stream %s went away before it could be opened: its joints stay "
                        "predict-only until it appears", name)  # fmt: skip
            plan.missing.append(name)
        if not any(i.kind == "imu" for i in inputs):
            raise InputError("every IMU stream went away before it could be opened")
        # first clock-offset estimates in parallel (each takes a few probe round trips)
        with ThreadPoolExecutor(max_workers=len(inputs)) as pool:
            list(pool.map(lambda i: i.refresh_clock(first=True), inputs))
    except BaseException:
        for inp in inputs:
            inp.close()
        outlet.close()
        raise
    return inputs


def _output_hook(engine, cfg: StreamConfig, inputs, pending_missing, collected, lost_errors):
    """Called with every output: remembers its sources, collects it, attaches late streams."""

    def on_output(o):
        engine._last_sources, engine._last_angles = o.source, o.angles_deg
        if collected is not None:
            collected.append(o)
        if pending_missing and (o.index % 150) == 0:
            for seg, name in list(pending_missing.items()):
                try:
                    inputs.append(
                        Input.open(
                            "imu", seg, name, stype=IMU_TYPE, timeout_s=0.02, clock=cfg.clock
                        )
                    )
                    del pending_missing[seg]
                    log.warning("LSL stream %s appeared: attached", name)
                except lost_errors:
                    pass

    return on_output


def _run_live(engine, inputs, outlet, cfg, on_output, status, view_port, loop_kw):
    """:func:`run_loop` with the terminal status and the live view; returns (result, view)."""
    view = None
    if view_port is not None:
        view, on_output, show_view = _live_view(cfg, view_port, on_output, inputs, outlet,
                                                engine.config.angle_joints)  # fmt: skip
    live = show = None
    if status:
        live, show = _status_printer(Console(stderr=True), cfg)
    if view is not None:
        show = show_view(show)
    try:
        res = run_loop(engine, inputs, outlet, on_output=on_output, status=show,
                       reattach=lambda inp: inp.reattach(0.05), **loop_kw)  # fmt: skip
    finally:
        if live is not None:
            live.stop()
        if view is not None:
            view.close()
    return res, view


def _summary(engine, res, inputs, pending_missing, cfg: StreamConfig, view) -> dict:
    lat = res.latency_s
    summary = {
        "outputs": res.outputs,
        "frames": engine.counters["frames"],
        "counters": dict(engine.counters),
        "events": [str(e) for e in list(engine.events)[-50:]],
        "latency_ms": {
            "p50": float(1e3 * np.median(lat)) if lat.size else None,
            "p99": float(1e3 * np.percentile(lat, 99)) if lat.size else None,
            "max": float(1e3 * lat.max()) if lat.size else None,
            "n": int(lat.size),
            "catch_up_outputs": res.catch_up_outputs,
        },
        "streams": [i.name for i in inputs],
        "missing": sorted(pending_missing.values()),
        "output_stream": cfg.output_stream_name,
        "interrupted": res.interrupted,
    }
    if engine.config.angle_joints:
        summary["angles_stream"] = f"{cfg.output_stream_name}-angles"
    if view is not None:
        summary["view_url"] = view.url
        summary["view"] = {"published": view.published, "sent": view.sent}
    return summary


def _write_outputs(out, collected, engine, cfg: StreamConfig, summary, record_inputs) -> str:
    """The ``.npz`` of the outputs (module docstring) and the ``.json`` summary; the npz path."""
    p = Path(out)
    p.parent.mkdir(parents=True, exist_ok=True)
    J = len(cfg.joints)
    np.savez(
        p.with_suffix(".npz"),
        t_s=np.array([o.t_s for o in collected]),
        position_m=np.array([o.position_m for o in collected]).reshape(-1, J, 3),
        std_m=np.array([o.std_m for o in collected]).reshape(-1, J, 3),
        source=np.array([o.source for o in collected], np.int8).reshape(-1, J),
        flags=np.array([o.flags for o in collected], np.uint8).reshape(-1, J),
        joints=np.array(cfg.joints),
        **_angle_arrays(collected, engine.config.angle_joints),
        **(_recorded_inputs(engine) if record_inputs else {}),
    )
    p.with_suffix(".json").write_text(json.dumps(summary, indent=2), encoding="utf-8")
    return str(p.with_suffix(".npz"))


def _angle_arrays(collected, joints) -> dict:
    """``angles_deg (T, A, 3)`` and ``angle_joints`` for the ``.npz`` (none without angles)."""
    if not joints:
        return {}
    a = np.array([o.angles_deg for o in collected], dtype=float).reshape(-1, len(joints), 3)
    return {"angles_deg": a, "angle_joints": np.array(joints)}


def run_stream(
    session=None,
    duration_s: float | None = None,
    out: str | Path | None = None,
    status: bool = True,
    *,
    idle_timeout_s: float | None = None,
    wait_for_reader_s: float | None = None,
    stop_event=None,
    record: bool = False,
    record_inputs: bool = False,
    return_engine: bool = False,
    view_port: int | None = None,
) -> StreamSummary:
    """Run the online engine on LSL inputs and publish the fused joints.

    Parameters
    ----------
    session : path, SessionConfig, StreamConfig or None
        A streaming session TOML (:func:`~kinefuse.streaming.config.load_stream_config`), an
        offline session (:func:`~kinefuse.streaming.config.stream_config_from_session`), a
        :class:`StreamConfig`, or None for the defaults (the streams of
        ``run_replay(..., name_prefix="kinefuse")``).
    duration_s : float, optional
        Stop after this wall time, s (default: until Ctrl-C, ``idle_timeout_s`` or
        ``stop_event``).
    out : path, optional
        Write the outputs (``.npz``) and the summary (``.json``): see the module docstring.
    status : bool
        Live terminal status (rich): streams, rates, per-joint source, latency.
    idle_timeout_s : float, optional
        Stop once no input sample arrived for this long.
    wait_for_reader_s : float, optional
        Wait up to this long for a consumer of the output stream before the inputs are opened.
    stop_event : threading.Event, optional
        Stop when set (tests, embedding).
    record : bool
        Keep the accepted samples in ``engine.accepted`` (tests).
    record_inputs : bool
        Also write the accepted input samples into the ``.npz`` of ``out`` (required; module
        docstring), implies ``record`` (memory grows with the session).
    return_engine : bool
        Put the :class:`Engine` in the summary (key ``"engine"``).
    view_port : int, optional
        Serve the live view (:class:`~kinefuse.streaming.liveview.LiveView`) on
        ``http://127.0.0.1:view_port/`` (0 = a free port) while the stream runs; its address
        is printed on stderr and is in the summary. The page never slows the stream down.

    Returns
    -------
    StreamSummary
        Inputs and timing: see the module docstring.
    """
    if record_inputs and out is None:
        raise InputError("record_inputs needs out: the accepted inputs are written to its .npz")
    cfg = stream_config(session)
    pylsl = import_pylsl()
    plan = _resolve_inputs(cfg)
    engine = build_engine(cfg, camera=plan.camera is not None, camera_rate_hz=plan.camera_rate_hz,
                          imu_rate_hz=plan.imu_rates, record=record or record_inputs)  # fmt: skip
    warm_up(engine)
    outlet = FusedOutlet(cfg.output_stream_name, cfg.joints, plan.camera_rate_hz,
                         processor=cfg.processor, lag_frames=cfg.lag,
                         angle_joints=engine.config.angle_joints)  # fmt: skip
    lost_errors = (TimeoutError, pylsl.util.TimeoutError, pylsl.util.LostError)
    inputs = _open_inputs(cfg, plan, outlet, wait_for_reader_s, lost_errors)
    pending_missing = {seg: cfg.imu_stream_name(seg) for seg in plan.segments
                       if cfg.imu_stream_name(seg) in plan.missing}  # fmt: skip
    collected = [] if out is not None else None
    on_output = _output_hook(engine, cfg, inputs, pending_missing, collected, lost_errors)
    loop_kw = dict(clock=pylsl.local_clock, duration_s=duration_s, idle_timeout_s=idle_timeout_s,
                   stop_event=stop_event)  # fmt: skip
    res, view = _run_live(engine, inputs, outlet, cfg, on_output, status, view_port, loop_kw)
    summary = _summary(engine, res, inputs, pending_missing, cfg, view)
    if out is not None:
        summary["out"] = _write_outputs(out, collected, engine, cfg, summary, record_inputs)
    return StreamSummary(**summary, engine=engine if return_engine else None)


def _live_view(cfg: StreamConfig, port: int, on_output, inputs, outlet, angle_joints=()):
    """Start the live view; return it, the output hook publishing to it and a status wrapper."""
    try:
        view = LiveView(cfg.joints, bone_edges(cfg.joints), port=port,
                        title=f"kinefuse stream -> {cfg.output_stream_name}",
                        source_names=_SOURCE_SHORT, angle_joints=angle_joints)  # fmt: skip
    except OSError as exc:
        for inp in inputs:
            inp.close()
        outlet.close()
        raise InputError(f"--view: {exc}") from None
    print(f"kinefuse stream: live view at {view.url}", file=sys.stderr, flush=True)
    recent: list = [None]  # run_loop's latency deque, handed over by the status callback

    def publish(o):
        on_output(o)
        view.publish(o, recent[0])

    def wrap(show):
        def status(engine, latencies):
            recent[0] = latencies
            if show is not None:
                show(engine, latencies)

        return status

    return view, publish, wrap


def _no_imu(cfg: StreamConfig, segments) -> str:
    names = [cfg.imu_stream_name(s) for s in segments]
    return f"no IMU stream found within {cfg.resolve_timeout_s:g} s (looked for {names})"


def _seen_hint(cfg: StreamConfig) -> str:
    """What LSL does see on this machine, and the prefix it suggests (``kinefuse replay``
    publishes ``PREFIX_imu_SEGMENT`` with ``--prefix``, default ``kinefuse``)."""
    seen = visible_streams(1.0)
    if not seen:
        return "; no LSL stream is visible on this machine"
    names = [n for n, _ in seen]
    text = f"; visible: {', '.join(names[:8])}" + (
        f" and {len(names) - 8} more" if len(names) > 8 else ""
    )
    prefixes = sorted({n.split("_imu_")[0] for n in names if "_imu_" in n} - {cfg.name_prefix})
    if prefixes:
        text += (
            f" (IMU streams with prefix {', '.join(map(repr, prefixes))}, this session looks for "
            f"{cfg.name_prefix!r}: set [stream] name_prefix, or publish with kinefuse replay "
            f"--prefix {cfg.name_prefix})"
        )
    return text


def _recorded_inputs(engine) -> dict:
    """The ``record_inputs`` arrays of :func:`run_stream` from ``engine.accepted``."""
    ecfg = engine.config
    acc = engine.accepted
    arrays = {}
    for seg in ecfg.segments:
        samples = acc["imu"][seg]
        arrays[f"imu_{seg}_t"] = np.array([t for t, _ in samples], float)
        arrays[f"imu_{seg}_q"] = np.array([q for _, q in samples], float).reshape(-1, 4)
    cj = tuple(ecfg.camera_joints or ())
    cam = acc["camera"]
    arrays["camera_t"] = np.array([c[0] for c in cam], float)
    arrays["camera_position_m"] = np.array([c[1] for c in cam], float).reshape(-1, len(cj), 3)
    arrays["camera_available"] = np.array([c[2] for c in cam], bool).reshape(-1, len(cj))
    arrays["camera_joints"] = np.array(cj, dtype=str)
    arrays["frame_t"] = np.array([f[0] for f in acc["frames"]], float)
    arrays["frame_synthesized"] = np.array([f[1] for f in acc["frames"]], bool)
    arrays["segments"] = np.array(ecfg.segments, dtype=str)
    rates = ecfg.imu_rate_hz
    arrays["imu_rate_hz"] = np.array(
        [float(rates[s] if isinstance(rates, Mapping) else rates) for s in ecfg.segments]
    )
    arrays["camera_rate_hz"] = np.array(float(ecfg.camera_rate_hz))
    return arrays
