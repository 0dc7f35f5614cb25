"""`kinefuse batch`: a study of real UTD-MHAD wrist sessions on a 2-worker LocalCluster.

The study numbers are checked against `kinefuse run`'s back-end run on each session in this
process (the single-session path, not the batch code); one broken session is a failed row; a
worker killed while it runs a task leaves a complete, correct table; a rerun skips finished
work; --force redoes it. Every server binds 127.0.0.1.
"""

from __future__ import annotations

import copy
import json
import os
import signal
import textwrap
from dataclasses import replace
from pathlib import Path

import pytest
from typer.testing import CliRunner

from kinefuse import batch as kb
from kinefuse import cli
from kinefuse.batch.tasks import task_dir
from kinefuse.exceptions import ConfigError, InputError

runner = CliRunner()
SESSION = Path(__file__).parent / "data" / "sessions" / "utd_mhad_a9_s1_t1.toml"
#: Eight small wrist trials (actions 1-21 carry the IMU on the right wrist).
TRIALS = [(a, s, 1) for a in (1, 5, 9, 12) for s in (1, 2)]


def _err(result) -> str:
    try:
        return result.stderr
    except ValueError:
        return result.output


def _session_text(inertial: Path, skeleton: Path, name: str) -> str:
    text = SESSION.read_text(encoding="utf-8")
    text = text.replace('name = "utd-mhad-a9-s1-t1"', f'name = "{name}"')
    text = text.replace('name = "paper-a"', 'name = "imu-only"')
    for old, new in (("Inertial/a9_s1_t1_inertial.mat", inertial), ("Skeleton/a9_s1_t1_skeleton.mat", skeleton)):  # fmt: skip
        text = text.replace(f'"../../../../shared/data/utd_mhad/{old}"', f'"{new}"')
    return text


