"""``kinefuse demo``: both papers' pipelines on packaged data, offline, with a report.

The packaged CMU clip (subject 02, trial 08, swordplay, 12.5 s; :func:`kinefuse.data.demo_motion`)
drives nine virtual IMUs and a virtual Kinect with noise and outages
(:func:`kinefuse.sim.virtual_recording`, fixed seed). On that recording:

* paper A (Sun 2024): KF, FIR and EM-KF/FIR on the elbows and wrists of both arms, from the
  IMU chain with the shoulder taken from the camera (:func:`kinefuse.pipelines.upper_limb`);
* paper B (Xu 2023): ELM/FIR, ELM/KF, IMU only, camera only (and ``kinefuse`` when registered)
  on the eight joints (:func:`kinefuse.pipelines.vision_assisted_from_recording`).

:func:`run_scenario` does this for any recording with the nine IMUs and a camera (the CMU-driven
scenarios of :mod:`kinefuse.apps.experiments` use it too); :func:`run_demo` is the
back-end of ``kinefuse demo``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kinefuse import _compile
from kinefuse.apps._common import labelled_runs, timed_quietly
from kinefuse.conventions import MODE_NAMES, PAPER_B_JOINTS, SOURCE_NAMES
from kinefuse.data import demo_motion
from kinefuse.evaluation import evaluate, tables
from kinefuse.evaluation.report import REPORT_NAME, ReportOptions, write_report
from kinefuse.exceptions import InputError
from kinefuse.io.output_folder import OutputFolder
from kinefuse.io.recording import Recording
from kinefuse.kinematics import calibrate, chain_positions, full_body
from kinefuse.kinematics import upper_limb as upper_limb_skeleton
from kinefuse.pipelines import upper_limb, vision_assisted_from_recording
from kinefuse.pipelines.labels import PAPER_A_LABELS, paper_b_methods
from kinefuse.progress import progress
from kinefuse.sim import virtual_recording
from kinefuse.sim.camera import bone_edges

__all__ = [
    "DEMO_SEED",
    "PAPER_A_TEST1",
    "ScenarioResult",
    "demo_recording",
    "demo_tables",
    "run_demo",
    "run_scenario",
    "whole_body",
]

#: Seed of the demo's virtual sensors.
DEMO_SEED = 3
#: Paper A test-1 settings ``joint kind -> (q, r)`` (SPEC §12.1: elbow q=1 R=0.01, wrist q=0.1 R=0.1).
PAPER_A_TEST1 = {"elbow": (1.0, 0.01), "wrist": (0.1, 0.1)}

#: Bones drawn in the report's skeleton snapshots.
SKELETON_EDGES = (
    ("elbow_l", "wrist_l"),
    ("elbow_r", "wrist_r"),
    ("knee_l", "ankle_l"),
    ("knee_r", "ankle_r"),
)


@dataclass(eq=False)
class ScenarioResult:
    """Everything :func:`run_scenario` computed on one recording (time-major arrays).

    Attributes
    ----------
    t_s : ndarray, shape (T,)
        Camera timestamps, s.
    joints : tuple of str
        The eight joints of paper B (:data:`kinefuse.conventions.PAPER_B_JOINTS`).
    reference : ndarray, shape (T, J, 3)
        True joint positions relative to the true ``spine_shoulder`` (paper B's chest-relative
        frame, ENU), m.
    camera : ndarray, shape (T, J, 3)
        Camera positions aligned to the same frame (NaN in outages), m.
    outage : ndarray of bool, shape (T, J)
        Camera unavailable.
    estimates : dict of str -> ndarray, shape (T, J, 3)
        Per table label (:data:`PAPER_A_LABELS`, :data:`PAPER_B_LABELS`): positions in the same
        frame, m. Paper A methods are NaN at the leg joints (paper A covers the arms).
    chain : ndarray, shape (T, J, 3)
        The unfiltered IMU chain of paper A (arms; NaN at the legs), m.
    modes : dict of str -> ndarray of int, shape (T, J)
        Filter branch per sample of paper A's methods (:data:`MODE_NAMES`; -1 at the legs).
    sources : dict of str -> ndarray of int, shape (T, J)
        Data source per sample of paper B's methods (:data:`SOURCE_NAMES`).
    run_time_s : dict of str -> float
        Wall-clock time of each method over the whole recording (paper A: the filters of the
        four arm joints; paper B: the pipeline for eight joints), s.
    paper_a : tuple of str
        Labels of paper A's methods that ran.
    paper_b : tuple of str
        Labels of paper B's methods that ran.
    notes : list of str
        Settings and caveats for the report.
    offset : ndarray, shape (T, 3) or None
        The true ``spine_shoulder`` at the camera timestamps (origin of the frame), m.
    """

    t_s: np.ndarray
    joints: tuple[str, ...]
    reference: np.ndarray
    camera: np.ndarray
    outage: np.ndarray
    estimates: dict[str, np.ndarray] = field(default_factory=dict)
    chain: np.ndarray | None = None
    modes: dict[str, np.ndarray] = field(default_factory=dict)
    sources: dict[str, np.ndarray] = field(default_factory=dict)
    run_time_s: dict[str, float] = field(default_factory=dict)
    paper_a: tuple[str, ...] = ()
    paper_b: tuple[str, ...] = ()
    notes: list[str] = field(default_factory=list)
    offset: np.ndarray | None = None

    def evaluation(self, methods: Sequence[str] | None = None, joints: Sequence[str] | None = None):
        """:func:`kinefuse.evaluation.evaluate` of some methods at some joints.

        Parameters
        ----------
        methods : sequence of str, optional
            Table labels (default: all, paper A first).
        joints : sequence of str, optional
            Joints (default: all eight).

        Returns
        -------
        EvaluationResult
        """
        methods = list(self.estimates if methods is None else methods)
        idx = [self.joints.index(j) for j in (self.joints if joints is None else joints)]
        names = tuple(self.joints[i] for i in idx)
        return evaluate(
            {m: self.estimates[m][:, idx] for m in methods},
            self.reference[:, idx],
            self.outage[:, idx],
            {m: self.run_time_s[m] for m in methods if m in self.run_time_s},
            joints=names,
        )


def _calibrate(recording, window_s: float):
    """Vision calibration of the eight limb segments (axes, lengths) over the first window."""
    return calibrate(recording, full_body(height_m=1.75), "vision", window_s=window_s)


def _paper_a(recording, calibration, settings, methods, result: ScenarioResult) -> None:
    """Paper A on both arms: chain with the camera's shoulder (gap-filled), then each filter."""
    t = result.t_s
    T, J = t.size, len(result.joints)
    chain = np.full((T, J, 3), np.nan)
    cam = recording.vision
    z = {}
    for side in ("r", "l"):
        sh = f"shoulder_{side}"
        p = cam.position(sh)
        ok = np.all(np.isfinite(p), axis=1)
        if not np.any(ok):
            raise InputError(f"the camera never sees {sh!r}; paper A needs the shoulder position")
        root = np.stack([np.interp(t, cam.t_s[ok], p[ok, k]) for k in range(3)], axis=-1)
        segs = (f"upper_arm_{side}", f"forearm_{side}")
        sk = upper_limb_skeleton(side, lengths={s: calibration.lengths_m[s] for s in segs})
        st = chain_positions(recording, sk, calibration, root={sh: root}, source="vision", t_s=t)
        for kind in ("elbow", "wrist"):
            j = f"{kind}_{side}"
            z[j] = st.position(j, masked=False)
            chain[:, result.joints.index(j)] = z[j]
    arm = [j for j in result.joints if j.startswith(("elbow", "wrist"))]
    za = np.stack([z[j] for j in arm], axis=1)
    q = [settings[j.split("_")[0]][0] for j in arm]
    r = [settings[j.split("_")[0]][1] for j in arm]
    dt = float(np.median(np.diff(t)))
    idx = [result.joints.index(j) for j in arm]
    # compile (first call) outside the timed run
    for m in methods:
        upper_limb(za[:40, 0], za[:40, 1], dt, m, q=q[:2], r=r[:2], joints=arm[:2])
    for m in methods:
        label = PAPER_A_LABELS[m]
        t0 = time.perf_counter()
        res = upper_limb(za[:, 0], za[:, 1], dt, m, q=q[:2], r=r[:2], joints=arm[:2])
        res2 = upper_limb(za[:, 2], za[:, 3], dt, m, q=q[2:], r=r[2:], joints=arm[2:])
        result.run_time_s[label] = time.perf_counter() - t0
        est = np.full((T, J, 3), np.nan)
        mode = np.full((T, J), -1, dtype=np.int64)
        est[:, idx] = np.concatenate([res.position, res2.position], axis=1) - result.offset[:, None]
        mode[:, idx] = np.concatenate([res.mode, res2.mode], axis=1)
        result.estimates[label] = est
        result.modes[label] = mode
    result.chain = chain - result.offset[:, None]
    result.paper_a = tuple(PAPER_A_LABELS[m] for m in methods)
    (qe, re_), (qw, rw) = settings["elbow"], settings["wrist"]
    result.notes.append(
        f"Paper A (Sun 2024) filters on the IMU chain (shoulder from the camera, gaps "
        f"interpolated): elbow q = {qe:g}, R = {re_:g} I; wrist q = {qw:g}, R = {rw:g} I; "
        "dt = 1/30 s, N = 20, thresholds 2 and 2. Shown only at the elbows and wrists."
    )


