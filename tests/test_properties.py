"""Property-based tests (hypothesis, issue 12): whatever the input, kinefuse either works or
raises its own error.

* Arbitrary bytes, and format headers followed by number-like noise, under every supported
  extension and every file format name: :func:`kinefuse.io.load` raises nothing but
  :class:`~kinefuse.exceptions.FormatError`.
* Random session tables, valid and invalid: :func:`kinefuse.session_file.load_session` raises
  nothing but :class:`~kinefuse.exceptions.InputError`.
* Random positive (semi-)definite models and measurements with NaN gaps: every filter gives
  finite means and symmetric PSD covariances.

Example counts are small (``max_examples``) so the file runs in seconds; ``deadline=None``
because the first call of a numba kernel compiles it.
"""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import kinefuse.io as kio
from kinefuse.exceptions import FormatError, InputError

_SETTINGS = settings(
    max_examples=25,
    deadline=None,
    database=None,
    derandomize=True,  # the same examples on every machine: a failure is reproducible
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

EXTENSIONS = (
    ".mat", ".c3d", ".trc", ".bvh", ".amc", ".asf", ".mvnx", ".xml", ".sto", ".mot", ".json",
    ".txt", ".csv", ".tsv",
)  # fmt: skip
#: Folder formats (a log folder, a dataset sample) are not single files.
FILE_FORMATS = tuple(f for f in kio.FORMATS if f not in ("ximu3", "neura"))

#: Openings of the text formats, so that the noise after them reaches the parsers.
HEADERS = (
    "# kinefuse-imu-csv 1\nt_s,sensor,qw,qx,qy,qz,acc_x,acc_y,acc_z,gyr_x,gyr_y,gyr_z\n",
    "# kinefuse-joint-csv 1\n# units: m\nt_s,elbow_r_x,elbow_r_y,elbow_r_z,elbow_r_available\n",
    "PathFileType\t4\t(X/Y/Z)\tx.trc\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\t"
    "OrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n30\t30\t2\t1\tm\t30\t1\t2\n"
    "Frame#\tTime\tElbow\n\t\tX1\tY1\tZ1\n",
    "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 3 Xposition Yposition Zposition\n"
    " End Site\n {\n  OFFSET 0 1 0\n }\n}\nMOTION\nFrames: 2\nFrame Time: 0.01\n",
    ":FULLY-SPECIFIED\n:DEGREES\n1\nroot ",
    '{"frames": [{"bodies": [{"joint_positions": ',
    '{"world_landmarks": [[',
    "PacketCounter\tAcc_X\tAcc_Y\tAcc_Z\tMat[1][1]\n",
    "Timestamp (us),Gyroscope X (deg/s),Gyroscope Y (deg/s)\n",
    "SpineBase_x,SpineBase_y,SpineBase_z,SpineBase_TrackingState\n",
    '<?xml version="1.0"?>\n<mvnx version="4">\n<subject frameRate="60">\n',
    "name\nversion=1\nnRows=2\nnColumns=4\ninDegrees=yes\nendheader\ntime\tpelvis_imu\n",
)
_NOISE = st.text(alphabet="0123456789.,-+e\t \nnaif#;", max_size=300)
CONTENT = st.one_of(
    st.binary(max_size=400),
    st.tuples(st.sampled_from(HEADERS), _NOISE).map(lambda hn: (hn[0] + hn[1]).encode()),
)


@pytest.fixture(scope="module")
def scratch():
    with tempfile.TemporaryDirectory() as d:
        yield Path(d)


def _load_only_format_error(path: Path, **kw) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            kio.load(path, **kw)
        except FormatError:
            pass


@pytest.mark.parametrize("ext", EXTENSIONS)
@_SETTINGS
@given(data=CONTENT)
def test_any_bytes_with_a_supported_extension_give_format_error(scratch, ext, data):
    path = scratch / f"recording{ext}"
    path.write_bytes(data)
    _load_only_format_error(path)


@pytest.mark.parametrize("fmt", FILE_FORMATS)
@_SETTINGS
@given(data=CONTENT)
def test_any_bytes_read_as_each_format_give_format_error(scratch, fmt, data):
    path = scratch / "recording.dat"
    path.write_bytes(data)
    _load_only_format_error(path, format=fmt)


# ------------------------------------------------------------------------------- sessions
_SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-5, 5),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.sampled_from(["paper-a", "elm-fir", "csv", "joint-csv", "imu.csv", "IMU 1", "forearm_r"]),
)
_VALUES = st.recursive(
    _SCALARS,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner),
    max_leaves=6,
)
_SECTION_KEYS = {
    "session": ["name", "out_dir", "extra"],
    "imu": ["format", "path", "segments", "rate_hz"],
    "skeleton": ["body_height_m", "lengths"],
    "camera": ["format", "path", "availability_threshold"],
    "reference": ["format", "path"],
    "method": ["name", "parameters"],
    "bogus": ["x"],
}
_GOOD = {
    "session": {"name": "s"},
    "imu": {"format": "csv", "path": "imu.csv", "segments": {"forearm_r": "IMU 2"}},
    "skeleton": {"body_height_m": 1.75},
    "method": {"name": "paper-a"},
}


