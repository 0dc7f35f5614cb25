"""The output timeline and coverage: which input backs each output sample (issue 12).

The output timeline follows the root stream (camera or reference) or the IMUs, resampled to
``rate_hz`` and extended over the span the IMUs cover; :func:`apply_coverage` then marks every
output sample available only where the inputs the method needs cover it.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from kinefuse import methods
from kinefuse._validation import finite_rows
from kinefuse.conventions import SOURCE_BRIDGED, SOURCE_IMU, SOURCE_KINDS, SOURCE_PREDICTED
from kinefuse.evaluation.tables import ResultTable, TableRow
from kinefuse.exceptions import InputError
from kinefuse.io import resample_coverage, resample_positions
from kinefuse.orientation.resample import MAX_GAP_S, default_max_gap_s
from kinefuse.pipelines.run.output import SessionOutput

__all__ = [
    "COVERAGE_NOTE",
    "COVERAGE_WARN_FRACTION",
    "IMU_MAX_GAP_S",
    "ROOT_MAX_GAP_S",
    "apply_coverage",
    "coverage_counts",
    "coverage_table",
    "nearest_samples",
    "sample_joint",
]

_CAMERA_METHODS = methods.names(needs="camera")


#: How the per-joint coverage notes begin (the report shows them as a table instead).
COVERAGE_NOTE = "coverage "


def _timeline(t_src: np.ndarray, rate_hz: float | None) -> np.ndarray:
    if rate_hz is None or t_src.size < 2:
        return t_src
    src_rate = 1.0 / float(np.median(np.diff(t_src)))
    if abs(src_rate - rate_hz) <= 0.05 * rate_hz:
        return t_src
    n = int(np.floor((t_src[-1] - t_src[0]) * rate_hz + 1e-9)) + 1
    return t_src[0] + np.arange(n) / rate_hz


def sample_joint(stream, joint: str, t: np.ndarray, *, fill: bool) -> np.ndarray:
    """Positions of one joint at ``t``: linear interpolation (across gaps if ``fill``)."""
    p = stream.position(joint)
    ok = np.all(np.isfinite(p), axis=1)
    if not np.any(ok):
        return np.full((t.size, 3), np.nan)
    if fill:
        return np.stack([np.interp(t, stream.t_s[ok], p[ok, k]) for k in range(3)], axis=-1)
    out, _ = resample_positions(stream.t_s, p, t)
    return out


def nearest_samples(t: np.ndarray, t_frames: np.ndarray) -> np.ndarray:
    """``(T,)`` bool: the samples of ``t`` that are the nearest to a frame of ``t_frames``
    (frames within half a step of ``t``'s span). All True for frames about as dense as ``t``
    or denser (median step up to 1.25 of ``t``'s: timestamp jitter would otherwise leave
    samples out); for a sparser stream, one sample per frame: where it measured, not where
    ``t`` falls between its frames."""
    t = np.asarray(t, dtype=float)
    f = np.asarray(t_frames, dtype=float)
    if t.size < 2 or f.size < 2 or np.median(np.diff(f)) <= 1.25 * np.median(np.diff(t)):
        return np.ones(t.size, dtype=bool)
    mask = np.zeros(t.size, dtype=bool)
    half = 0.5 * float(np.median(np.diff(t)))
    f = f[(f >= t[0] - half) & (f <= t[-1] + half)]
    i = np.clip(np.searchsorted(t, f), 1, t.size - 1)
    i -= (f - t[i - 1]) <= (t[i] - f)
    mask[i] = True
    return mask


#: Longest interval between two IMU orientation samples interpolated across, s (SLERP), or 1.5
#: steps of a stream sampled more sparsely (:func:`kinefuse.orientation.resample.default_max_gap_s`):
#: a 50 Hz sensor that drops a packet leaves 40 ms, covered.
IMU_MAX_GAP_S = MAX_GAP_S
#: Longest gap of the root stream (camera or reference root joints) bridged by linear
#: interpolation, s; beyond it, or outside the stream, the chain has no root.
ROOT_MAX_GAP_S = 1.0
#: A joint whose available fraction is below this gets a coverage warning.
COVERAGE_WARN_FRACTION = 0.95


def _valid_span(t: np.ndarray, ok: np.ndarray) -> tuple[float, float] | None:
    idx = np.flatnonzero(ok)
    return None if idx.size == 0 else (float(t[idx[0]]), float(t[idx[-1]]))


def _imu_span(st) -> tuple[float, float] | None:
    return _valid_span(st.t_s, np.all(np.isfinite(st.q_world_from_sensor), axis=1))


def _stream_span(stream) -> tuple[float, float] | None:
    return _valid_span(stream.t_s, np.any(stream.available, axis=1))


def _check_overlap(recording, root_stream, root_name: str) -> None:
    """Streams that never overlap in time are an error naming the spans (not a calibration one)."""
    spans = {seg: _imu_span(st) for seg, st in recording.imu.items()}
    common = (max(a for a, _ in spans.values()), min(b for _, b in spans.values()))
    if common[0] > common[1]:
        listed = ", ".join(f"{seg} {a:.2f}-{b:.2f} s" for seg, (a, b) in spans.items())
        raise InputError(
            f"the IMU streams do not overlap in time ({listed}): no instant has every mapped "
            "sensor; check the files' clocks or map sensors of one recording"
        )
    root = _stream_span(root_stream)
    if root is None or root[0] > common[1] or root[1] < common[0]:
        where = "no valid sample" if root is None else f"{root[0]:.2f}-{root[1]:.2f} s"
        raise InputError(
            f"the IMU streams ({common[0]:.2f}-{common[1]:.2f} s) and the {root_name} "
            f"({where}) do not overlap in time; check the clocks (time offset) of the files"
        )


def _extend_to_imu(t: np.ndarray, recording) -> np.ndarray:
    """The root timeline extended (same step) over the span the IMUs cover; never cut."""
    if t.size < 2:
        return t
    spans = [sp for sp in (_imu_span(st) for st in recording.imu.values()) if sp is not None]
    a, b = min(sp[0] for sp in spans), max(sp[1] for sp in spans)
    dt = float(np.median(np.diff(t)))
    n_before = int(np.floor((t[0] - a) / dt + 1e-9)) if a < t[0] - 0.5 * dt else 0
    n_after = int(np.floor((b - t[-1]) / dt + 1e-9)) if b > t[-1] + 0.5 * dt else 0
    if not (n_before or n_after):
        return t
    before = t[0] - dt * np.arange(n_before, 0, -1)
    after = t[-1] + dt * np.arange(1, n_after + 1)
    return np.concatenate([before, t, after])


def _covered(t_src, p, t: np.ndarray, max_gap_s: float | None = None) -> np.ndarray:
    return resample_coverage(t_src, finite_rows(p), t, max_gap_s=max_gap_s)


def _input_coverage(recording, sk, root_stream, t: np.ndarray, joints):
    """Per-sample coverage of the chain's inputs on ``t``.

    Returns
    -------
    coverage : dict
        ``"imu <segment>"`` (T,) per IMU; ``"imu"`` (T, J): every IMU of the joint's chain;
        ``"root"`` (T, J): the root stream has the chain's root joint there (usual sampling).
    root_ok : ndarray of bool, shape (T, J)
        The root is usable: data, or a gap of at most :data:`ROOT_MAX_GAP_S` interpolated
        across (never extrapolated).
    inputs : dict of str -> tuple of str
        Per joint, the ``"imu <segment>"`` keys of ``coverage`` its position depends on (its
        chain's IMUs, and the pelvis IMU when it places the root).
    """
    cov: dict[str, np.ndarray] = {}
    extra = [s for s in (sk.root_segment,) if s and s in recording.imu and root_stream is None]
    for seg in (*sk.segments, *extra):
        st = recording.imu[seg]
        q = st.q_world_from_sensor
        # the chain's orientations are SLERPed across the same gaps (default_max_gap_s):
        # dropped packets of a wireless sensor are covered, a longer dropout is not
        cov[f"imu {seg}"] = (
            _covered(st.t_s, q, t, default_max_gap_s(st.t_s))
            if st.t_s.size > 1
            else np.isin(t, st.t_s)
        )
    seg_of = dict(zip(sk.distal, sk.segments, strict=True))
    parent = {
        s: (sk.segments[p] if p >= 0 else None)
        for s, p in zip(sk.segments, sk.parents, strict=True)
    }
    T = t.size
    imu = np.ones((T, len(joints)), bool)
    root = np.ones((T, len(joints)), bool)
    root_ok = np.ones((T, len(joints)), bool)
    step = 0.0
    if root_stream is not None and root_stream.t_s.size > 1:
        step = float(np.median(np.diff(root_stream.t_s)))
    inputs = {}
    for j, joint in enumerate(joints):
        s, used = seg_of[joint], []
        while s is not None:
            imu[:, j] &= cov[f"imu {s}"]
            used.append(f"imu {s}")
            top, s = s, parent[s]
        r = sk.proximal[sk.segments.index(top)]
        if root_stream is None:  # fixed root, or hips from the pelvis IMU (its coverage)
            for seg in extra:
                root[:, j] &= cov[f"imu {seg}"]
                used.append(f"imu {seg}")
            root_ok[:, j] = root[:, j]
        elif r in root_stream.joints:
            p = root_stream.position(r)
            root[:, j] = _covered(root_stream.t_s, p, t)
            root_ok[:, j] = _covered(root_stream.t_s, p, t, max(ROOT_MAX_GAP_S, 1.5 * step))
        inputs[joint] = tuple(used)
    cov["imu"], cov["root"] = imu, root
    return cov, root_ok, inputs


def apply_coverage(
    out: SessionOutput,
    coverage: Mapping,
    root_ok: np.ndarray,
    joints,
    method: str,
    root_name: str = "root",
    inputs: Mapping | None = None,
) -> None:
    """Set ``available``, ``coverage`` and the predicted source code of ``out`` in place.

    A sample is *available* when its position is finite and the inputs of the method back
    it: the IMUs of the joint's chain and the chain's root (``paper-a``, ``imu-only``), that
    or the camera (the camera methods), the camera (``camera-only``). Elsewhere the source is
    :data:`~kinefuse.conventions.SOURCE_PREDICTED` and ``available`` is False, whatever the
    filter predicted. An IMU-chain sample whose root was interpolated across a gap of the
    root stream is ``SOURCE_BRIDGED``. Warnings are added for joints below
    :data:`COVERAGE_WARN_FRACTION`: they name the joint's inputs with gaps (``inputs``, per
    joint the ``"imu <segment>"`` keys it depends on; None: every IMU) and count the other
    samples as predicted or without an estimate.
    """
    cols = [list(joints).index(j) for j in out.joints]
    T, J = out.position.shape[:2]
    cov = {k: (v if v.ndim == 1 else v[:, cols]) for k, v in coverage.items()}
    chain_ok = cov["imu"] & root_ok[:, cols]
    finite = np.all(np.isfinite(out.position), axis=-1)
    cam = np.zeros((T, J), bool) if out.camera is None else np.all(np.isfinite(out.camera), -1)
    if out.camera is not None:
        cov["camera"] = cam
    if out.reference is not None:
        cov["reference"] = np.all(np.isfinite(out.reference), axis=-1)
    if method == "camera-only":
        backed = cam
    elif method in _CAMERA_METHODS:
        backed = chain_ok | cam
    else:
        backed = chain_ok
    out.available = finite & backed
    out.source = np.where(finite & ~backed, SOURCE_PREDICTED, out.source).astype(np.int64)
    root_gap = out.available & chain_ok & ~cov["root"] & (out.source == SOURCE_IMU)
    out.source[root_gap] = SOURCE_BRIDGED  # root interpolated across a gap of its stream
    out.coverage = cov
    span = f"{out.t_s[0]:.2f}-{out.t_s[-1]:.2f} s" if T else "no samples"
    for j, joint in enumerate(out.joints):
        frac = float(np.mean(out.available[:, j])) if T else 0.0
        if frac >= COVERAGE_WARN_FRACTION:
            continue
        label = {"root": f"the chain's root ({root_name})"}
        mine = None if inputs is None else inputs.get(joint)
        short = [
            k.split(" ", 1)[1] + " IMU" if k.startswith("imu ") else label.get(k, k)
            for k, v in cov.items()
            if k != "reference" and k != "imu" and (mine is None or not k.startswith("imu ")
                                                     or k in mine)
            and np.mean(v if v.ndim == 1 else v[:, j]) < 0.999
        ]  # fmt: skip
        why = f"; not covered by: {', '.join(short)}" if short else ""
        n_none = int(np.sum(~finite[:, j]))
        n_pred = int(np.sum(finite[:, j] & ~backed[:, j]))
        rest = [f"{n_pred} predicted (source 'predicted', available = 0)"] if n_pred else []
        rest += [f"{n_none} without an estimate (NaN)"] if n_none else []
        msg = (
            f"{joint}: only {frac:.0%} of the {T} output samples ({span}) are backed by the "
            f"inputs{why}; the other samples: {' and '.join(rest)}"
        )
        out.warnings.append(msg)
        out.notes.append(f"WARNING: {msg}")
    n_pred = int(np.sum(finite & ~backed))
    if n_pred and out.reference is not None:
        out.notes.append(
            f"metrics: the {n_pred} predicted joint samples (no input backs them) are excluded; "
            "every method is scored on the samples it outputs as available"
        )
    for joint, row in coverage_counts(out).items():
        kinds = ", ".join(f"{row[k]} {k}" for k in ("measured", "fused", "bridged", "predicted"))
        streams = ", ".join(f"{k[:-8]} {v}" for k, v in row.items() if k.endswith(" covered"))
        out.notes.append(
            f"{COVERAGE_NOTE}{joint}: {row['available']} of {row['samples']} samples available "
            f"({kinds}); covered by {streams}"
        )
    if out.reference is not None and T:
        frac = float(np.mean(np.any(cov["reference"], axis=1)))
        if frac < COVERAGE_WARN_FRACTION:
            msg = (
                f"the reference covers only {frac:.0%} of the {T} output samples ({span}); "
                "the metrics are computed on that part only"
            )
            out.warnings.append(msg)
            out.notes.append(f"WARNING: {msg}")


def coverage_counts(out: SessionOutput) -> dict:
    """Per joint: samples, available, each source kind and each stream's covered samples."""
    kinds = ("measured", "fused", "bridged", "predicted")
    res = {}
    for j, joint in enumerate(out.joints):
        src = out.source[:, j]
        row = {"samples": int(src.size), "available": int(np.sum(out.available[:, j]))}
        for kind in kinds:
            codes = [c for c, k in SOURCE_KINDS.items() if k == kind]
            row[kind] = int(np.sum(np.isin(src, codes)))
        row["none"] = int(np.sum(src < 0))
        for name, v in out.coverage.items():
            if name != "imu" and not name.startswith("imu "):
                row[f"{name} covered"] = int(np.sum(v[:, j]))
        row["imu covered"] = int(np.sum(out.coverage["imu"][:, j]))
        res[joint] = row
    return res


def coverage_table(out: SessionOutput):
    """:func:`coverage_counts` as a :class:`~kinefuse.evaluation.tables.ResultTable`."""
    counts = coverage_counts(out)
    headers = tuple(next(iter(counts.values())))
    return ResultTable(
        title="Coverage per joint (output samples)",
        label_headers=("Joint",),
        value_headers=headers,
        rows=tuple(
            TableRow((joint,), tuple(float(row[h]) for h in headers))
            for joint, row in counts.items()
        ),
        digits=0,
        best=False,  # counts: smaller is not better
        notes=(
            "available = backed by the inputs the method needs; measured = one stream (IMU "
            "chain or camera), fused = camera-fused, bridged = outage bridged by the learned "
            "model, predicted = no input (the filter's prediction, never available).",
        ),
    )


def _output_timeline(recording, method: str, params: Mapping, segs, root_kind: str):
    """The output timeline, s, and the root stream (camera or reference, None for the IMUs).

    30 Hz by default for ``paper-a`` and the camera methods, else the root stream's own rate;
    on a root stream, extended over the span the IMUs cover.
    """
    root_stream = None
    if root_kind == "vision":
        root_stream = recording.vision
    elif root_kind == "reference":
        root_stream = recording.reference
    default_rate = 30.0 if method in ("paper-a", *_CAMERA_METHODS) else None
    rate = params.get("rate_hz", default_rate)
    if root_stream is not None:
        t = _timeline(root_stream.t_s, None if rate is None else float(rate))
        _check_overlap(recording, root_stream, "camera" if root_kind == "vision" else root_kind)
        return _extend_to_imu(t, recording), root_stream
    t0 = max(float(recording.imu[s].t_s[0]) for s in segs)
    t1 = min(float(recording.imu[s].t_s[-1]) for s in segs)
    base = recording.imu[segs[0]].t_s
    base = base[(base >= t0 - 1e-9) & (base <= t1 + 1e-9)]
    if rate is None:
        return _regular(base), None
    return _timeline(base, float(rate)), None


def _regular(t: np.ndarray) -> np.ndarray:
    """``t`` where its steps are regular, else a uniform grid over its span (ends kept) at about
    its median step: an IMU that drops packets leaves no holes in the output's frames (TRC and
    ``.mot`` readers expect a constant rate; the coverage columns say what the inputs covered)."""
    if t.size < 3:
        return t
    step = float(np.median(np.diff(t)))
    if step <= 0 or np.max(np.diff(t)) <= 1.5 * step:
        return t
    return np.linspace(t[0], t[-1], int(np.floor((t[-1] - t[0]) / step + 0.5)) + 1)


def _sample_joints(stream, joints, t: np.ndarray) -> np.ndarray:
    """``(T, J, 3)`` positions of ``joints`` on ``t`` (NaN for joints the stream lacks)."""
    nan = np.full((t.size, 3), np.nan)
    return np.stack(
        [sample_joint(stream, j, t, fill=False) if j in stream.joints else nan for j in joints],
        axis=1,
    )