def _paper_b(recording, calibration, methods, params, result: ScenarioResult, causal=()) -> None:
    """Paper B on the eight joints with each method (shared calibration and alignment).

    ``causal``: methods also run causally, labelled ``"<label> causal"``.
    """
    done = []
    for m, is_causal, label in labelled_runs(methods, causal):
        fused, result.run_time_s[label] = timed_quietly(
            vision_assisted_from_recording,
            recording,
            calibration=calibration,
            method=m,
            joints=result.joints,
            params=params,
            causal=is_causal,
        )
        result.estimates[label] = fused.result.position
        result.sources[label] = fused.result.source.astype(np.int64)
        result.camera = fused.z_cam
        done.append(label)
    result.paper_b = tuple(done)
    result.notes.append(
        "Paper B (Xu 2023): IMU chain from the chest (offsets and lengths from the camera), "
        "camera aligned by Kabsch; ELM/FIR and ELM/KF with IMM + RTS, ELM bridging during "
        "camera outages; settings SPEC §12.2. All positions are relative to spine_shoulder."
    )


def _empty_result(recording, joints: tuple[str, ...]) -> ScenarioResult:
    """A :class:`ScenarioResult` with the reference and the outages of ``joints`` only: positions
    at the camera timestamps, relative to the true ``spine_shoulder``."""
    cam = recording.vision
    t = cam.t_s
    ref = recording.reference
    rs = ref.position("spine_shoulder")
    cols = []
    for j in joints:
        pj = ref.position(j)
        cols.append(np.stack([np.interp(t, ref.t_s, pj[:, k]) for k in range(3)], -1))
    offset = np.stack([np.interp(t, ref.t_s, rs[:, k]) for k in range(3)], -1)
    reference = np.stack(cols, axis=1) - offset[:, None]
    avail = np.stack([cam.available[:, cam.index(j)] for j in joints], axis=1)
    avail &= cam.available[:, cam.index("spine_shoulder")][:, None]
    return ScenarioResult(
        t_s=t,
        joints=joints,
        reference=reference,
        camera=np.full(reference.shape, np.nan),
        outage=~avail,
        offset=offset,
    )