@pytest.fixture(scope="module")
def sessions(shared_data, tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("study")
    utd = shared_data / "utd_mhad"
    for a, s, t in TRIALS:
        stem = f"a{a}_s{s}_t{t}"
        (d / f"utd_{stem}.toml").write_text(
            _session_text(
                utd / "Inertial" / f"{stem}_inertial.mat",
                utd / "Skeleton" / f"{stem}_skeleton.mat",
                f"utd-{stem}",
            ),
            encoding="utf-8",
        )
    # broken: a truncated inertial file (the reader fails on the worker)
    bad = d / "truncated_inertial.mat"
    bad.write_bytes((utd / "Inertial" / "a3_s1_t1_inertial.mat").read_bytes()[:300])
    (d / "zz_broken.toml").write_text(
        _session_text(bad, utd / "Skeleton" / "a3_s1_t1_skeleton.mat", "broken"),
        encoding="utf-8",
    )
    return d


def _numba_threads() -> int:
    import numba

    return numba.config.NUMBA_NUM_THREADS


def _malloc_env() -> tuple:
    import os

    return os.environ.get("MALLOC_TRIM_THRESHOLD_"), os.environ.get("OPENBLAS_NUM_THREADS")


@pytest.fixture(scope="module")
def client():
    from distributed import Client

    from kinefuse.batch.runner import start_local_cluster

    cluster = start_local_cluster(2)
    c = Client(cluster)
    assert all(a.startswith("tcp://127.0.0.1:") for a in (cluster.scheduler_address, *c.nthreads()))
    assert set(c.run(_numba_threads).values()) == {1}  # numba single-threaded in each worker
    # glibc's adaptive malloc kept (Dask's MALLOC_TRIM_THRESHOLD_ made IMU-only runs 3x slower),
    # Dask's one BLAS thread per worker kept; unless this process itself sets the variable
    trim = os.environ.get("MALLOC_TRIM_THRESHOLD_")
    assert set(c.run(_malloc_env).values()) == {(trim, "1")}
    yield c
    c.close()
    cluster.close()


@pytest.fixture(scope="module")
def serial(sessions, tmp_path_factory) -> dict:
    """metrics.json of `kinefuse run`'s back-end on every good session, in this process."""
    from kinefuse.pipelines.run import run_session

    out = tmp_path_factory.mktemp("serial")
    res = {}
    for a, s, t in TRIALS:
        stem = f"a{a}_s{s}_t{t}"
        run_session(sessions / f"utd_{stem}.toml", out / stem)
        res[f"utd-{stem}"] = json.loads((out / stem / "metrics.json").read_text())
    return res


def _rows(table: dict) -> list[dict]:
    return [dict(zip(table, vals, strict=True)) for vals in zip(*table.values(), strict=True)]


def _value(rows, recording, estimate, metric, subset="all"):
    hits = [
        r["value"]
        for r in rows
        if r["recording"] == recording
        and r["estimate"] == estimate
        and r["metric"] == metric
        and r["subset"] == subset
    ]
    assert len(hits) == 1, (recording, estimate, metric, hits)
    return hits[0]


def _check_against_serial(rows, serial):
    for rec, m in serial.items():
        for est in m["methods"]:
            o = m["results"][est]["wrist_r"]["overall"]
            for ax in m["axes"]:
                assert _value(rows, rec, est, f"rmse_{ax}") == pytest.approx(o[ax], rel=1e-9)
            assert _value(rows, rec, est, "rmse_3d") == pytest.approx(o["rmse_3d"], rel=1e-9)
            assert _value(rows, rec, est, "error_cdf_0.9") == pytest.approx(
                o["error_at_p"], rel=1e-9
            )
            assert _value(rows, rec, est, "n_samples") == o["n_samples"]


@pytest.fixture(scope="module")
def first_run(sessions, client, tmp_path_factory):
    """The study, with one worker process killed (SIGKILL) while it runs a task."""
    out = tmp_path_factory.mktemp("batch") / "out"
    study = kb.study_from_sessions(sessions, out_dir=out)
    killed = []

    def on_event(kind, payload):
        if kind != "finished" or killed:
            return
        busy = [w for w, keys in client.processing().items() if keys]
        if busy:
            pid = client.run(os.getpid, workers=busy[:1])[busy[0]]
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
            # what a worker killed mid-write leaves (whether this one got that far is timing)
            final = task_dir(out, study.tasks[0])
            final.with_name(f".tmp-{final.name}-0dead000").mkdir(parents=True)

    summary = kb.run_study(study, client=client, quiet=True, on_event=on_event)
    return study, summary, killed


def test_study_matches_single_session_runs_despite_a_killed_worker(first_run, serial):
    from kinefuse.batch.table import read_table

    study, summary, killed = first_run
    assert killed, "no worker was busy to be killed"
    assert summary["counts"] == {"done": 8, "skipped": 0, "failed": 1, "total": 9}
    ((key, error),) = summary["failed"]
    assert key == "broken/imu-only" and "truncated_inertial.mat" in error and "\n" not in error
    parquet, csv = summary["table"]
    rows = _rows(read_table(parquet))
    assert {r["recording"] for r in rows} == {*serial, "broken"}
    _check_against_serial(rows, serial)
    bad = [r for r in rows if r["recording"] == "broken"]
    assert len(bad) == 1 and bad[0]["status"] == "failed" and bad[0]["error"] == error
    assert all(r["calibrated_on"] == "camera" for r in rows if r["status"] == "done")
    # CSV holds the same rows
    import pyarrow.csv as pacsv

    assert pacsv.read_csv(str(csv)).num_rows == len(rows)
    # per recording: kinefuse run's outputs, published once, no temporaries left
    rec_root = study.out_dir / "recordings"
    assert not list(rec_root.glob("*/.tmp-*"))
    for rec in serial:
        files = {p.name for p in (rec_root / rec / "imu-only").iterdir()}
        assert {f"{rec}_joints.csv", f"{rec}_joints.trc", "report.html", "metrics.json"} <= files
    assert not (rec_root / "broken" / "imu-only").exists()


def test_run_warnings_are_kept_per_task_and_summarised(first_run):
    """Every finished task keeps its run's warnings (as `kinefuse run` prints them); the
    printed summary names the tasks that have some and the study report lists them."""
    from kinefuse.batch.report import _warnings_section
    from kinefuse.batch.runner import _warned_line, summary_tables

    _, summary, _ = first_run
    done = [r for r in summary["results"] if r["status"] != "failed"]
    assert done and all(isinstance(r["warnings"], list) for r in done)
    one = dict(done[0], warnings=["knee_r <axis> tilted"])
    fake = dict(summary, results=[one, *({**r, "warnings": []} for r in done[1:])])
    (line,) = [r.labels[1] for r in summary_tables(fake)[0].rows if r.labels[0] == "warnings"]
    assert line.startswith(f"1 of {len(done)} tasks: {one['recording']}/{one['method']} (1)")
    page = _warnings_section(fake["results"])
    assert 'class="warnings"' in page and "knee_r &lt;axis&gt; tilted" in page
    assert _warnings_section([{**r, "warnings": []} for r in done]) == ""
    many = [{"recording": f"r{i}", "method": "imu-only", "warnings": ["w"]} for i in range(7)]
    assert _warned_line(many, 9) == (
        "7 of 9 tasks: r0/imu-only (1), r1/imu-only (1), r2/imu-only (1), r3/imu-only (1), "
        "r4/imu-only (1) and 2 more; the study report lists them"
    )


def test_rerun_skips_finished_and_force_redoes_despite_a_restart(first_run, serial, client):
    from kinefuse.batch.table import read_table

    study, _, _ = first_run
    marker = study.out_dir / "recordings" / "utd-a1_s1_t1" / "imu-only" / "result.json"
    before = marker.stat().st_mtime_ns
    again = kb.run_study(study, client=client, quiet=True, report=False)
    assert again["counts"] == {"done": 0, "skipped": 8, "failed": 1, "total": 9}
    assert marker.stat().st_mtime_ns == before
    _check_against_serial(_rows(read_table(again["table"][0])), serial)
    # --force on one recording, the cluster restarted meanwhile: redone, same numbers
    pick = ("utd-a1_s1_t1",)
    two = replace(study, tasks=tuple(t for t in study.tasks if t.recording in pick))
    events = []

    def restart_once(kind, payload):  # the cluster loses the submitted tasks: resubmitted
        events.append(kind)
        if kind == "poll" and events.count("poll") == 1:
            # a restarted worker re-imports kinefuse and may load cold numba caches on a loaded
            # 2-core machine: distributed's default 120 s wait for it was seen to run out in CI,
            # and once one worker of two had not returned after 600 s; the study needs one, so
            # the restart does not wait for them (the run below waits for its results)
            client.restart(timeout=600, wait_for_workers=False)

    forced = kb.run_study(
        two, client=client, force=True, quiet=True, report=False, on_event=restart_once
    )
    assert "resubmitted" in events
    assert forced["counts"] == {"done": 1, "skipped": 0, "failed": 0, "total": 1}
    assert marker.stat().st_mtime_ns != before
    rows = _rows(read_table(forced["table"][0]))
    _check_against_serial(rows, {k: serial[k] for k in pick})


def test_study_report_lists_failures_and_renders(first_run, tmp_path):
    from _chromium import _run, count_loaded_images, ensure_chromium

    _, summary, _ = first_run
    html = summary["report"].read_text(encoding="utf-8")
    assert "truncated_inertial.mat" in html and "Calibrated on: camera" in html
    assert "Inside camera outages" not in html  # UTD-MHAD has none (SOURCE.md)
    assert html.count("<img ") == 2  # 3-D RMSE and CDF 0.9 box plots (no outages in the data)
    browser = ensure_chromium()
    assert count_loaded_images(browser, summary["report"]) == (2, 2)
    r = _run(
        browser, ["--dump-dom", "--enable-logging=stderr", "--v=0"], summary["report"].as_uri()
    )
    assert "CONSOLE" not in r.stderr and "Uncaught" not in r.stderr, r.stderr[-800:]


def test_cli_rerun_on_a_glob_starts_no_cluster(first_run, sessions, monkeypatch):
    study, _, _ = first_run
    import kinefuse.batch.runner as runner_mod

    def no_cluster(*a, **k):
        raise AssertionError("a rerun with nothing to do must not start a cluster")

    monkeypatch.setattr(runner_mod, "connect", no_cluster)
    res = runner.invoke(
        cli.app, ["batch", str(sessions / "utd_*.toml"), "--out", str(study.out_dir), "--quiet"]
    )
    assert res.exit_code == 0, (res.output, _err(res))


def test_cli_without_the_batch_extra_says_what_to_install(monkeypatch, sessions):
    monkeypatch.setattr(kb, "missing_packages", lambda: ["distributed"])
    res = runner.invoke(cli.app, ["batch", str(sessions)])
    assert res.exit_code == 1
    assert "pip install 'kinefuse[batch]'" in _err(res)


# ------------------------------------------------------------------------------------------
# study files (no cluster)
# ------------------------------------------------------------------------------------------

STUDY = """\
    [study]
    name = "utd"
    methods = ["imu-only", "kinefuse"]
    [defaults]
    skeleton = {{ body_height_m = 1.75 }}
    method = {{ parameters = {{ calibration = "vision", calibration_window_s = 10.0 }} }}
    [[recordings]]
    files = "{utd}/Inertial/a[19]_s1_t1_inertial.mat"
    pattern = 'a(?P<a>\\d+)_s(?P<s>\\d+)_t(?P<t>\\d+)_inertial'
    [recordings.session]
    session = {{ name = "a{{a}}-s{{s}}-t{{t}}" }}
    imu = {{ format = "utd_mhad", path = "{{path}}", segments = {{ forearm_r = "utd_mhad_inertial" }} }}
    camera = {{ format = "utd_mhad", path = "{{dir}}/../Skeleton/a{{a}}_s{{s}}_t{{t}}_skeleton.mat" }}
    reference = {{ format = "utd_mhad", path = "{{dir}}/../Skeleton/a{{a}}_s{{s}}_t{{t}}_skeleton.mat" }}
    [overrides."a9-*"]
    methods = ["imu-only"]
    method = {{ parameters = {{ calibration_window_s = 5.0 }} }}
    {extra}
"""


def _study(tmp_path, shared_data, extra="") -> Path:
    p = tmp_path / "study.toml"
    text = STUDY.format(utd=shared_data / "utd_mhad", extra=extra)
    p.write_text(textwrap.dedent(text), encoding="utf-8")
    return p


def test_study_file_templates_defaults_overrides(tmp_path, shared_data):
    st = kb.load_study(_study(tmp_path, shared_data))
    assert [t.key for t in st.tasks] == [
        "a1-s1-t1/imu-only",
        "a1-s1-t1/kinefuse",
        "a9-s1-t1/imu-only",
    ]
    assert all(t.error is None for t in st.tasks)
    assert st.out_dir == (tmp_path / "results" / "utd").resolve()
    a1, _, a9 = st.tasks
    assert a1.document["method"]["parameters"]["calibration_window_s"] == 10.0
    assert a9.document["method"]["parameters"] == {
        "calibration": "vision",
        "calibration_window_s": 5.0,
    }
    assert a9.document["camera"]["path"].endswith("Skeleton/a9_s1_t1_skeleton.mat")


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        (
            '[overrides."x"]\nskeletn = { body_height_m = 1.8 }',
            r"\[overrides.'x'\] skeletn: unknown key \(did you mean 'skeleton'\?\)",
        ),
        ("[study2]\n", r"\[top level\] study2: unknown key \(did you mean 'study'\?\)"),
        (
            "[defaults.imu]\nrate_hzz = 50",
            r"\[defaults.imu\] rate_hzz: unknown key \(did you mean 'rate_hz'\?\)",
        ),
    ],
)
def test_study_file_unknown_keys(tmp_path, shared_data, extra, match):
    with pytest.raises(ConfigError, match=match):
        kb.load_study(_study(tmp_path, shared_data, extra))


