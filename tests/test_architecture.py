"""The house rules of docs/architecture.md, checked on the source with ``ast`` (issue 14).

- Imports at module level. Inside a function only (a) an optional dependency
  (:data:`OPTIONAL_DEPENDENCIES`) or (b) in a module that calls ``_compile.interpret_kernels()``,
  a kinefuse module that loads compiled kernels: the switch to interpreted kernels must run before
  any kernel module is imported, so that lazy path stays (with a comment saying so).
- A module has at most :data:`MAX_MODULE_LINES` lines, unless its docstring contains
  :data:`LONG_MODULE_MARKER` followed by the reason (e.g. a compiled-kernel file whose kernels
  must share one module so numba can inline them).
- A public function or method (name without a leading ``_``) has at most
  :data:`MAX_FUNCTION_LINES` lines of code: from ``def`` to its last line, the docstring not
  counted (numpydoc docstrings with shapes, units and deviations are wanted, not penalised).

Ratchet: the redesign is merged branch by branch, so today's violations are listed below by
name. A violation not in a list fails; a list entry that is no longer a violation fails too, so
the lists only shrink. When a test fails it prints what to add (never do that for new code) or
what to remove.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass

from conftest import REPO_ROOT
from kinefuse._compile import KERNEL_MODULES

SRC = REPO_ROOT / "src"
PACKAGE = SRC / "kinefuse"

MAX_MODULE_LINES = 700
MAX_FUNCTION_LINES = 80
LONG_MODULE_MARKER = "compiled-kernel module:"

#: Optional dependencies (extras in pyproject.toml, or a system installation): imported where
#: they are used so that kinefuse works without them.
OPTIONAL_DEPENDENCIES = frozenset(
    {
        "pylsl",  # [lsl]
        "dask",  # [batch]
        "distributed",  # [batch]
        "pyarrow",  # [batch]
        "playwright",  # tests / live-view browser checks
        "opensim",  # conda-only OpenSim bindings
        "ezc3d",  # [c3d]
        "filterpy",  # [bench]: the peer of `kinefuse bench`
    }
)

# ---- ratchet: today's violations (main @ 1a9b5ab); remove entries as they are fixed ---------

#: ``path::function -> imported module`` for imports inside functions.
ALLOWED_FUNCTION_IMPORTS: frozenset[str] = frozenset(
    {
        "kinefuse/_compile.py::interpret_kernels -> sys",
        "kinefuse/_compile.py::kernels_cached -> glob",
        "kinefuse/batch/__init__.py::compare_workers -> kinefuse.batch.runner",
        "kinefuse/batch/__init__.py::run_study -> kinefuse.batch.runner",
        "kinefuse/batch/report.py::_box_figure -> matplotlib.backends.backend_agg",
        "kinefuse/batch/report.py::_box_figure -> matplotlib.figure",
        "kinefuse/batch/report.py::summary_table -> kinefuse.evaluation.tables",
        "kinefuse/batch/report.py::write_study_report -> kinefuse",
        "kinefuse/batch/runner.py::_Progress.__init__ -> rich.console",
        "kinefuse/batch/runner.py::_Progress.__init__ -> rich.progress",
        "kinefuse/batch/runner.py::_has_bokeh -> importlib.util",
        "kinefuse/batch/runner.py::_kernels_cached -> kinefuse._compile",
        "kinefuse/batch/runner.py::_numba_cache_dir -> kinefuse._compile",
        "kinefuse/batch/runner.py::compare_table -> kinefuse.evaluation.tables",
        "kinefuse/batch/runner.py::compare_workers -> dataclasses",
        "kinefuse/batch/runner.py::compare_workers -> kinefuse.batch.tasks",
        "kinefuse/batch/runner.py::run_study -> kinefuse.batch.report",
        "kinefuse/batch/runner.py::run_study -> rich.console",
        "kinefuse/batch/runner.py::summary_tables -> kinefuse.batch.report",
        "kinefuse/batch/runner.py::summary_tables -> kinefuse.evaluation.tables",
        "kinefuse/batch/study.py::_check_sections -> kinefuse.session",
        "kinefuse/batch/study.py::_task_list -> kinefuse.session",
        "kinefuse/batch/tasks.py::one_line -> kinefuse.exceptions",
        "kinefuse/batch/tasks.py::run_task -> kinefuse.pipelines.session",
        "kinefuse/batch/tasks.py::run_task -> kinefuse.session",
        "kinefuse/cli.py::_check_json -> kinefuse.io.output_folder",
        "kinefuse/cli.py::_check_report_free -> kinefuse.evaluation.report",
        "kinefuse/cli.py::_fresh_dir -> kinefuse.evaluation.report",
        "kinefuse/cli.py::_jsonable -> kinefuse.evaluation.tables",
        "kinefuse/cli.py::_kv_table -> rich",
        "kinefuse/cli.py::_kv_table -> rich.table",
        "kinefuse/cli.py::_present -> kinefuse.evaluation.tables",
        "kinefuse/cli.py::_replay_table -> rich",
        "kinefuse/cli.py::_replay_table -> rich.table",
        "kinefuse/cli.py::_stream_session -> dataclasses",
        "kinefuse/cli.py::_stream_session -> kinefuse.session",
        "kinefuse/cli.py::_version_callback -> kinefuse",
        "kinefuse/cli.py::_write_json -> kinefuse.io._common",
        "kinefuse/cli.py::batch -> kinefuse.batch",
        "kinefuse/cli.py::batch -> kinefuse.batch.runner",
        "kinefuse/cli.py::demo -> kinefuse._compile",
        "kinefuse/cli.py::evaluate -> kinefuse.io",
        "kinefuse/cli.py::evaluate -> kinefuse.session",
        "kinefuse/cli.py::init_session -> kinefuse.session",
        "kinefuse/cli.py::progress -> rich.progress",
        "kinefuse/cli.py::run -> kinefuse.session",
        "kinefuse/data/__init__.py::demo_motion -> kinefuse.io.cmu",
        "kinefuse/evaluation/angles.py::write_angle_report -> kinefuse",
        "kinefuse/evaluation/angles.py::write_angle_report -> kinefuse.evaluation.report",
        "kinefuse/evaluation/bench.py::_engine_rows -> kinefuse.streaming.replay",
        "kinefuse/evaluation/bench.py::_filterpy_filter -> kinefuse.filters._base",
        "kinefuse/evaluation/bench.py::_find_filter_class -> importlib",
        "kinefuse/evaluation/bench.py::_kf_rts_rows -> kinefuse.filters",
        "kinefuse/evaluation/bench.py::_model -> kinefuse.models",
        "kinefuse/evaluation/bench.py::_online_rows -> kinefuse.filters",
        "kinefuse/evaluation/bench.py::_other_filter_rows -> kinefuse.filters",
        "kinefuse/evaluation/bench.py::_pipeline_rows -> pickle",
        "kinefuse/evaluation/bench.py::_pipeline_rows -> tempfile",
        "kinefuse/evaluation/bench.py::engine_frame_times -> kinefuse.streaming.config",
        "kinefuse/evaluation/bench.py::engine_frame_times -> kinefuse.streaming.runner",
        "kinefuse/evaluation/bench.py::filterpy_frame_times -> kinefuse.models",
        "kinefuse/evaluation/bench.py::pipeline_recording -> dataclasses",
        "kinefuse/evaluation/bench.py::pipeline_recording -> kinefuse.data",
        "kinefuse/evaluation/bench.py::pipeline_recording -> kinefuse.sim",
        "kinefuse/evaluation/bench.py::run_bench -> kinefuse.exceptions",
        "kinefuse/evaluation/bench.py::run_benchmarks -> numba",
        "kinefuse/evaluation/plots.py::figure_to_png -> PIL",
        "kinefuse/evaluation/plots.py::skeleton_figure -> mpl_toolkits.mplot3d",
        "kinefuse/evaluation/report.py::_html -> kinefuse",
        "kinefuse/evaluation/tables.py::to_rich -> rich",
        "kinefuse/evaluation/tables.py::to_rich -> rich.table",
        "kinefuse/filters/ufir.py::UFIRFilter._run -> warnings",
        "kinefuse/filters/ufir.py::UFIRFilter._run_cv -> warnings",
        "kinefuse/filters/warm_up.py::_em -> kinefuse.filters",
        "kinefuse/filters/warm_up.py::_imm -> kinefuse.filters",
        "kinefuse/filters/warm_up.py::_imm -> kinefuse.models",
        "kinefuse/filters/warm_up.py::_kf -> kinefuse.filters",
        "kinefuse/filters/warm_up.py::_model -> kinefuse.models",
        "kinefuse/filters/warm_up.py::_ufir -> kinefuse.filters",
        "kinefuse/io/_registry.py::detect_format -> kinefuse.io._unsupported",
        "kinefuse/io/_unsupported.py::_readable_files -> kinefuse.io._registry",
        "kinefuse/io/_unsupported.py::looks_like -> scipy.io",
        "kinefuse/io/ximu3.py::_plain_csv_reader -> kinefuse.io._registry",
        "kinefuse/kinematics/calibration.py::_crop -> dataclasses",
        "kinefuse/kinematics/calibration.py::calibrate -> kinefuse.kinematics.functional",
        "kinefuse/kinematics/calibration.py::calibrate -> kinefuse.kinematics.hinge",
        "kinefuse/kinematics/functional.py::align_headings -> scipy.spatial.transform",
        "kinefuse/kinematics/functional.py::functional_calibration -> kinefuse.kinematics.hinge",
        "kinefuse/kinematics/hinge.py::hinge_frames -> kinefuse.kinematics.forward",
        "kinefuse/kinematics/hinge.py::hinge_frames -> kinefuse.kinematics.skeleton",
        "kinefuse/kinematics/hinge.py::hinge_frames -> kinefuse.orientation.resample",
        "kinefuse/pipelines/demo.py::ScenarioResult.evaluation -> kinefuse.evaluation",
        "kinefuse/pipelines/demo.py::_calibrate -> kinefuse.kinematics",
        "kinefuse/pipelines/demo.py::_paper_a -> kinefuse.kinematics",
        "kinefuse/pipelines/demo.py::_paper_a -> kinefuse.pipelines.upper_limb",
        "kinefuse/pipelines/demo.py::_paper_b -> kinefuse.pipelines",
        "kinefuse/pipelines/demo.py::_run_demo -> kinefuse.evaluation.report",
        "kinefuse/pipelines/demo.py::demo_recording -> kinefuse.data",
        "kinefuse/pipelines/demo.py::demo_recording -> kinefuse.sim",
        "kinefuse/pipelines/demo.py::demo_tables -> kinefuse.evaluation.tables",
        "kinefuse/pipelines/demo.py::paper_b_methods -> kinefuse.pipelines",
        "kinefuse/pipelines/demo.py::progress -> kinefuse.cli",
        "kinefuse/pipelines/demo.py::run_demo -> kinefuse.evaluation.report",
        "kinefuse/pipelines/demo.py::run_demo -> kinefuse.io.output_folder",
        "kinefuse/pipelines/demo.py::run_scenario -> kinefuse.io.recording",
        "kinefuse/pipelines/demo.py::whole_body -> kinefuse.sim.camera",
        "kinefuse/pipelines/experiments.py::_arm_chain -> kinefuse.kinematics",
        "kinefuse/pipelines/experiments.py::_arm_recording -> kinefuse.sim",
        "kinefuse/pipelines/experiments.py::_branch_fractions -> kinefuse.conventions",
        "kinefuse/pipelines/experiments.py::_cmu_motions -> kinefuse.data",
        "kinefuse/pipelines/experiments.py::_cmu_motions -> kinefuse.io.cmu",
        "kinefuse/pipelines/experiments.py::_cmu_recording -> kinefuse.sim",
        "kinefuse/pipelines/experiments.py::_cmu_scenario -> kinefuse.pipelines",
        "kinefuse/pipelines/experiments.py::_cmu_scenario -> kinefuse.pipelines.demo",
        "kinefuse/pipelines/experiments.py::_filter_runs -> kinefuse.pipelines.upper_limb",
        "kinefuse/pipelines/experiments.py::_neura_inputs -> dataclasses",
        "kinefuse/pipelines/experiments.py::_neura_inputs -> kinefuse.io",
        "kinefuse/pipelines/experiments.py::_neura_scenario -> kinefuse.pipelines",
        "kinefuse/pipelines/experiments.py::_neura_scenario -> kinefuse.pipelines.session",
        "kinefuse/pipelines/experiments.py::_paper_a -> kinefuse.evaluation",
        "kinefuse/pipelines/experiments.py::_paper_a -> kinefuse.evaluation.tables",
        "kinefuse/pipelines/experiments.py::_paper_b -> kinefuse.evaluation.tables",
        "kinefuse/pipelines/experiments.py::_paper_b -> kinefuse.pipelines",
        "kinefuse/pipelines/experiments.py::_paper_b -> kinefuse.pipelines.demo",
        "kinefuse/pipelines/experiments.py::_pooled -> kinefuse.evaluation",
        "kinefuse/pipelines/experiments.py::_table -> kinefuse.evaluation.tables",
        "kinefuse/pipelines/experiments.py::_timing -> kinefuse.filters",
        "kinefuse/pipelines/experiments.py::_timing -> kinefuse.filters.integrated",
        "kinefuse/pipelines/experiments.py::_timing -> kinefuse.filters.ufir",
        "kinefuse/pipelines/experiments.py::_timing -> kinefuse.models",
        "kinefuse/pipelines/experiments.py::_utd_recording -> kinefuse.io",
        "kinefuse/pipelines/experiments.py::_utd_scenario -> kinefuse.pipelines",
        "kinefuse/pipelines/experiments.py::_utd_wrist_chain -> dataclasses",
        "kinefuse/pipelines/experiments.py::_utd_wrist_chain -> kinefuse.pipelines.session",
        "kinefuse/pipelines/experiments.py::_vision_methods -> kinefuse.pipelines.demo",
        "kinefuse/pipelines/experiments.py::_vision_methods -> kinefuse.pipelines.vision_assisted",
        "kinefuse/pipelines/experiments.py::run_experiment -> kinefuse.pipelines.demo",
        "kinefuse/pipelines/experiments.py::run_experiment -> kinefuse.pipelines.neura_imu_only",
        "kinefuse/pipelines/experiments.py::run_experiment -> kinefuse.pipelines.realism",
        "kinefuse/pipelines/features.py::_orientation_at -> kinefuse.orientation",
        "kinefuse/pipelines/features.py::_world_rate -> scipy.spatial.transform",
        "kinefuse/pipelines/neura_imu_only.py::_knee_flexion_deg -> kinefuse.kinematics",
        "kinefuse/pipelines/neura_imu_only.py::_knee_flexion_deg -> kinefuse.kinematics.hinge",
        "kinefuse/pipelines/neura_imu_only.py::_scores -> kinefuse.kinematics",
        "kinefuse/pipelines/neura_imu_only.py::run_neura_imu_only -> kinefuse.evaluation.tables",
        "kinefuse/pipelines/neura_imu_only.py::run_neura_imu_only -> kinefuse.io",
        "kinefuse/pipelines/neura_imu_only.py::run_neura_imu_only -> kinefuse.kinematics",
        "kinefuse/pipelines/realism.py::_camera_from -> kinefuse.io",
        "kinefuse/pipelines/realism.py::_cmu -> kinefuse.io.cmu",
        "kinefuse/pipelines/realism.py::_filled_orientation -> scipy.spatial.transform",
        "kinefuse/pipelines/realism.py::broad_trial -> kinefuse.io.broad",
        "kinefuse/pipelines/realism.py::broad_trial -> kinefuse.orientation",
        "kinefuse/pipelines/realism.py::broad_trial -> kinefuse.sim",
        "kinefuse/pipelines/realism.py::cmu_arm_pieces -> kinefuse.sim",
        "kinefuse/pipelines/realism.py::cmu_walk_chain_error_mm -> kinefuse.sim",
        "kinefuse/pipelines/realism.py::leg_chain_error_mm -> kinefuse.pipelines.session",
        "kinefuse/pipelines/realism.py::neura_chain_error_mm -> kinefuse.io",
        "kinefuse/pipelines/realism.py::run_realism -> kinefuse.pipelines.experiments",
        "kinefuse/pipelines/realism.py::utd_wrist_figures -> kinefuse.io",
        "kinefuse/pipelines/realism.py::wrist_chain_figures -> kinefuse.pipelines.session",
        "kinefuse/pipelines/session.py::SessionOutput.evaluation -> kinefuse.evaluation",
        "kinefuse/pipelines/session.py::_at -> kinefuse.io",
        "kinefuse/pipelines/session.py::_baselines -> kinefuse.pipelines.demo",
        "kinefuse/pipelines/session.py::_baselines -> kinefuse.pipelines.vision_assisted",
        "kinefuse/pipelines/session.py::_check_params -> difflib",
        "kinefuse/pipelines/session.py::_covered -> kinefuse.io",
        "kinefuse/pipelines/session.py::_declared_axes -> kinefuse.kinematics",
        "kinefuse/pipelines/session.py::_ensure_orientations -> dataclasses",
        "kinefuse/pipelines/session.py::_ensure_orientations -> kinefuse.orientation",
        "kinefuse/pipelines/session.py::_format_name -> kinefuse.io",
        "kinefuse/pipelines/session.py::_hip_roots -> kinefuse.kinematics",
        "kinefuse/pipelines/session.py::_hip_roots -> kinefuse.kinematics.forward",
        "kinefuse/pipelines/session.py::_hip_roots -> kinefuse.orientation.resample",
        "kinefuse/pipelines/session.py::_load -> kinefuse.exceptions",
        "kinefuse/pipelines/session.py::_load -> kinefuse.io",
        "kinefuse/pipelines/session.py::_outputs -> kinefuse.evaluation.report",
        "kinefuse/pipelines/session.py::_paper_a_filter -> kinefuse.pipelines.upper_limb",
        "kinefuse/pipelines/session.py::_plan -> kinefuse.kinematics",
        "kinefuse/pipelines/session.py::_rigid_align -> kinefuse.kinematics",
        "kinefuse/pipelines/session.py::_run_and_write -> kinefuse.evaluation",
        "kinefuse/pipelines/session.py::_run_and_write -> kinefuse.evaluation.angles",
        "kinefuse/pipelines/session.py::_run_and_write -> kinefuse.io",
        "kinefuse/pipelines/session.py::_run_and_write -> kinefuse.io.opensim",
        "kinefuse/pipelines/session.py::_vision -> kinefuse.pipelines",
        "kinefuse/pipelines/session.py::_vision -> kinefuse.pipelines.vision_assisted",
        "kinefuse/pipelines/session.py::_write_angles -> kinefuse.io._common",
        "kinefuse/pipelines/session.py::_write_angles -> kinefuse.io.mot",
        "kinefuse/pipelines/session.py::_write_angles -> kinefuse.kinematics",
        "kinefuse/pipelines/session.py::build_chain -> kinefuse.kinematics",
        "kinefuse/pipelines/session.py::coverage_table -> kinefuse.evaluation.tables",
        "kinefuse/pipelines/session.py::evaluate_recording -> dataclasses",
        "kinefuse/pipelines/session.py::evaluate_recording -> kinefuse.exceptions",
        "kinefuse/pipelines/session.py::evaluate_recording -> kinefuse.io",
        "kinefuse/pipelines/session.py::load_streams -> kinefuse.io",
        "kinefuse/pipelines/session.py::process_recording -> kinefuse.kinematics",
        "kinefuse/pipelines/session.py::process_recording -> kinefuse.kinematics.angles",
        "kinefuse/pipelines/session.py::process_recording -> kinefuse.kinematics.functional",
        "kinefuse/pipelines/session.py::process_recording -> kinefuse.orientation.resample",
        "kinefuse/pipelines/session.py::process_recording -> kinefuse.session",
        "kinefuse/pipelines/session.py::process_recording -> scipy.spatial.transform",
        "kinefuse/pipelines/session.py::run_session -> kinefuse.io.output_folder",
        "kinefuse/pipelines/session.py::run_session -> kinefuse.session",
        "kinefuse/pipelines/upper_limb.py::upper_limb_from_recording -> kinefuse.io.recording",
        "kinefuse/pipelines/upper_limb.py::upper_limb_from_recording -> kinefuse.kinematics",
        "kinefuse/pipelines/vision_assisted.py::_kinefuse -> kinefuse.pipelines.kinefuse_fusion",
        "kinefuse/pipelines/vision_assisted.py::vision_assisted_from_recording -> kinefuse.conventions",
        "kinefuse/pipelines/vision_assisted.py::vision_assisted_from_recording -> kinefuse.io.recording",
        "kinefuse/pipelines/vision_assisted.py::vision_assisted_from_recording -> kinefuse.kinematics",
        "kinefuse/pipelines/vision_assisted.py::vision_assisted_from_recording -> kinefuse.kinematics.forward",
        "kinefuse/pipelines/vision_assisted.py::vision_assisted_from_recording -> kinefuse.orientation",
        "kinefuse/session.py::session_template -> kinefuse.io",
        "kinefuse/sim/__init__.py::virtual_recording -> kinefuse.conventions",
        "kinefuse/sim/imu.py::simulate_imu_from_pose -> kinefuse.orientation",
        "kinefuse/streaming/config.py::load_stream_config -> kinefuse.session",
        "kinefuse/streaming/engine.py::Engine.__init__ -> kinefuse.streaming._kernels",
        "kinefuse/streaming/engine.py::Engine.push_imu -> kinefuse.orientation",
        "kinefuse/streaming/engine.py::Engine.restore -> kinefuse.orientation",
        "kinefuse/streaming/engine.py::_Chain.__init__ -> kinefuse.streaming._kernels",
        "kinefuse/streaming/engine.py::offline_causal -> kinefuse.kinematics",
        "kinefuse/streaming/lsl.py::_pull_options -> inspect",
        "kinefuse/streaming/processors.py::KalmanFusionProcessor._fast_step -> kinefuse.streaming._kernels",
        "kinefuse/streaming/replay.py::demo_recording -> kinefuse.data",
        "kinefuse/streaming/replay.py::demo_recording -> kinefuse.sim",
        "kinefuse/streaming/replay.py::load_recording -> kinefuse.io",
        "kinefuse/streaming/runner.py::_live_view -> kinefuse.sim.camera",
        "kinefuse/streaming/runner.py::_live_view -> kinefuse.streaming.liveview",
        "kinefuse/streaming/runner.py::_live_view -> sys",
        "kinefuse/streaming/runner.py::_status_printer -> rich.live",
        "kinefuse/streaming/runner.py::_status_printer -> rich.table",
        "kinefuse/streaming/runner.py::build_engine -> kinefuse.pipelines.vision_assisted",
        "kinefuse/streaming/runner.py::build_engine -> kinefuse.streaming.paper_b",
        "kinefuse/streaming/runner.py::run_stream -> concurrent.futures",
        "kinefuse/streaming/runner.py::run_stream -> kinefuse.streaming.lsl",
        "kinefuse/streaming/runner.py::run_stream -> rich.console",
    }
)

#: Modules above MAX_MODULE_LINES without a stated reason.
ALLOWED_LONG_MODULES: frozenset[str] = frozenset(
    {
        "kinefuse/cli.py",
        "kinefuse/evaluation/bench.py",
        "kinefuse/filters/_kernels_em.py",
        "kinefuse/filters/_kernels_ufir.py",
        "kinefuse/io/_common.py",
        "kinefuse/io/kinect.py",
        "kinefuse/kinematics/calibration.py",
        "kinefuse/kinematics/functional.py",
        "kinefuse/pipelines/experiments.py",
        "kinefuse/pipelines/kinefuse_fusion.py",
        "kinefuse/pipelines/session.py",
        "kinefuse/pipelines/vision_assisted.py",
        "kinefuse/session.py",
        "kinefuse/sim/imu.py",
        "kinefuse/streaming/engine.py",
    }
)

#: ``path::qualified.name`` of public functions above MAX_FUNCTION_LINES lines of code.
ALLOWED_LONG_FUNCTIONS: frozenset[str] = frozenset(
    {
        "kinefuse/batch/report.py::write_study_report",
        "kinefuse/batch/runner.py::run_study",
        "kinefuse/batch/study.py::load_study",
        "kinefuse/cli.py::evaluate",
        "kinefuse/cli.py::stream",
        "kinefuse/evaluation/bench.py::format_report",
        "kinefuse/evaluation/metrics.py::evaluate",
        "kinefuse/evaluation/plots.py::skeleton_figure",
        "kinefuse/evaluation/report.py::write_report",
        "kinefuse/evaluation/tables.py::joint_method_table",
        "kinefuse/evaluation/viewer.py::report_viewer_html",
        "kinefuse/filters/_kernels_axis.py::kf_filter_axis",
        "kinefuse/filters/_kernels_blocks.py::rts_blocks",
        "kinefuse/filters/_kernels_em.py::em_kf_run",
        "kinefuse/filters/_kernels_em.py::em_kf_run_cv",
        "kinefuse/filters/_kernels_em.py::em_update",
        "kinefuse/filters/_kernels_em.py::em_update_cv",
        "kinefuse/filters/_kernels_em.py::integrated_run",
        "kinefuse/filters/_kernels_em.py::integrated_run_cv",
        "kinefuse/filters/_kernels_ufir.py::ufir_horizon_axes",
        "kinefuse/filters/_kernels_ufir.py::ufir_horizon_axis",
        "kinefuse/filters/_kernels_ufir.py::ufir_run",
        "kinefuse/filters/_kernels_ufir.py::ufir_run_cv",
        "kinefuse/io/bvh.py::load_motion_bvh",
        "kinefuse/io/c3d.py::read_c3d",
        "kinefuse/io/kinect.py::read_azure_kinect_json",
        "kinefuse/io/mvnx.py::read_mvnx",
        "kinefuse/io/opensense.py::read_opensense",
        "kinefuse/io/trc.py::read_trc",
        "kinefuse/io/utd_mhad.py::read_utd_mhad",
        "kinefuse/io/ximu3.py::read_ximu3",
        "kinefuse/io/xsens_dot.py::read_xsens_dot",
        "kinefuse/kinematics/calibration.py::calibrate",
        "kinefuse/kinematics/forward.py::forward_kinematics",
        "kinefuse/kinematics/functional.py::functional_calibration",
        "kinefuse/pipelines/kinefuse_fusion.py::kinefuse_fusion",
        "kinefuse/pipelines/neura_imu_only.py::run_neura_imu_only",
        "kinefuse/pipelines/offset_bridge.py::prequential_bridge",
        "kinefuse/pipelines/realism.py::run_realism",
        "kinefuse/pipelines/session.py::process_recording",
        "kinefuse/pipelines/vision_assisted.py::vision_assisted_from_recording",
        "kinefuse/session.py::load_session",
        "kinefuse/sim/imu.py::simulate_imu_from_pose",
        "kinefuse/streaming/engine.py::Engine.push_imu",
        "kinefuse/streaming/engine.py::offline_causal",
        "kinefuse/streaming/replay.py::run_replay",
        "kinefuse/streaming/runner.py::run_loop",
        "kinefuse/streaming/runner.py::run_stream",
    }
)


# ---- the source model ------------------------------------------------------------------------


@dataclass(frozen=True)
class Module:
    name: str  # dotted, e.g. kinefuse.filters.kalman
    rel: str  # path relative to src/, e.g. kinefuse/filters/kalman.py
    tree: ast.Module
    n_lines: int
    is_package: bool


def _modules() -> dict[str, Module]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(SRC).as_posix()
        parts = rel[: -len(".py")].split("/")
        is_package = parts[-1] == "__init__"
        if is_package:
            parts = parts[:-1]
        text = path.read_text(encoding="utf-8")
        tree = ast.parse(text, filename=rel)
        out[".".join(parts)] = Module(
            ".".join(parts), rel, tree, len(text.splitlines()), is_package
        )
    return out


MODULES = _modules()


def _absolute(module: Module, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = module.name.split(".")
    if not module.is_package:
        base = base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _targets(module: Module, node: ast.Import | ast.ImportFrom) -> list[str]:
    """Modules an import statement names (``from a import b`` names ``a`` and ``a.b`` if a module)."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    base = _absolute(module, node)
    subs = [f"{base}.{alias.name}" for alias in node.names if f"{base}.{alias.name}" in MODULES]
    return [base, *subs]


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _module_level_imports(module: Module) -> list[ast.Import | ast.ImportFrom]:
    """Imports that run when the module is imported (not in functions, not TYPE_CHECKING-only)."""
    found: list[ast.Import | ast.ImportFrom] = []

    def visit(body):
        for node in body:
            if isinstance(node, ast.Import | ast.ImportFrom):
                found.append(node)
            elif isinstance(node, ast.If) and _is_type_checking(node):
                visit(node.orelse)
            elif isinstance(node, ast.If | ast.Try | ast.With | ast.ClassDef):
                for field in ("body", "orelse", "finalbody", "handlers"):
                    for child in getattr(node, field, []):
                        visit(child.body if isinstance(child, ast.ExceptHandler) else [child])

    visit(module.tree.body)
    return found