def run_scenario(
    recording,
    *,
    paper_a: Sequence[str] = ("kf", "fir", "em-kf-fir"),
    paper_b: Sequence[str] | None = None,
    paper_b_causal: Sequence[str] = (),
    paper_a_settings: Mapping[str, tuple[float, float]] = PAPER_A_TEST1,
    paper_b_params=None,
    calibration_window_s: float = 5.0,
    advance: Callable[..., None] | None = None,
) -> ScenarioResult:
    """Both papers' pipelines on one recording with nine IMUs, a camera and a reference.

    Parameters
    ----------
    recording : Recording
        IMU orientations for ``chest`` and the eight limb segments (paper B), a camera
        (``vision``, ENU or any frame) with the shoulders and ``spine_shoulder``, and the
        ``reference`` at the camera timestamps (e.g. :func:`kinefuse.sim.virtual_recording`).
    paper_a : sequence of str
        Paper A filters (:data:`PAPER_A_LABELS` keys); empty to skip paper A.
    paper_b : sequence of str, optional
        Paper B methods (default :func:`paper_b_methods`); empty to skip paper B.
    paper_b_causal : sequence of str
        Paper B methods to run causally as well (table label ``"<label> causal"``).
    paper_a_settings : mapping
        ``{"elbow": (q, r), "wrist": (q, r)}``, q in (m/s)² per step, r in m² (default paper
        A's test 1, :data:`PAPER_A_TEST1`).
    paper_b_params : VisionParams, optional
        Paper B settings (default SPEC §12.2).
    calibration_window_s : float
        Length of the vision calibration window at the start, s (segment axes, lengths).
    advance : callable, optional
        Progress callback, called once per method.

    Returns
    -------
    ScenarioResult
        Positions relative to the true ``spine_shoulder`` (paper B's chest-relative frame).

    Notes
    -----
    Calibration: :func:`kinefuse.kinematics.calibrate` ("vision") of the eight limb segments
    over the first ``calibration_window_s``; both papers use its axes and lengths. Paper A's
    shoulder comes from the camera, linearly interpolated across its outages; paper A's
    estimates are shifted by the true ``spine_shoulder`` so that they share paper B's frame
    (a common translation: errors are unchanged).
    """
    if not isinstance(recording, Recording):
        raise InputError(f"expected recording as a Recording, got {type(recording).__name__}")
    if recording.vision is None or recording.reference is None:
        raise InputError("expected a recording with a camera (vision) and a reference")
    advance = advance or (lambda n=1: None)
    paper_b = paper_b_methods() if paper_b is None else tuple(paper_b)
    result = _empty_result(recording, tuple(PAPER_B_JOINTS))
    calibration = _calibrate(recording, calibration_window_s)
    result.notes.append(
        f"Calibration: segment axes and lengths from the camera over the first "
        f"{calibration_window_s:g} s (RMS residual "
        f"{np.sqrt(np.mean(np.square(list(calibration.residual_deg.values())))):.2f} deg)."
    )
    if paper_a:
        _paper_a(recording, calibration, paper_a_settings, tuple(paper_a), result)
        advance()
    if paper_b:
        _paper_b(recording, calibration, paper_b, paper_b_params, result, tuple(paper_b_causal))
        advance()
    return result