@st.composite
def session_tables(draw):
    """The valid session, with random sections, keys and values replaced, added or removed."""
    table = {k: dict(v) for k, v in _GOOD.items()}
    for _ in range(draw(st.integers(0, 4))):
        section = draw(st.sampled_from(sorted(_SECTION_KEYS)))
        op = draw(st.sampled_from(["set", "drop", "drop_section", "not_a_table"]))
        if op == "drop_section":
            table.pop(section, None)
        elif op == "not_a_table":
            table[section] = draw(_SCALARS)
        else:
            sec = table.setdefault(section, {})
            if not isinstance(sec, dict):
                continue
            key = draw(st.sampled_from(_SECTION_KEYS[section]))
            if op == "drop":
                sec.pop(key, None)
            else:
                sec[key] = draw(_VALUES)
    return table


def _toml(table: dict) -> str:
    import json

    def value(v):
        if v is None:
            return '""'
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, float):
            return (
                "nan"
                if v != v
                else ("inf" if v > 0 else "-inf")
                if abs(v) == float("inf")
                else repr(v)
            )
        if isinstance(v, int):
            return str(v)
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return "{" + ", ".join(f"{json.dumps(k)} = {value(x)}" for k, x in v.items()) + "}"

    lines = []
    for section, body in table.items():
        if not isinstance(body, dict):
            lines.insert(0, f"{section} = {value(body)}")
            continue
        lines.append(f"[{section}]")
        lines += [f"{json.dumps(k)} = {value(v)}" for k, v in body.items()]
    return "\n".join(lines) + "\n"


@_SETTINGS
@given(table=session_tables())
def test_random_session_tables_give_input_error_only(scratch, table):
    from kinefuse.session_file import load_session

    (scratch / "imu.csv").write_text("# kinefuse-imu-csv 1\nt_s,sensor,qw,qx,qy,qz\n")
    path = scratch / "session.toml"
    path.write_text(_toml(table), encoding="utf-8")
    try:
        load_session(path)
    except InputError:
        pass


@_SETTINGS
@given(text=st.text(max_size=300))
def test_random_session_text_gives_input_error_only(scratch, text):
    from kinefuse.session_file import load_session

    path = scratch / "session.toml"
    path.write_text(text, encoding="utf-8")
    try:
        load_session(path)
    except InputError:
        pass


# -------------------------------------------------------------------------------- filters
def _filters(model):
    from kinefuse.filters import EMKalmanFilter, IntegratedFilter, KalmanFilter, UFIRFilter

    return {
        "KF": KalmanFilter(model),
        "EM-KF": EMKalmanFilter(model),
        "UFIR": UFIRFilter(model, horizon=8),
        "EM-KF/FIR": IntegratedFilter(model, horizon=8),
    }


@st.composite
def models_and_measurements(draw):
    from kinefuse.models import constant_velocity

    dt = draw(st.sampled_from([1 / 100, 1 / 30, 0.1]))
    q = draw(st.floats(1e-4, 1e2))
    r_diag = np.array(draw(st.lists(st.floats(1e-5, 1.0), min_size=3, max_size=3)))
    rot = np.linalg.qr(np.random.default_rng(draw(st.integers(0, 2**16))).normal(size=(3, 3)))[0]
    r = rot @ np.diag(r_diag) @ rot.T  # a full SPD measurement covariance
    model = constant_velocity(dt, q, 0.5 * (r + r.T))
    seed = draw(st.integers(0, 2**16))
    rng = np.random.default_rng(seed)
    T = draw(st.integers(1, 60))
    z = np.cumsum(rng.normal(scale=0.05, size=(T, 3)), axis=0)
    gaps = rng.random(T) < draw(st.floats(0.0, 0.9))
    z[gaps] = np.nan
    if T > 4 and draw(st.booleans()):
        z[rng.integers(T)] += rng.normal(scale=5.0, size=3)  # an outlier
    return model, z