def test_study_file_bad_glob_placeholder_and_session(tmp_path, shared_data):
    p = _study(tmp_path, shared_data)
    text = p.read_text()
    p.write_text(text.replace("a[19]_s1", "a99_s1"))
    with pytest.raises(ConfigError, match="matches no file"):
        kb.load_study(p)
    p.write_text(text.replace("{dir}/../Skeleton", "{dri}/../Skeleton"))
    with pytest.raises(
        ConfigError, match=r"unknown placeholder \{dri\} \(did you mean \{dir\}\?\)"
    ):
        kb.load_study(p)
    # a bad session is a failed task, not a failed study
    p.write_text(text.replace("body_height_m = 1.75", "body_height_m = 175"))
    st = kb.load_study(p)
    assert all("not a plausible body height" in t.error for t in st.tasks)


def test_example_study_lists_the_utd_mhad_wrist_trials(shared_data):
    root = Path(__file__).resolve().parents[1]
    st = kb.load_study(root / "examples" / "studies" / "utd_mhad_wrist.toml")
    assert len(st.recordings) == 503  # actions 1-21 x subjects 1-6 x 4 trials, 1 never released
    assert st.methods == ("imu-only", "elm-fir", "kinefuse") and len(st.tasks) == 3 * 503
    assert all(t.error is None for t in st.tasks)