def _with_parents(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[: i + 1]) for i in range(len(parts))]


def _loads_kernels() -> set[str]:
    """kinefuse modules whose import (at module level, transitively) imports a kernel module."""
    edges: dict[str, set[str]] = {}
    for module in MODULES.values():
        deps = set()
        for node in _module_level_imports(module):
            for target in _targets(module, node):
                deps.update(p for p in _with_parents(target) if p in MODULES)
        edges[module.name] = deps
    loads = set(KERNEL_MODULES)
    changed = True
    while changed:
        changed = False
        for name, deps in edges.items():
            if name not in loads and deps & loads:
                loads.add(name)
                changed = True
    return loads


def _function_imports(module: Module):
    """(qualified function name, import node) for every import inside a function body."""

    def visit(node, qual, in_function):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                yield from visit(child, f"{qual}{child.name}.", True)
            elif isinstance(child, ast.ClassDef):
                yield from visit(child, f"{qual}{child.name}.", in_function)
            elif isinstance(child, ast.Import | ast.ImportFrom) and in_function:
                yield qual.rstrip("."), child
            else:
                yield from visit(child, qual, in_function)

    yield from visit(module.tree, "", False)


def _calls_interpret_kernels(module: Module) -> bool:
    return any(
        isinstance(node, ast.Call)
        and (
            (isinstance(node.func, ast.Attribute) and node.func.attr == "interpret_kernels")
            or (isinstance(node.func, ast.Name) and node.func.id == "interpret_kernels")
        )
        for node in ast.walk(module.tree)
    )