def demo_recording(seed: int = DEMO_SEED):
    """The demo's virtual recording: packaged CMU clip, 9 IMUs, Kinect-like camera with outages.

    Parameters
    ----------
    seed : int
        Seed of the virtual sensors.

    Returns
    -------
    Recording
    """
    return virtual_recording(demo_motion(), seed=seed)


def whole_body(recording, scenario: ScenarioResult):
    """Every reference joint at the camera times, in the scenario's chest-relative frame.

    Returns
    -------
    (names, positions, edges)
        Joint names (K,), positions (T, K, 3) in m relative to the true ``spine_shoulder``
        and the bones along the canonical tree: the ``body`` of
        :func:`kinefuse.evaluation.write_report`.
    """
    ref = recording.reference
    t = scenario.t_s
    names = tuple(ref.joints)
    pos = np.stack(
        [
            np.stack([np.interp(t, ref.t_s, ref.position(j)[:, k]) for k in range(3)], -1)
            for j in names
        ],
        axis=1,
    )
    if scenario.offset is not None:
        pos = pos - scenario.offset[:, None]
    return names, pos, bone_edges(names)


def demo_tables(scenario: ScenarioResult) -> tuple[object, list]:
    """The evaluation of paper B's methods and the paper-style comparison tables.

    Returns
    -------
    evaluation : EvaluationResult
        Paper B's methods on the eight joints.
    tables : list of ResultTable
        Paper A layout (Tables 4-5) for the right elbow and wrist with the paper's numbers,
        paper A's run time per step (Table 6), and paper B's layout (Tables 3-5) at the joints
        the paper tabulates, with its numbers.
    """
    ev_b = scenario.evaluation(scenario.paper_b) if scenario.paper_b else None
    out = []
    if scenario.paper_a:
        arm = ("elbow_r", "wrist_r", "elbow_l", "wrist_l")
        ev_a = scenario.evaluation(scenario.paper_a, arm)
        for joint, kind in (("elbow_r", "elbow"), ("wrist_r", "wrist")):
            out.append(
                tables.method_table(
                    ev_a,
                    joint,
                    paper=tables.PAPER_A_RMSE_M[kind],
                    title=f"Paper A layout (Tables 4-5): RMSE at {joint} (m), next to the paper's test 1",
                )
            )
        t = tables.timing_table(ev_a, paper=tables.PAPER_A_TIME_PER_STEP_MS)
        out.append(
            tables.ResultTable(
                title="Paper A layout (Table 6): run time of the four arm joints "
                "(sampling time 33.33 ms)",
                label_headers=t.label_headers,
                value_headers=t.value_headers,
                rows=t.rows,
                digits=t.digits,
                notes=t.notes,
            )
        )
    if ev_b is not None:
        out.append(
            tables.joint_method_table(
                ev_b,
                joints=[j for j in tables.PAPER_B_RMSE_M if j in ev_b.joints],
                paper=tables.PAPER_B_RMSE_M,
                title="Paper B layout (Tables 3-5): RMSE (m), next to the paper's numbers",
            )
        )
    return ev_b, out