# ---- kinefuse experiment --workers: an experiment's trials through the same cluster path ----


def _numbers(tree, path=""):
    """Every number of a results tree by its path, timing keys left out (they differ per run)."""
    if isinstance(tree, dict):
        out = {}
        for k, v in tree.items():
            if "time" in str(k) or str(k).endswith("_ms"):
                continue
            out.update(_numbers(v, f"{path}/{k}"))
        return out
    if isinstance(tree, (list, tuple)):
        out = {}
        for i, v in enumerate(tree):
            out.update(_numbers(v, f"{path}[{i}]"))
        return out
    if isinstance(tree, (int, float)) and not isinstance(tree, bool):
        return {path: float(tree)}
    return {path: tree}


@pytest.mark.parametrize("name", ["paper-a", "paper-b"])
def test_experiment_trials_on_dask_equal_the_serial_run(client, shared_data, name):
    import numpy as np

    from kinefuse.apps.experiments import run_experiment
    from kinefuse.batch.trials import dask_trial_map

    serial = run_experiment(name, shared_data, quick=True, quiet=True)
    on_dask = run_experiment(
        name, shared_data, quick=True, quiet=True, trial_map=dask_trial_map(client)
    )
    a, b = _numbers(serial["results"]), _numbers(on_dask["results"])
    assert a.keys() == b.keys()
    nums = [k for k, v in a.items() if isinstance(v, float)]
    assert len(nums) > 50
    assert [a[k] for k in a if k not in nums] == [b[k] for k in b if k not in nums]
    # same code and seeds; only the BLAS summation order may differ between processes
    np.testing.assert_allclose([b[k] for k in nums], [a[k] for k in nums], rtol=1e-9, atol=1e-12)
    assert serial["notes"] == on_dask["notes"]