def _public_functions(module: Module):
    """(qualified name, lines of code without the docstring) of public functions and methods."""

    def visit(body, qual):
        for node in body:
            if isinstance(node, ast.ClassDef):
                yield from visit(node.body, f"{qual}{node.name}.")
            elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                if node.name.startswith("_"):
                    continue
                n = node.end_lineno - node.lineno + 1
                doc = node.body[0]
                if (
                    isinstance(doc, ast.Expr)
                    and isinstance(doc.value, ast.Constant)
                    and isinstance(doc.value.value, str)
                ):
                    n -= doc.end_lineno - doc.lineno + 1
                yield f"{qual}{node.name}", n

    yield from visit(module.tree.body, "")


# ---- the checks --------------------------------------------------------------------------------


def function_import_violations() -> set[str]:
    kernel_loaders = _loads_kernels()
    out = set()
    for module in MODULES.values():
        gate = _calls_interpret_kernels(module)
        for qual, node in _function_imports(module):
            targets = _targets(module, node)
            if all(t.split(".")[0] in OPTIONAL_DEPENDENCIES for t in targets):
                continue
            if gate and any(p in kernel_loaders for t in targets for p in _with_parents(t)):
                continue  # behind _compile.interpret_kernels (see the module's comment)
            named = ", ".join(targets[1:] or targets)  # `from a import b`: a.b if a module
            out.add(f"{module.rel}::{qual} -> {named}")
    return out