def run_demo(out_dir, force: bool = False, quiet: bool = False) -> dict:
    """Back-end of ``kinefuse demo``: both papers on the packaged clip; HTML report.

    Parameters
    ----------
    out_dir : str or Path
        Output folder (created); gets ``report.html``, ``figures/`` and ``metrics.json``.
    force : bool
        Replace earlier results (``report.html``, ``metrics.json``, ``figures/``).
    quiet : bool
        No progress bar.

    Returns
    -------
    dict
        ``evaluation`` (paper B's methods on the eight joints, EvaluationResult), ``report``
        (Path), ``tables`` (paper A and paper B layouts next to the papers' numbers),
        ``all_methods`` (EvaluationResult of every method, as in the report) and ``notes``.

    Raises
    ------
    FileExistsError
        An earlier result exists and ``force`` is False (nothing is written).
    InputError
        ``out_dir`` is a file or not writable (checked before any work).

    Notes
    -----
    The results are staged and moved into ``out_dir`` when complete
    (:class:`kinefuse.io.output_folder.OutputFolder`): an interrupted demo leaves the
    previous results untouched.
    """
    out_dir = Path(out_dir)
    # every earlier result needs force; the new set is staged and moved in when complete
    stage = OutputFolder(out_dir, (REPORT_NAME, "metrics.json", "figures"), force=force)
    try:
        summary = _run_demo(stage.path, quiet)
        stage.commit()
    except BaseException:
        stage.discard()
        raise
    summary["report"] = out_dir / REPORT_NAME
    return summary


def _run_demo(out_dir: Path, quiet: bool) -> dict:

    t0 = time.perf_counter()
    with progress("Demo", total=4, quiet=quiet) as advance:
        recording = demo_recording()
        advance()
        scenario = run_scenario(recording, advance=advance)
        ev_b, tbls = demo_tables(scenario)
        ev_all = scenario.evaluation()
        notes = [
            "Data: CMU mocap subject 02 trial 08 (swordplay, 12.5 s; mocap.cs.cmu.edu, NSF "
            "EIA-0196217) driving nine virtual IMUs (ICM-20948 error model, 100 Hz, on-board "
            f"orientation) and a virtual Kinect (30 Hz, mm jitter, bone-length variation, "
            f"occlusions and dropouts), seed {DEMO_SEED}.",
            *scenario.notes,
        ]
        if _compile.interpreting():
            notes.append(
                "The filter kernels ran interpreted: this machine has not compiled them yet, and "
                "compiling would take far longer than this small demo. Results are identical; the "
                "run times are those of interpreted kernels. Any `kinefuse run`, `experiment` or "
                "`bench` compiles them once (cached for later runs)."
            )
        report = write_report(
            out_dir,
            ev_all,
            scenario.estimates,
            scenario.reference,
            scenario.t_s,
            scenario.outage,
            measurement=scenario.camera,
            modes=scenario.modes,
            sources=scenario.sources,
            body=whole_body(recording, scenario),
            options=ReportOptions(
                title="kinefuse demo: CMU swordplay, virtual IMUs and Kinect",
                notes=notes,
                axis_labels=("X", "Y", "Z"),
                paper=None,
                mode_names=MODE_NAMES,
                source_names=SOURCE_NAMES,
                skeleton_edges=SKELETON_EDGES,
                viewer_methods=[m for m in ("ELM/FIR", "kinefuse") if m in ev_all.methods],
            ),
        )
        advance()
    notes.append(f"Wall time {time.perf_counter() - t0:.1f} s.")
    return {
        "evaluation": ev_b if ev_b is not None else ev_all,
        "all_methods": ev_all,
        "report": report,
        "tables": tbls,
        "notes": notes,
    }