def _assert_psd(P, what):
    assert np.all(np.isfinite(P)), what
    np.testing.assert_allclose(P, np.swapaxes(P, -1, -2), rtol=1e-9, atol=1e-12, err_msg=what)
    scale = np.max(np.abs(np.diagonal(P, axis1=-2, axis2=-1)), axis=-1, keepdims=True)
    eig = np.linalg.eigvalsh(0.5 * (P + np.swapaxes(P, -1, -2)))
    assert np.all(eig >= -1e-9 * scale), (what, eig.min())


@_SETTINGS
@given(case=models_and_measurements())
def test_every_filter_gives_finite_means_and_psd_covariances(case):
    model, z = case
    started = np.flatnonzero(np.all(np.isfinite(z), axis=1))
    for name, f in _filters(model).items():
        if started.size == 0:  # never observed: a clear error, nothing invented
            with pytest.raises(InputError, match="all NaN"):
                f.filter(z)
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            _, res = f.filter(z)
        k0 = started[0]
        assert np.all(np.isfinite(res.mean[k0:])), name
        _assert_psd(res.cov[k0:], name)


@_SETTINGS
@given(case=models_and_measurements(), other=models_and_measurements())
def test_imm_gives_finite_means_and_psd_covariances(case, other):
    from kinefuse.filters import IMM
    from kinefuse.models import constant_velocity

    (m_imu, z_imu), (m_cam, z_cam) = case, other
    T = min(len(z_imu), len(z_cam))
    m_cam = constant_velocity(m_imu.dt_s, float(m_cam.Q[1, 1]), m_cam.R)  # one dt for both
    z = np.stack([z_imu[:T], z_cam[:T]], axis=-2)  # (T, 2 models, 3)
    seen = np.flatnonzero(np.any(np.all(np.isfinite(z), axis=-1), axis=-1))
    imm = IMM(m_imu, m_cam)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if seen.size == 0:
            with pytest.raises(InputError):  # nothing observed: a clear error, not NaN
                imm.filter(z)
            return
        _, res = imm.filter(z)
    k0 = seen[0]
    assert np.all(np.isfinite(res.mean[k0:]))
    _assert_psd(res.cov[k0:], "IMM combined")
    _assert_psd(res.model_cov[k0:], "IMM per model")
    mu = res.mu[k0:]
    assert np.all(mu >= 0) and np.allclose(mu.sum(axis=-1), 1.0)


@_SETTINGS
@given(
    N=st.integers(7, 80),
    dt=st.sampled_from([0.01, 1 / 30, 0.1]),
    q=st.floats(1e-3, 50.0),
    r=st.floats(1e-6, 1e-1),
    missing=st.floats(0.0, 0.6),
    seed=st.integers(0, 2**31 - 1),
)
def test_ufir_cv_covariance_closed_form_matches_iterative(N, dt, q, r, missing, seed):
    """Any horizon, model and missing pattern: the O(1) closed-form covariance of the
    constant-velocity UFIR equals the literal iterative form (the oracle) to rounding."""
    from kinefuse.filters import UFIRFilter
    from kinefuse.models import constant_velocity

    rng = np.random.default_rng(seed)
    T = 2 * N + 40
    z = np.cumsum(rng.normal(scale=0.01, size=(1, T, 3)), axis=1)
    z[:, rng.random(T) < missing] = np.nan
    z[:, 0] = 0.0
    f = UFIRFilter(constant_velocity(dt, q=q, r=r), horizon=N)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # KF fallback inside long gaps
        _, fast = f.filter(z)
        _, ref = f._run(z, f.init((1,)), fast=False)
    np.testing.assert_array_equal(fast.fir_ready, ref.fir_ready)
    np.testing.assert_allclose(
        fast.cov, ref.cov, rtol=1e-9, atol=1e-13 * np.nanmax(np.abs(ref.cov))
    )


@_SETTINGS
@given(
    shape=st.lists(st.integers(0, 6), min_size=1, max_size=3),
    fill=st.sampled_from([np.nan, np.inf, -np.inf]),
    frac=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**31 - 1),
)
def test_finite_rows_equals_numpy_reduction(shape, fill, frac, seed):
    """Any shape (an empty last axis too) and any non-finite value: ``finite_rows`` is numpy's
    ``np.all(np.isfinite(a), axis=-1)`` (the oracle)."""
    from kinefuse._validation import finite_rows

    rng = np.random.default_rng(seed)
    a = rng.normal(size=shape)
    a[rng.random(shape) < frac] = fill
    np.testing.assert_array_equal(finite_rows(a), np.all(np.isfinite(a), axis=-1))
