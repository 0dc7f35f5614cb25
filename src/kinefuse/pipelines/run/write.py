"""Writing a session's results: :func:`run_session`, the back-end of ``kinefuse run``.

The joint positions (kinefuse joint CSV with per-sample source, filter branch, standard
deviation and coverage; TRC for OpenSim), the calibrated sensor orientations (OpenSense
``.sto``), the joint angles (CSV and ``.mot``), the HTML report and, with a reference, the
metrics; all staged and moved into the output folder as one set
(:class:`kinefuse.io.output_folder.OutputFolder`).
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from kinefuse.conventions import MODE_NAMES, SOURCE_KINDS, SOURCE_NAMES
from kinefuse.evaluation import ReportOptions, write_report
from kinefuse.evaluation.angles import angle_extremes_table, angle_section, write_angle_report
from kinefuse.evaluation.report import REPORT_NAME
from kinefuse.evaluation.tables import to_html
from kinefuse.exceptions import ConfigError
from kinefuse.io import ImuStream, JointStream, write_joint_csv, write_trc
from kinefuse.io._write import printf_rows, write_text_safely
from kinefuse.io.mot import write_mot
from kinefuse.io.opensim import write_opensense_sto
from kinefuse.io.output_folder import OutputFolder
from kinefuse.kinematics import angle_components
from kinefuse.pipelines.run.chain_file import CHAIN_FILE
from kinefuse.pipelines.run.output import SessionOutput
from kinefuse.pipelines.run.process import process_recording
from kinefuse.pipelines.run.streams import load_streams
from kinefuse.pipelines.run.timeline import COVERAGE_NOTE, coverage_counts, coverage_table
from kinefuse.session_file import SessionConfig, load_session

__all__ = ["RunResult", "output_paths", "run_session"]


@dataclass(eq=False)
class RunResult(Mapping):
    """What :func:`run_session` did: the files written, the notes, the scores.

    Also a read-only mapping of its fields (``angles_deg`` and ``evaluation`` only when set),
    the form ``kinefuse run --json`` writes.

    Attributes
    ----------
    outputs : list of Path
        Every file written (joints CSV and TRC, orientations, angles).
    notes : list of str
        What was done (calibration, lengths, alignments) and warnings.
    provenance : dict
        Which data calibrated what (also in ``provenance.json``).
    coverage : dict
        :func:`~kinefuse.pipelines.run.timeline.coverage_counts` per joint.
    warnings : list of str
        Problems the user must see.
    tables : list of ResultTable
        The coverage table.
    angles_deg : dict or None
        Flexion range per joint, deg (with joint angles).
    evaluation : EvaluationResult or None
        The scores (with a reference in the output's frame).
    report : Path or None
        The HTML report.
    """

    outputs: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    provenance: dict = field(default_factory=dict)
    coverage: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    tables: list = field(default_factory=list)
    angles_deg: dict | None = None
    evaluation: object = None
    report: Path | None = None

    def _keys(self) -> list[str]:
        optional = ("angles_deg", "evaluation")
        return [
            f.name
            for f in fields(self)
            if f.name not in optional or getattr(self, f.name) is not None
        ]

    def __getitem__(self, key: str):
        if key not in self._keys():
            raise KeyError(key)
        return getattr(self, key)

    def __iter__(self) -> Iterator[str]:
        return iter(self._keys())

    def __len__(self) -> int:
        return len(self._keys())


def _outputs(out_dir: Path, stem: str) -> dict[str, Path]:
    """Every result ``kinefuse run`` may write into ``out_dir`` (all replaced as one set)."""
    return {
        "csv": out_dir / f"{stem}_joints.csv",
        "trc": out_dir / f"{stem}_joints.trc",
        "angles_csv": out_dir / f"{stem}_angles.csv",
        "mot": out_dir / f"{stem}_angles.mot",
        "orientations_sto": out_dir / f"{stem}_orientations.sto",
        "report": out_dir / REPORT_NAME,
        "metrics": out_dir / "metrics.json",
        "provenance": out_dir / "provenance.json",
        "chain": out_dir / CHAIN_FILE,
        "figures": out_dir / "figures",
    }


def output_paths(cfg, out_dir=None) -> tuple[Path, ...]:
    """Every path :func:`run_session` may write for ``cfg`` (``--json`` may be none of them)."""
    return tuple(_outputs(Path(cfg.out_dir if out_dir is None else out_dir), _stem(cfg)).values())


def _stem(cfg) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "-" for ch in cfg.name) or "session"


def run_session(path, out_dir=None, force: bool = False, stage=None) -> RunResult:
    """Back-end of ``kinefuse run``: process the recording a session file describes.

    Parameters
    ----------
    path : str or Path or SessionConfig
        Session TOML (:func:`kinefuse.session_file.load_session`), or an already validated one.
    out_dir : str or Path, optional
        Output folder (default the session's ``out_dir``); created if needed.
    force : bool
        Replace the results of an earlier run in ``out_dir``.
    stage : callable, optional
        ``stage(text)`` is called as each stage starts (reading, processing, writing, the
        report), e.g. to show it on a progress bar.

    Returns
    -------
    RunResult
        ``outputs`` (paths written), ``evaluation`` (with a reference), ``report``, ``notes``,
        ``provenance``, ``coverage``, ``warnings``, ``tables``, ``angles_deg``; also readable
        as a mapping (``result["outputs"]``), as the CLI's ``--json`` writes it.

    Raises
    ------
    ConfigError
        Invalid session, unknown format, unreadable file, unknown sensor, wrong units, no
        valid samples, a method that needs a camera without one.
    InputError
        Data that cannot be processed (the message says what and where); an output folder
        that is a file, not writable, or whose outputs would overwrite an input (checked
        before any processing).
    FileExistsError
        Any earlier result (joints CSV/TRC, ``report.html``, ``metrics.json``, ``figures/``)
        exists and ``force`` is False (checked before any processing; nothing is written).

    Notes
    -----
    Outputs in ``out_dir``: ``<name>_joints.csv`` (kinefuse joint CSV: ``t_s``, per joint
    ``_x/_y/_z`` in m, ``_available``, ``_source`` (:data:`kinefuse.conventions.SOURCE_NAMES`),
    ``_mode`` (:data:`kinefuse.conventions.MODE_NAMES`, -1 without a filter), ``_std_m_x/y/z``
    (m)); ``<name>_joints.trc`` (OpenSim, m); with a calibration ``<name>_orientations.sto``
    (OpenSense orientation table of the calibrated sensor orientations, input of OpenSense IK);
    with a reference ``report.html``, ``figures/``, ``metrics.json``.

    The results are written atomically (:class:`kinefuse.io.output_folder.OutputFolder`):
    staged in a hidden temporary folder and moved into ``out_dir`` only when complete, so an
    interrupted or failed run leaves the previous results untouched. Files get the mode the
    user's umask gives.
    """
    cfg = path if isinstance(path, SessionConfig) else load_session(path)
    out_dir = Path(cfg.out_dir if out_dir is None else out_dir)
    targets = _outputs(out_dir, _stem(cfg))
    folder = OutputFolder(
        out_dir,
        [p.name for p in targets.values()],
        force=force,
        protect=cfg.inputs,
        what="output folder",
    )
    try:
        result = _run_and_write(cfg, folder.path, stage or (lambda text: None), out_dir)
        folder.commit()
    except BaseException:
        folder.discard()
        raise
    final = {p: out_dir / p.name for p in result.outputs}
    result.outputs = [final[p] for p in result.outputs]
    if result.report is not None:
        result.report = out_dir / result.report.name
    return result


def _run_and_write(cfg, folder: Path, stage, out_dir: Path) -> RunResult:
    """Process the session and write every result into ``folder`` (the staging folder, moved
    to ``out_dir`` when complete)."""
    targets = _outputs(folder, _stem(cfg))
    params = cfg.processing_parameters()
    strict = params.get("strict_units", True)
    stage(f"reading {_input_size(p for p in cfg.inputs if Path(p) != Path(cfg.path))}")
    recording, notes = load_streams(cfg, strict_units=bool(strict))
    stage(f"calibrating, {cfg.method.name}")
    try:
        out = process_recording(
            recording,
            cfg.method.name,
            params,
            lengths=cfg.skeleton.lengths_m,
            body_height_m=cfg.skeleton.body_height_m,
        )
    except ConfigError as exc:
        raise ConfigError(f"{cfg.path.name}: {exc}") from None
    out.notes[:0] = notes
    out.warnings[:0] = [n.removeprefix("WARNING: ") for n in notes if n.startswith("WARNING: ")]
    stage("writing the joints, angles and orientations")
    cov_table = coverage_table(out)  # printed, and in the report
    result = RunResult(
        outputs=_write_positions(out, cfg, targets),
        notes=out.notes,
        provenance=out.provenance,
        coverage=coverage_counts(out),
        warnings=list(out.warnings),
        tables=[cov_table],
    )
    if out.sensor_orientations:
        result.outputs.append(_write_orientations(out, targets))
    if out.chain_description is not None:
        text = json.dumps(out.chain_description, indent=1) + "\n"
        result.outputs.append(write_text_safely(targets["chain"], text))
        out.notes.append(
            f"{CHAIN_FILE}: the calibrated chain; kinefuse stream {_shown(cfg.path)} --chain "
            f"{_shown(out_dir / CHAIN_FILE)} runs it on live IMU streams (docs/streaming.md)"
        )
    if out.angles:
        result.outputs += _write_angles(out, targets, cfg, False)
        result.tables.append(angle_extremes_table(out.angles))
        result.angles_deg = {
            j: {
                "flexion_min": float(np.nanmin(a[:, 0])),
                "flexion_max": float(np.nanmax(a[:, 0])),
            }
            for j, a in out.angles.items()
        }
    stage("writing the report")
    _write_report(out, cfg, folder, result, cov_table)
    return result


def _input_size(paths) -> str:
    """``"name (12 MB)"`` of the session's inputs (folders: their files)."""
    parts = []
    for p in paths:
        p = Path(p)
        files = [f for f in p.rglob("*") if f.is_file()] if p.is_dir() else [p]
        size = sum(f.stat().st_size for f in files if f.exists())
        parts.append(f"{p.name} ({size / 1e6:.0f} MB)" if size >= 1e6 else p.name)
    return ", ".join(parts)


def _write_positions(out: SessionOutput, cfg, targets: Mapping[str, Path]) -> list[Path]:
    """The joint CSV (positions, availability, source, mode, std, coverage) and the TRC."""
    stream = JointStream(
        t_s=out.t_s,
        position_m=out.position,
        available=out.available,
        joints=out.joints,
        frame=out.frame,
    )
    extra = {"source": out.source, "mode": out.mode, "std_m": out.std_m}
    for name, v in out.coverage.items():  # "imu thigh_r" (T,) -> imu_thigh_r_covered
        extra[f"{name.replace(' ', '_')}_covered"] = v.astype(np.int8)
    csv = write_joint_csv(
        targets["csv"],
        stream,
        extra,
        metadata={
            "session": cfg.name,
            "method": cfg.method.name,
            "root": out.root,
            "source_codes": ", ".join(
                f"{k}={v} ({SOURCE_KINDS[k]})" for k, v in SOURCE_NAMES.items()
            ),
            "mode_codes": ", ".join(f"{k}={v}" for k, v in MODE_NAMES.items())
            + ", -1=no filter (the method filters nothing)",
            "std_m": "1-sigma position uncertainty of the filter, m"
            + (
                "; empty where the method gives none"
                if np.isfinite(out.std_m).any()
                else f"; empty: {cfg.method.name} gives none"
            ),
            "available": "1 where the inputs the method needs cover the sample (else the "
            "position, if any, is a prediction)",
            "covered": "<stream>_covered: 1 where that input stream has data at the sample",
        },
    )
    trc = write_trc(targets["trc"], stream, note=f"root: {out.root}; frame: {out.frame}")
    return [csv, trc]


def _write_orientations(out: SessionOutput, targets: Mapping[str, Path]) -> Path:
    """The calibrated sensor orientations as an OpenSense ``.sto`` (input of OpenSense IK)."""
    imus = {
        s: ImuStream(t_s=out.t_s, q_world_from_sensor=q, name=s)
        for s, q in out.sensor_orientations.items()
    }
    sto = write_opensense_sto(targets["orientations_sto"], imus)
    out.notes.append(
        f"OpenSense: {sto.name} holds the calibrated sensor orientations (heading corrections "
        f"applied, frame {out.frame}) for OpenSense IK; for a z-up world set "
        "sensor_to_opensim_rotations = -1.5707963 0 0 in the IMU IK setup"
    )
    return sto


def _write_report(out: SessionOutput, cfg, folder: Path, result: RunResult, cov_table) -> None:
    """The HTML report: scores and figures with a reference, else the joint angles; the
    warnings above the notes, the coverage per joint as a table (not as notes)."""
    title = f"kinefuse: {cfg.name} ({cfg.method.name})"
    notes = [n for n in out.notes if not n.startswith(COVERAGE_NOTE)]
    coverage = f"<section><h2>Coverage</h2>{to_html(cov_table)}</section>"
    ev = out.evaluation()
    if ev is not None:
        result.evaluation = ev
        result.report = write_report(
            folder,
            ev,
            out.trajectories(),
            out.reference,
            out.t_s,
            modes={ev.methods[0]: out.mode} if np.any(out.mode >= 0) else None,
            sources={ev.methods[0]: out.source},
            options=ReportOptions(
                title=title,
                notes=notes,
                warnings=result.warnings,
                # east/north/up only in an ENU frame (e.g. not a Vicon frame's x, y, z)
                axis_labels=("East", "North", "Up")
                if out.frame.startswith("ENU")
                else ("X", "Y", "Z"),
                skeleton_edges=out.edges or None,
                sections=[coverage, angle_section(out.t_s, out.angles, folder / "figures")],
                extra_metrics={"provenance": out.provenance},
            ),
        )
    else:
        result.report = write_angle_report(
            folder,
            out.t_s,
            out.angles,
            title=title,
            notes=notes,
            warnings=result.warnings,
            sections=[coverage],
            provenance=out.provenance,
            unscored=(
                "reference given, not scored (see the notes)"
                if str(out.provenance.get("alignment", "")).startswith("none (")
                else "no reference"
            ),
        )


def _shown(path) -> str:
    """``path`` as a command typed here would take it: relative to the working folder when
    below it, else absolute."""
    p = Path(path).resolve()
    try:
        return p.relative_to(Path.cwd().resolve()).as_posix()
    except ValueError:
        return str(p)


def _angle_rows(t_s, columns: Sequence) -> list[str]:
    """The rows of the joint-angle CSV: time as its shortest round-trip ``repr``, each angle
    with 4 decimals, an empty field where not finite (one pass: :func:`printf_rows`)."""
    return printf_rows([t_s, *columns], ",".join(["%r"] + ["%.4f"] * len(columns)), nan="")


def _write_angles(out: SessionOutput, targets: Mapping[str, Path], cfg, force: bool) -> list:
    """Joint angles next to the positions: CSV (``t_s`` + one column per angle) and ``.mot``."""
    cols = {
        f"{j}_{c}_deg": a[:, k]
        for j, a in out.angles.items()
        for k, c in enumerate(angle_components(j))
    }
    head = [
        "# kinefuse joint angles (deg), ISB conventions (Wu et al. 2002/2005, Grood & Suntay 1983)",
        f"# session: {cfg.name}",
        f"# method: {cfg.method.name}",
        f"# calibration: {out.provenance.get('calibration')}",
        f"# root: {out.root}",
        f"# frame: {out.frame}",
        "t_s," + ",".join(cols),
    ]
    rows = _angle_rows(out.t_s, list(cols.values()))
    csv = write_text_safely(targets["angles_csv"], "\n".join(head + rows) + "\n", force=force)
    mot = write_mot(
        targets["mot"],
        out.t_s,
        {k[: -len("_deg")]: v for k, v in cols.items()},
        name=f"{cfg.name} joint angles",
        metadata={
            "convention": "ISB (Wu 2002/2005), flexion first",
            "calibration": str(out.provenance.get("calibration")),
            "root": out.root,
            "frame": out.frame,
        },
        force=force,
    )
    return [csv, mot]
