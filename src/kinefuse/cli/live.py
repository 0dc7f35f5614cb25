"""Live commands: ``stream`` (fuse LSL streams online) and ``replay`` (publish a recording)."""

import dataclasses
import logging
import math
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated

import typer
from rich import box
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from kinefuse.cli._app import backend, backend_module, stderr
from kinefuse.cli._output import (
    Json,
    JsonForce,
    Quiet,
    check_json,
    existing_file,
    finish,
    one_line,
)
from kinefuse.exceptions import InputError
from kinefuse.io import FORMATS, detect_format
from kinefuse.io.output_folder import check_folder_usable
from kinefuse.session_file import load_session, read_toml

__all__ = ["replay", "stream"]


def _flag(flag: str, help_text: str):
    """The annotation of an on/off ``--flag`` option."""
    return Annotated[bool, typer.Option(flag, help=help_text)]


def _seconds(flag: str, help_text: str):
    """The annotation of a ``--flag SECONDS`` option: a number of seconds, None if not given."""
    return Annotated[float | None, typer.Option(flag, metavar="SECONDS", help=help_text)]


def _positive(value: float | None, option: str) -> None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise InputError(f"{option}: expected a number of seconds > 0, got {value:g}")


def _stream_session(path: Path, resolve_timeout_s: float | None, chain_file: Path | None = None):
    """The StreamConfig of SESSION.toml: a ``[stream]`` table -> streaming loader, else offline."""
    # the streaming back-end's loaders, imported when the command runs (kinefuse.streaming loads
    # compiled kernels)
    config = backend_module("stream", "kinefuse.streaming.config")
    p = path.expanduser()
    existing_file(p, "SESSION.toml")
    doc = read_toml(p)
    overrides = {} if resolve_timeout_s is None else {"resolve_timeout_s": resolve_timeout_s}
    chain = None
    if chain_file is not None:
        if "stream" in doc:
            raise InputError(
                f"--chain {chain_file}: SESSION.toml {p} is a streaming session (it has a "
                "[stream] table); with --chain give the offline session file the chain was "
                "calibrated from (the one `kinefuse run` wrote that chain.json for)"
            )
        chain = backend_module("stream", "kinefuse.pipelines.run.chain_file").read_chain(chain_file)
    with warnings.catch_warnings(record=True) as caught:  # one clean line each, not Python's
        warnings.simplefilter("always")  # file:line form
        if "stream" in doc:
            cfg = dataclasses.replace(config.load_stream_config(p), **overrides)
        else:
            cfg = config.stream_config_from_session(load_session(p), chain, **overrides)
    for w in caught:
        stderr().print(Text(f"kinefuse: warning: {one_line(str(w.message))}", style="yellow"))
    return cfg


def _out_files(out: Path, force: bool) -> None:
    if not out.name or out.is_dir():
        raise InputError(f"--out {out}: is a folder; give a file name such as {out / 'live'}")
    for target in (out.with_suffix(".npz"), out.with_suffix(".json")):
        if target.exists() and not force:
            raise FileExistsError(
                f"{target} already exists; pass --force to overwrite it, or choose another --out"
            )
    check_folder_usable(out.parent, "--out")  # written when the stream ends: checked now


def _kv_table(title: str, rows: list[tuple[str, str]], caption: str | None = None):
    t = Table(title=escape(title), caption=None if caption is None else escape(caption),
              caption_justify="left", box=box.SIMPLE, pad_edge=False, show_header=False)  # fmt: skip
    t.add_column("item", no_wrap=True)
    t.add_column("value", no_wrap=True)
    for k, v in rows:  # text, not rich markup (notes may hold "[stream]"-like brackets)
        t.add_row(escape(k), escape(v))
    return t


def _ms(v) -> str:
    return "–" if v is None else f"{v:.3f}"


def _stream_table(summary: Mapping):
    lat = summary.get("latency_ms") or {}
    rows = [
        ("output stream", str(summary.get("output_stream", "–"))),
        *([("joint-angle stream", summary["angles_stream"])] if summary.get("angles_stream") else []),
        ("outputs", str(summary.get("outputs", 0))),
        ("frames", str(summary.get("frames", 0))),
        ("latency p50 / p99 / max (ms)",
         f"{_ms(lat.get('p50'))} / {_ms(lat.get('p99'))} / {_ms(lat.get('max'))}"),
        ("timed outputs (start-up backlog not timed)",
         f"{lat.get('n', 0)} ({lat.get('catch_up_outputs', 0)})"),
    ]  # fmt: skip
    counters = summary.get("counters") or {}
    rows += [
        (name.replace("_", " "), str(n))
        for name, n in counters.items()
        if n and name not in ("outputs", "frames")
    ]
    missing = summary.get("missing") or []
    rows.append(("missing streams", ", ".join(missing) if missing else "none"))
    if summary.get("out"):
        rows.append(("written", str(summary["out"])))
    if summary.get("view_url"):
        v = summary.get("view") or {}
        rows.append(
            ("live view", f"{summary['view_url']} ({v.get('sent', 0)} frames sent to viewers)")
        )
    caption = "stopped by Ctrl-C (pending frames flushed)" if summary.get("interrupted") else None
    return _kv_table("kinefuse stream", rows, caption)