def long_module_violations() -> set[str]:
    out = set()
    for module in MODULES.values():
        if module.n_lines <= MAX_MODULE_LINES:
            continue
        doc = ast.get_docstring(module.tree) or ""
        if LONG_MODULE_MARKER not in doc:
            out.add(module.rel)
    return out


def long_function_violations() -> set[str]:
    return {
        f"{module.rel}::{qual}"
        for module in MODULES.values()
        for qual, n in _public_functions(module)
        if n > MAX_FUNCTION_LINES
    }


def _ratchet(found: set[str], allowed: frozenset[str], what: str, name: str) -> None:
    new = sorted(found - allowed)
    fixed = sorted(allowed - found)
    lines = []
    if new:
        lines.append(f"{len(new)} new {what} (fix them; see docs/architecture.md):")
        lines += [f"    {v!r}," for v in new]
    if fixed:
        lines.append(f"{len(fixed)} entries of {name} are no longer violations; remove them:")
        lines += [f"    {v!r}," for v in fixed]
    assert not lines, "\n".join(lines)


def test_imports_inside_functions_only_for_optional_dependencies():
    _ratchet(
        function_import_violations(),
        ALLOWED_FUNCTION_IMPORTS,
        "imports inside functions",
        "ALLOWED_FUNCTION_IMPORTS",
    )