def test_trial_map_keeps_call_order_and_raises_a_trials_error(client):
    import operator

    from kinefuse.batch.trials import dask_trial_map

    trial_map = dask_trial_map(client)
    seen = []
    assert trial_map(pow, [(2, k) for k in range(12)], lambda: seen.append(1)) == [
        2**k for k in range(12)
    ]
    assert len(seen) == 12
    with pytest.raises(ZeroDivisionError):
        trial_map(operator.truediv, [(1, 1), (1, 0), (2, 1)])


def test_cli_experiment_workers_refused_before_a_cluster(monkeypatch):
    import kinefuse.batch.runner as runner_mod

    def no_cluster(*a, **k):
        raise AssertionError("refused input must not start a cluster")

    monkeypatch.setattr(runner_mod, "connect", no_cluster)
    res = runner.invoke(cli.app, ["experiment", "neura-imu-only", "--workers", "2"])
    assert res.exit_code == 2
    assert "only paper-a and paper-b run on Dask" in _err(res)
    monkeypatch.setattr(kb, "missing_packages", lambda: ["distributed"])
    res = runner.invoke(cli.app, ["experiment", "paper-b", "--quick", "--workers", "2"])
    assert res.exit_code == 1
    assert "pip install 'kinefuse[batch]'" in _err(res)


def test_cli_and_apps_agree_on_the_trial_experiments():
    from kinefuse.apps.experiments import TRIAL_EXPERIMENTS
    from kinefuse.cli.offline import TRIAL_EXPERIMENTS as CLI_TRIAL_EXPERIMENTS

    assert CLI_TRIAL_EXPERIMENTS == TRIAL_EXPERIMENTS


def test_summary_says_which_rows_equal_the_reference():
    from kinefuse.batch.report import summary_table

    def result(recording, values):
        rows = [
            {"estimate": e, "joint": "wrist_r", "metric": "rmse_3d", "subset": "all", "value": v}
            for e, v in values.items()
        ]
        return {"recording": recording, "status": "done", "rows": rows}

    # the camera equals the reference on every recording; kinefuse only on one
    results = [
        result("r1", {"camera": 0.0, "kinefuse": 0.03, "IMU chain": 0.05}),
        result("r2", {"camera": 0.0, "kinefuse": 0.0, "IMU chain": 0.06}),
    ]
    (note,) = summary_table(results, "all", "t").notes
    named = note.split(":")[0]
    assert "camera" in named and "kinefuse" not in named and "IMU chain" not in named
    results[1]["rows"][0]["value"] = 0.01  # the camera differs once: nothing to note
    assert summary_table(results, "all", "t").notes == ()


def test_summary_without_any_reference_says_so_instead_of_an_empty_table():
    """IMU-only sessions (no [reference]) give no error rows: the summary says there is nothing
    to score and where the outputs are, instead of printing an empty error table."""
    from kinefuse.batch.report import NO_SCORES
    from kinefuse.batch.runner import summary_tables

    done = {"recording": "x", "status": "done", "rows": [
        {"estimate": "task", "joint": "all", "metric": "task_wall_s", "subset": "all", "value": 0.9}
    ]}  # fmt: skip
    summary = {"counts": {"total": 1, "done": 1, "skipped": 0, "failed": 0}, "study": "s",
               "cluster": "c", "wall_s": 1.0, "tasks_wall_s": 0.9, "table": ["t.csv"],
               "results": [done], "failed": []}  # fmt: skip
    (run,) = summary_tables(summary)  # no error table
    assert ("scores", NO_SCORES) in [r.labels for r in run.rows]
    done["rows"].append(
        {
            "estimate": "IMU chain",
            "joint": "knee_l",
            "metric": "rmse_3d",
            "subset": "all",
            "value": 0.04,
        }
    )
    run, scores = summary_tables(summary)
    assert "scores" not in [r.labels[0] for r in run.rows] and len(scores.rows) == 1


# ---- a study's layers, compare-workers, refused input (no cluster) ----


