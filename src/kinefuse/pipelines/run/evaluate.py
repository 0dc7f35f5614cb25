"""``kinefuse evaluate``: one method on any loadable recording that has a reference."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

from kinefuse.conventions import SEGMENTS
from kinefuse.exceptions import ConfigError, FormatError, InputError
from kinefuse.io import FORMATS, load
from kinefuse.pipelines.run.calibration import no_still_window
from kinefuse.pipelines.run.parameters import _CAMERA_METHODS
from kinefuse.pipelines.run.process import process_recording

__all__ = ["evaluate_recording"]


def evaluate_recording(
    path,
    method: str,
    parameters: Mapping | None = None,
    *,
    format: str | None = None,
    calibration: str | None = None,
    root: str | None = None,
    align: str | None = None,
    body_height_m: float | None = None,
):
    """Back-end of ``kinefuse evaluate``: one method on a recording with a reference.

    Parameters
    ----------
    path : str or Path
        Anything :func:`kinefuse.io.load` reads (a file or a dataset folder), with a reference
        (or a camera, which then serves as the reference, as in paper A).
    method : str
        A :mod:`kinefuse.methods` name.
    parameters : mapping, optional
        As ``[method.parameters]``; ``calibration``, ``root`` and ``align`` below override it.
    format : str, optional
        A :data:`kinefuse.io.FORMATS` key (default: detected).
    calibration : str, optional
        ``"auto"`` (default: ``"vision"`` with a camera the method fuses; else ``"static"``
        when the IMUs hold still for 2 s somewhere, ``"functional"`` when they never do, as a
        walk that starts at once; an IMU-only choice is in every table's label, e.g. "[functional
        calibration (auto), ...]"), ``"static"`` (a still pose in
        the IMU data), ``"functional"``, ``"vision"`` or ``"reference"`` (then axes *and*
        segment lengths come from the reference, and every table says "[calibrated on
        reference, lengths from reference, ...]").
    root : str, optional
        Where the chain starts (default ``"reference"``: the root joints, e.g. the hips, are
        taken as measured by the reference, as paper A measures the shoulder; not a
        calibration, but an input from the reference: labelled "[root from reference]").
    align : {"none", "rigid"}, optional
        ``"rigid"``: Kabsch-align the estimates to the reference before scoring (labelled).
    body_height_m : float, optional
        Body height for anthropometric segment lengths (Winter 2009).

    Returns
    -------
    EvaluationResult
        The method, the unfiltered IMU chain and the camera (if any) per joint.

    Raises
    ------
    InputError
        Unreadable file, no reference, no limb IMU, a method that needs a camera without one,
        no still window for static calibration.
    """
    if format is not None and format not in FORMATS:
        raise InputError(
            f"--format: unknown format {format!r}; expected one of {', '.join(sorted(FORMATS))}"
        )
    rec = _load_scorable(path, format, method)
    params = dict(parameters or {})
    if method not in _CAMERA_METHODS:
        if rec.vision is not None:
            rec = replace(rec, vision=None)
        params["root"] = root or params.get("root", "reference")
    elif root is not None:
        params["root"] = root
    if calibration not in (None, "auto"):
        params["calibration"] = calibration
    tags = []
    if "calibration" not in params:  # chosen here: the tables say which, if IMU-only
        why = "" if rec.vision is not None else no_still_window(rec.imu)
        params["calibration"] = "vision" if rec.vision is not None else (
            "functional" if why else "static")  # fmt: skip
        if params["calibration"] != "vision":
            tags.append(f"{params['calibration']} calibration (auto)")
    if params["calibration"] == "reference":
        params.setdefault("measured_lengths", True)
    if align is not None:
        params["align_to_reference"] = align
    try:
        out = process_recording(rec, method, params, body_height_m=body_height_m, tags=tags)
    except (ConfigError, InputError) as exc:
        raise InputError(f"{path}: {exc}{_evaluate_hint(str(exc), params)}") from None
    ev = out.evaluation()
    if ev is None:
        raise InputError(f"{path}: nothing to score: {out.notes[-1]}")
    return ev


def _evaluate_hint(message: str, params: Mapping) -> str:
    """What ``kinefuse evaluate`` (no session file) can do about an error whose advice names
    session keys or Python arguments: its own options."""
    if "declared_axes" in message or "[skeleton.axes]" in message or "needs a [camera]" in message:
        if params.get("calibration") != "reference":
            return (
                " (kinefuse evaluate takes no session file: --calibration reference calibrates "
                "from the reference, labelled so in every table; or write a session with "
                "`kinefuse init-session --from` and run it)"
            )
    return ""


def _load_scorable(path, format, method: str):
    """The recording, its canonical-segment IMUs only, with a reference (or the camera as one)."""
    try:
        rec = load(path, format=format)
    except FileNotFoundError as exc:
        raise InputError(f"{path}: {exc}") from None
    except FormatError:
        raise
    imu = {k: v for k, v in rec.imu.items() if k in SEGMENTS}
    if not rec.imu:
        if rec.vision is not None or rec.reference is not None:
            holds = "joint or marker positions only"
        elif (rec.metadata or {}).get("table") is not None:
            holds = "a table of other quantities (e.g. joint angles), no positions or IMU signals"
        else:
            holds = "no IMU signals"
        raise InputError(
            f"{path}: no IMU data: the file holds {holds} (kinefuse evaluate scores IMU methods; "
            "kinefuse.io.load reads it)"
        )
    if not imu:
        raise InputError(
            f"{path}: no IMU on a canonical segment (found {sorted(rec.imu)}); name the "
            "segments in a session ([imu.segments], `kinefuse init-session --from`)"
        )
    if rec.reference is None:
        if rec.vision is None:
            raise InputError(f"{path}: the recording has no reference to evaluate against")
        if method in _CAMERA_METHODS:
            raise InputError(
                f"{path}: method {method!r} needs a camera, and this recording's only joint "
                "stream is used as the reference; try 'imu-only' or 'paper-a'"
            )
        rec = replace(rec, reference=rec.vision)
    elif rec.vision is None and method in _CAMERA_METHODS:
        raise InputError(
            f"{path}: method {method!r} needs a camera, and this recording has none (only a "
            "reference, which kinefuse scores against and never feeds to a method); try "
            "'imu-only' or 'paper-a'"
        )
    rec = replace(rec, imu=imu)
    return rec