def _replay_table(summary: Mapping, rate: float):
    caption = (
        f"{summary.get('recording_s', 0.0):.1f} s of recording published in "
        f"{summary.get('duration_s', 0.0):.1f} s wall time (--rate {rate:g})"
    )
    if summary.get("interrupted"):
        caption += "; stopped by Ctrl-C"
    t = Table(title="kinefuse replay", caption=caption, caption_justify="left",
              box=box.SIMPLE_HEAD, pad_edge=False)  # fmt: skip
    t.add_column("stream", no_wrap=True)
    t.add_column("samples pushed", justify="right", no_wrap=True)
    for name, n in (summary.get("samples") or {}).items():
        t.add_row(escape(name), str(n))
    return t


_StreamSession = Annotated[
    Path,
    typer.Argument(
        metavar="SESSION.toml",
        help="Streaming session (with a stream table) or offline session "
        "(`kinefuse init-session`).",
    ),
]
_StreamDuration = _seconds(
    "--duration", "Stop after this wall time (default: Ctrl-C or --idle-timeout)."
)
_StreamIdleTimeout = _seconds("--idle-timeout", "Stop once no input sample arrived for this long.")
_StreamResolveTimeout = _seconds(
    "--resolve-timeout",
    "How long to look for the input streams (default: the session's resolve_timeout_s, 5 s).",
)
_StreamOut = Annotated[
    Path | None,
    typer.Option(
        "--out",
        "-o",
        metavar="FILE",
        help="Write the outputs to FILE.npz and the summary to FILE.json.",
    ),
]
_StreamForce = Annotated[
    bool, typer.Option("--force", "-f", help="Overwrite existing --out files.")
]
_StreamRecordInputs = _flag(
    "--record-inputs",
    "Also store the accepted input samples in FILE.npz (re-run the session "
    "offline with kinefuse.streaming.offline_causal); needs --out.",
)
_StreamWaitForReader = _seconds(
    "--wait-for-reader",
    "Wait up to this long for a reader of the output stream before "
    "starting (inputs are buffered meanwhile).",
)
_StreamNoStatus = _flag("--no-status", "No live status table on stderr.")
_StreamChain = Annotated[
    Path | None,
    typer.Option(
        "--chain",
        metavar="FILE",
        help="The calibrated IMU chain kinefuse run wrote for this session (OUT_DIR/chain.json): "
        "its segments, sensor axes, lengths and root, streamed without a camera (IMU-only "
        "live capture).",
    ),
]
_StreamView = _flag(
    "--view",
    "Serve a live 3-D view (skeleton, source per joint, latency) on "
    "http://127.0.0.1:PORT/ (loopback only; the address is printed). Viewers never "
    "slow the stream down.",
)
_StreamViewPort = Annotated[
    int,
    typer.Option("--view-port", metavar="PORT", help="Port of --view (0 = any free port)."),
]


def stream(
    session: _StreamSession,
    duration: _StreamDuration = None,
    idle_timeout: _StreamIdleTimeout = None,
    resolve_timeout: _StreamResolveTimeout = None,
    out: _StreamOut = None,
    force: _StreamForce = False,
    record_inputs: _StreamRecordInputs = False,
    wait_for_reader: _StreamWaitForReader = None,
    no_status: _StreamNoStatus = False,
    view: _StreamView = False,
    view_port: _StreamViewPort = 0,
    chain: _StreamChain = None,
    quiet: Quiet = False,
    json_file: Json = None,
) -> None:
    """Fuse live LSL streams online and publish the joints; Ctrl-C stops (frames are flushed).

    Inputs: PREFIX_imu_SEGMENT (type IMU) per segment and PREFIX_camera (type MoCap), see replay.

    Output: PREFIX_fused (type MoCap), one sample per camera frame (without a camera: per
    1/output_rate_hz); per joint JOINT_x/_y/_z and JOINT_std_x/_y/_z (m), JOINT_source (code)
    and JOINT_flags (bit mask), both codes listed in the stream's desc (docs/streaming.md).
    With --chain and calibrated segment frames also PREFIX_fused-angles (type Angles), deg, ISB,
    for each joint whose two segments have frames: JOINT_flexion/_adduction/_internal_rotation
    per shoulder, elbow, hip, knee and ankle; trunk_flexion/_lateral_bending/_axial_rotation.

    PREFIX: name_prefix of a streaming session (stream table), or an offline session's name.
    """
    for value, option in ((duration, "--duration"), (idle_timeout, "--idle-timeout"),
                          (resolve_timeout, "--resolve-timeout"),
                          (wait_for_reader, "--wait-for-reader")):  # fmt: skip
        _positive(value, option)
    if record_inputs and out is None:
        raise InputError("--record-inputs needs --out FILE (the inputs are stored in FILE.npz)")
    if not 0 <= view_port <= 65535:
        raise InputError(f"--view-port must be in [0, 65535], got {view_port}")
    cfg = _stream_session(session, resolve_timeout, chain)
    if out is not None:
        _out_files(out, force)
    check_json(json_file, force, (session,))
    if quiet:
        logging.getLogger("kinefuse.streaming").setLevel(logging.ERROR)
    summary = backend("stream")(
        cfg, duration, out, not (no_status or quiet), idle_timeout_s=idle_timeout,
        wait_for_reader_s=wait_for_reader, record_inputs=record_inputs,
        **({"view_port": view_port} if view else {}),
    )  # fmt: skip
    finish(summary, _stream_table, quiet=quiet, json_file=json_file, force=force)