def _minimal_session(utd: Path, name: str, extra: str = "") -> str:
    stem = "a9_s1_t1"
    return textwrap.dedent(
        f"""\
        [session]
        name = "{name}"
        [imu]
        format = "utd_mhad"
        path = "{utd / "Inertial" / f"{stem}_inertial.mat"}"
        [imu.segments]
        forearm_r = "utd_mhad_inertial"
        [camera]
        format = "utd_mhad"
        path = "{utd / "Skeleton" / f"{stem}_skeleton.mat"}"
        [reference]
        format = "utd_mhad"
        path = "{utd / "Skeleton" / f"{stem}_skeleton.mat"}"
        [method]
        name = "imu-only"
        """
    ) + textwrap.dedent(extra)


_LAYERED_STUDY = """\
[study]
name = "layers"
[defaults]
{defaults}
[[recordings]]
sessions = ["sessions/*.toml"]
{overrides}
"""


def _layered(tmp_path, shared_data, session_extra, defaults, overrides=""):
    """A study of one session (``session_extra`` appended) under ``defaults`` and ``overrides``;
    the task's merged parameters (as `kinefuse run` would process them)."""
    from kinefuse.session_file import load_session

    (tmp_path / "sessions").mkdir()
    (tmp_path / "sessions" / "s.toml").write_text(
        _minimal_session(shared_data / "utd_mhad", "rec-1", session_extra), encoding="utf-8"
    )
    p = tmp_path / "study.toml"
    p.write_text(_LAYERED_STUDY.format(defaults=defaults, overrides=overrides), encoding="utf-8")
    (task,) = kb.load_study(p).tasks
    assert task.error is None, task.error
    return load_session(task.source, document=task.document).processing_parameters()


DOC_DEFAULTS = """\
skeleton = { body_height_m = 1.75 }
method = { parameters = { calibration = "vision", calibration_window_s = 10.0 } }"""


def test_defaults_yield_to_the_sessions_own_calibration_section(tmp_path, shared_data):
    """docs/batch.md's defaults and a session's own `[calibration] method`: the session wins
    (they are one setting), the defaults' other settings still apply."""
    params = _layered(tmp_path, shared_data, '[calibration]\nmethod = "reference"\n', DOC_DEFAULTS)
    assert params["calibration"] == "reference"
    assert params["calibration_window_s"] == 10.0


def test_defaults_calibration_section_yields_to_the_sessions_parameters(tmp_path, shared_data):
    params = _layered(
        tmp_path,
        shared_data,
        '[method.parameters]\ncalibration = "reference"\nroot = "reference"\n',
        '[defaults.calibration]\nmethod = "vision"\nwindow_s = 4.0\n'
        '[defaults.skeleton]\nbody_height_m = 1.75\nroot = "vision"',
    )
    assert params["calibration"] == "reference" and params["root"] == "reference"
    assert params["calibration_window_s"] == 4.0


def test_overrides_win_over_the_sessions_own_calibration(tmp_path, shared_data):
    params = _layered(
        tmp_path,
        shared_data,
        '[calibration]\nmethod = "reference"\n',
        DOC_DEFAULTS,
        '[overrides."rec-*"]\nmethod = { parameters = { calibration = "vision" } }',
    )
    assert params["calibration"] == "vision"


def test_same_setting_table_is_what_processing_parameters_merges(tmp_path):
    """Every pair of spellings the study layers treat as one setting is one that
    `SessionConfig.processing_parameters` merges, and it merges no other."""
    from kinefuse.batch.study import _SAME_SETTING
    from kinefuse.session_file import (
        CalibrationConfig,
        ImuConfig,
        MethodConfig,
        ReferenceConfig,
        SessionConfig,
        SkeletonConfig,
    )

    sections = {"calibration": {}, "skeleton": {}, "reference": {}}
    for _, (section, key) in _SAME_SETTING:
        sections[section][key] = f"value of [{section}] {key}"
    sk, ref = sections["skeleton"], sections["reference"]
    cfg = SessionConfig(
        path=tmp_path / "s.toml",
        name="s",
        out_dir=tmp_path,
        imu=ImuConfig(format="csv", path=tmp_path, rate_hz=None, segments={}),
        skeleton=SkeletonConfig(
            body_height_m=1.75,
            root=sk["root"],
            root_position_m=sk["root_position_m"],
            axes={"forearm_r": sk["axes"]},
        ),
        camera=None,
        reference=ReferenceConfig(format="csv", path=tmp_path, align=ref["align"]),
        method=MethodConfig(name="imu-only"),
        calibration=CalibrationConfig(settings=sections["calibration"]),
    )
    params = cfg.processing_parameters()
    expected = {
        param: (
            {"forearm_r": sk["axes"]}
            if (section, key) == ("skeleton", "axes")
            else sections[section][key]
        )
        for (_, _, param), (section, key) in _SAME_SETTING
    }
    assert params == expected