def test_modules_at_most_700_lines_unless_they_say_why():
    _ratchet(
        long_module_violations(),
        ALLOWED_LONG_MODULES,
        f"modules above {MAX_MODULE_LINES} lines without {LONG_MODULE_MARKER!r} in the docstring",
        "ALLOWED_LONG_MODULES",
    )


def test_public_functions_at_most_80_lines():
    _ratchet(
        long_function_violations(),
        ALLOWED_LONG_FUNCTIONS,
        f"public functions above {MAX_FUNCTION_LINES} lines of code",
        "ALLOWED_LONG_FUNCTIONS",
    )


# ---- the checker checks itself on small sources ---------------------------------------------


def _fake(name: str, source: str, is_package: bool = False) -> Module:
    tree = ast.parse(source)
    rel = name.replace(".", "/") + ("/__init__.py" if is_package else ".py")
    return Module(name, rel, tree, len(source.splitlines()), is_package)


def test_checker_sees_nested_and_relative_imports():
    mod = _fake(
        "kinefuse.pkg.mod",
        "import os\n"
        "def f():\n"
        "    from . import sibling\n"
        "    class C:\n"
        "        def g(self):\n"
        "            import pylsl\n"
        "class K:\n"
        "    def m(self):\n"
        "        from ..io import load\n",
    )
    found = [(q, _targets(mod, n)[0]) for q, n in _function_imports(mod)]
    assert found == [("f", "kinefuse.pkg"), ("f.C.g", "pylsl"), ("K.m", "kinefuse.io")]


def test_checker_counts_code_lines_without_the_docstring():
    body = "\n".join(f"    x{i} = {i}" for i in range(3))
    mod = _fake(
        "kinefuse.m", f'def f():\n    """Doc.\n\n    More.\n    """\n{body}\ndef _g():\n    pass\n'
    )
    assert list(_public_functions(mod)) == [("f", 4)]


def test_checker_ignores_type_checking_imports():
    mod = _fake(
        "kinefuse.m",
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import kinefuse.x\nelse:\n"
        "    import kinefuse.y\n",
    )
    names = [_targets(mod, n)[0] for n in _module_level_imports(mod)]
    assert names == ["typing", "kinefuse.y"]