def replay(
    recording: Annotated[
        str,
        typer.Argument(
            metavar="RECORDING",
            help="A file or folder `kinefuse.io.load` reads, or `demo` (built-in: 9 virtual IMUs "
            "at 100 Hz and a virtual camera at 30 Hz with outages, 12.5 s).",
        ),
    ],
    rate: Annotated[
        float,
        typer.Option("--rate", metavar="FACTOR", help="Speed-up factor (2 = twice real time)."),
    ] = 1.0,
    prefix: Annotated[
        str, typer.Option("--prefix", metavar="TEXT", help="Stream name prefix.")
    ] = "kinefuse",
    loop: _flag("--loop", "Start again at the end (timestamps keep increasing).") = False,
    duration: _seconds(
        "--duration",
        "Publish this much recording time (default: the recording once, or "
        "until Ctrl-C with --loop).",
    ) = None,
    no_raw: _flag("--no-raw", "Publish the orientation channels only (no acc_*, gyr_*).") = False,
    fmt: Annotated[
        str | None,
        typer.Option("--format", metavar="FORMAT", help="Reader of RECORDING (default: detected)."),
    ] = None,
    wait_for_consumers: _seconds(
        "--wait-for-consumers",
        "Before publishing, wait up to this long until every stream has a reader (once one "
        "has, 2 s more at most: a reader of some streams only does not hold the replay).",
    ) = None,
    quiet: Quiet = False,
    json_file: Json = None,
    force: JsonForce = False,
) -> None:
    """Publish a recording as live LSL streams, at its real rate or --rate times faster.

    PREFIX_imu_SEGMENT, one per IMU (type IMU): qw qx qy qz (when the recording has
    orientations: kinefuse stream needs them), acc_x/y/z m/s^2, gyr_x/y/z rad/s.

    PREFIX_camera (type MoCap): per joint JOINT_x/_y/_z in m (NaN if unseen), JOINT_available.

    Timestamps: the recording's, moved to the LSL clock and divided by --rate. Ctrl-C stops.
    """
    if not (math.isfinite(rate) and rate > 0):
        raise InputError(f"--rate: expected a speed-up factor > 0, got {rate:g}")
    _positive(duration, "--duration")
    _positive(wait_for_consumers, "--wait-for-consumers")
    if not prefix.strip():
        raise InputError("--prefix: expected a non-empty stream name prefix")
    if recording != "demo" and not Path(recording).exists():
        raise InputError(
            f"RECORDING {recording}: file not found (give a file or folder kinefuse.io.load "
            "reads, or `demo`)"
        )
    check_json(json_file, force, () if recording == "demo" else (Path(recording),))
    source = recording if recording == "demo" else Path(recording)
    if fmt is not None and fmt not in FORMATS:
        raise InputError(
            f"--format: unknown reader {fmt!r}; expected one of {', '.join(sorted(FORMATS))}"
        )
    if source != "demo" and fmt is None:
        detect_format(source)  # an unreadable recording fails here, before "Publishing"

    def ready() -> None:  # the recording was read and can be published
        if not quiet:
            stderr().print(
                f"Publishing {recording} as {prefix}_* LSL streams at {rate:g}x (Ctrl-C stops)..."
            )

    summary = backend("replay")(
        source, rate, prefix, loop, duration, include_raw=not no_raw,
        wait_for_consumers_s=wait_for_consumers, quiet=quiet, format=fmt, on_ready=ready,
    )  # fmt: skip
    finish(summary, lambda s: _replay_table(s, rate), quiet=quiet, json_file=json_file, force=force)