def _broken_sessions(tmp_path) -> Path:
    d = tmp_path / "sessions"
    d.mkdir()
    for name in ("bad-1", "bad-2"):
        (d / f"{name}.toml").write_text(
            _minimal_session(tmp_path / "no_such_folder", name), encoding="utf-8"
        )
    return d


def _no_cluster(monkeypatch):
    import kinefuse.batch.runner as runner_mod

    def no_cluster(*a, **k):
        raise AssertionError("this command must not start a cluster")

    monkeypatch.setattr(runner_mod, "connect", no_cluster)


def test_cli_compare_workers_lists_failed_tasks_and_exits_1(tmp_path, monkeypatch):
    """Sessions that fail when loaded need no cluster: each timed run records them as failed,
    and --compare-workers reports them as a plain run does."""
    _no_cluster(monkeypatch)
    d = _broken_sessions(tmp_path)
    args = ["batch", str(d), "--out", str(tmp_path / "out")]
    plain = runner.invoke(cli.app, args)
    res = runner.invoke(cli.app, [*args, "--compare-workers", "1,2"])
    assert plain.exit_code == 1 and res.exit_code == 1, (res.output, _err(res))
    assert "Failed tasks (2)" in plain.output and "Failed tasks (2)" in res.output
    assert res.output.count("Failed tasks") == 1  # same failures in both runs: listed once
    assert "bad-1/imu-only" in res.output and "no_such_folder" in res.output
    assert "2 of 2 tasks failed with 1 worker(s); 2 of 2 tasks failed with 2" in _err(res)


@pytest.mark.parametrize("counts", ["0,2", "1,-1"])
def test_cli_compare_workers_refuses_counts_below_1(tmp_path, monkeypatch, counts):
    _no_cluster(monkeypatch)
    res = runner.invoke(
        cli.app, ["batch", str(_broken_sessions(tmp_path)), "--compare-workers", counts]
    )
    assert res.exit_code == 2
    assert "--compare-workers: expected worker counts of at least 1" in _err(res)
    assert not (tmp_path / "sessions-batch").exists()
    study = kb.study_from_sessions(tmp_path / "sessions", out_dir=tmp_path / "out")
    with pytest.raises(InputError, match=r"expected each at least 1, got \[0, 2\]"):
        kb.compare_workers(study, [0, 2])
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("target", ["nope.toml", "nope", "nope/"])
def test_cli_study_that_does_not_exist_is_named(tmp_path, monkeypatch, target):
    monkeypatch.chdir(tmp_path)
    res = runner.invoke(cli.app, ["batch", target])
    assert res.exit_code == 2
    assert f"{target}: no such file or folder" in _err(res)


def test_cli_recording_instead_of_a_study_is_refused_before_running(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "walk.mat").write_bytes(b"MATLAB 5.0")
    res = runner.invoke(cli.app, ["batch", "walk.mat"])
    assert res.exit_code == 2
    assert "walk.mat: not a study or session file (*.toml)" in _err(res)
    assert "init-session SESSION.toml --from walk.mat" in _err(res)
    assert not (tmp_path / "walk-batch").exists()  # nothing written


def test_cli_existing_json_is_refused_before_running_and_says_what_force_does(
    tmp_path, monkeypatch
):
    def no_run(*a, **k):
        raise AssertionError("an existing --json file must be refused before the study runs")

    monkeypatch.setattr(kb, "run_study", no_run)
    monkeypatch.setattr(kb, "compare_workers", no_run)
    out = tmp_path / "out.json"
    out.write_text("{}", encoding="utf-8")
    d = _broken_sessions(tmp_path)
    for extra in ([], ["--force"], ["--compare-workers", "1"]):
        res = runner.invoke(cli.app, ["batch", str(d), "--json", str(out), *extra])
        assert res.exit_code == 2, (res.output, _err(res))
        err = " ".join(_err(res).split())
        assert "file exists; remove it or choose another file" in err
        assert "--force redoes every finished task and does not overwrite the --json file" in err
        assert "pass --force" not in err
    assert out.read_text(encoding="utf-8") == "{}"


def test_docs_table_snippet_runs_with_the_batch_extra_alone(tmp_path, monkeypatch):
    """docs/batch.md's Python snippet on a written study table, with pandas not importable
    (`pip install 'kinefuse[batch]'` installs distributed and pyarrow only)."""
    import re
    import sys

    from kinefuse.batch.table import flatten, write_table

    def res(recording, method, values):
        rows = [
            {"estimate": e, "joint": "wrist_r", "subset": "all", "metric": "rmse_3d",
             "value": v, "unit": "m"}
            for e, v in values.items()
        ]  # fmt: skip
        return {"recording": recording, "method": method, "status": "done", "rows": rows}

    results = [
        res("r1", "kinefuse", {"kinefuse": 0.01, "IMU chain": 0.05}),
        res("r2", "kinefuse", {"kinefuse": 0.03, "IMU chain": 0.07}),
        res("r3", "kinefuse", {"kinefuse": 0.02, "IMU chain": None}),
        {"recording": "r4", "method": "kinefuse", "status": "failed", "error": "x", "rows": []},
    ]
    parquet, _ = write_table(tmp_path, flatten(results))
    doc = (Path(__file__).resolve().parents[1] / "docs" / "batch.md").read_text(encoding="utf-8")
    (snippet,) = [
        b for b in re.findall(r"```python\n(.*?)```", doc, re.S) if "study_results.parquet" in b
    ]
    snippet = snippet.replace("results/utd-mhad-wrist/study_results.parquet", str(parquet))
    assert str(parquet) in snippet
    monkeypatch.setitem(sys.modules, "pandas", None)  # import pandas -> ImportError
    printed = []
    monkeypatch.setattr("builtins.print", lambda *a: printed.append(" ".join(map(str, a))))
    exec(compile(snippet, "docs/batch.md", "exec"), {})
    assert printed == ["kinefuse IMU chain wrist_r 0.060", "kinefuse kinefuse wrist_r 0.020"]


def test_cli_refuses_an_unusable_out_folder_before_any_task(tmp_path, monkeypatch):
    """`kinefuse batch ... --out DIR` where DIR cannot be created (``/proc`` refuses new entries
    even to root) or lies under a file: exit 2 with one line naming the folder, before any task
    runs (the study runner must not be reached)."""
    pytest.importorskip("dask.distributed")
    monkeypatch.setattr(kb, "run_study", lambda *a, **k: pytest.fail("the study ran"))
    d = _broken_sessions(tmp_path)
    afile = tmp_path / "afile"
    afile.write_text("x")
    for out, reason in (("/proc/kinefuse-batch", "not writable"), (afile / "o", "not a folder")):
        res = runner.invoke(cli.app, ["batch", str(d), "--out", str(out)])
        err = [ln for ln in _err(res).splitlines() if ln.strip()]
        assert res.exit_code == 2 and len(err) == 1, (res.exit_code, err)
        assert err[0].startswith(f"kinefuse: error: --out {out}") and reason in err[0], err


def test_a_changed_setting_reruns_the_task_instead_of_reusing_its_result(sessions, tmp_path):
    """A finished task whose study settings changed (here the calibration window) is stale:
    the next run computes it again and replaces the stored result (before: 'finished earlier
    (skipped)' with the old numbers); unchanged, it is skipped."""
    from kinefuse.batch.tasks import is_finished, is_stale, run_task, task_settings

    study = kb.study_from_sessions(sessions / "utd_*.toml", out_dir=tmp_path)
    task = study.tasks[0]
    first = run_task(task, str(tmp_path), study=study.name)
    assert first["status"] == "done" and first["settings"] == task_settings(task)
    assert run_task(task, str(tmp_path), study=study.name)["status"] == "skipped"
    doc = copy.deepcopy(task.document)
    doc["method"]["parameters"]["calibration_window_s"] = 1.0
    changed = replace(task, document=doc)
    assert is_stale(tmp_path, changed) and not is_finished(tmp_path, changed)
    again = run_task(changed, str(tmp_path), study=study.name)
    assert again["status"] == "done" and again["rerun"]
    assert again["rows"] != first["rows"]  # a 1-s window calibrates differently
    assert is_finished(tmp_path, changed) and not is_finished(tmp_path, task)
    assert run_task(changed, str(tmp_path), study=study.name)["status"] == "skipped"


def test_out_holding_another_study_is_refused_without_force(sessions, tmp_path):
    """`--out` pointing at another study's folder would replace its table and report: refused
    unless --force; the same study resumes there."""
    from kinefuse.batch.runner import _claim_out_dir

    base = kb.study_from_sessions(sessions / "utd_*.toml", out_dir=tmp_path)
    one, two = replace(base, name="one"), replace(base, name="two")
    _claim_out_dir(one, force=False)
    (tmp_path / "study_results.csv").write_text("study,recording\none,r\n", encoding="utf-8")
    _claim_out_dir(one, force=False)  # the same study: resumes
    with pytest.raises(FileExistsError, match="holds the table and report of study 'one'"):
        _claim_out_dir(two, force=False)
    (tmp_path / ".kinefuse-study.json").unlink()  # a folder from before the marker: the table
    with pytest.raises(FileExistsError, match="study 'one'"):
        _claim_out_dir(two, force=False)
    _claim_out_dir(two, force=True)
    _claim_out_dir(two, force=False)  # now two's
