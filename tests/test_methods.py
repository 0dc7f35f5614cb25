"""The method registry (kinefuse.methods): every list of methods in the package agrees with it,
and streaming a session whose method has no online form is refused (or substituted, warned)."""

from __future__ import annotations

import dataclasses
import warnings

import pytest

from kinefuse import methods
from kinefuse.exceptions import ConfigError
from kinefuse.session_file import CAMERA_METHODS, METHODS, MethodConfig, load_session
from kinefuse.streaming.config import (
    PROCESSORS,
    load_stream_config,
    online_processor,
    stream_config_from_session,
)


def test_registry_is_consistent():
    assert methods.names() == tuple(methods.REGISTRY) == METHODS
    assert CAMERA_METHODS == methods.names(needs="camera")
    for m in methods.REGISTRY.values():
        assert m.needs and set(m.needs) <= set(methods.INPUTS)
        assert m.forms and set(m.forms) <= set(methods.FORMS)
        assert ("online" in m.forms) == (m.online is not None)
        assert m.online is None or m.online in methods.PROCESSORS
        assert m.online_substitute is None or (
            m.online is None and m.online_substitute in methods.PROCESSORS
        )
        assert m.summary and "\n" not in m.summary and m.label
    assert methods.names(form="online") == ("paper-a", "elm-fir", "elm-kf")
    assert set(methods.BASELINES) <= set(methods.names())
    with pytest.raises(ConfigError, match="did you mean 'elm-fir'"):
        methods.get("elm-fri")
    # the paper's name points to its methods (difflib's nearest name would be 'paper-a')
    for name in ("paper-b", "Paper_B"):
        with pytest.raises(ConfigError, match="paper B's methods are 'elm-fir'.*'elm-kf'"):
            methods.get(name)
    assert methods.unknown_fix("imu") == "did you mean 'imu-only'?"
    with pytest.raises(ConfigError, match="expected form"):
        methods.names(form="live")
    lines = methods.help_lines()
    assert len(lines) == len(METHODS) and all(n in ln for n, ln in zip(METHODS, lines, strict=True))
    assert len(methods.help_lines(form="online")) == 3


def test_implementation_tables_match_the_registry():
    """The implementation tables stay where they are; here they are checked against it."""
    from kinefuse.apps.bench_engine import ENGINE_PROCESSORS, PIPELINE_METHODS
    from kinefuse.pipelines import METHODS as FUSION_METHODS
    from kinefuse.pipelines import UPPER_LIMB_METHODS
    from kinefuse.pipelines.labels import BASELINE_METHODS
    from kinefuse.pipelines.labels import PAPER_A_LABELS as _A_METHODS
    from kinefuse.pipelines.paper_b import PAPER_B_METHODS as PAPER_B_ONLINE

    # every registered method but paper A's filter runs through vision_assisted's table
    assert set(FUSION_METHODS) >= set(methods.names()) - {"paper-a"}
    builtin = {k for k, f in FUSION_METHODS.items() if f.__module__.startswith("kinefuse.")}
    assert builtin <= set(methods.names())
    assert set(UPPER_LIMB_METHODS) == set(methods.FILTERS)
    assert {k: methods.FILTERS[k] for k in _A_METHODS} == _A_METHODS
    assert set(PAPER_B_ONLINE) == {
        m for m in methods.names(form="online") if methods.get(m).paper == methods.PAPER_B
    }
    assert PROCESSORS == tuple(methods.PROCESSORS)
    assert set(ENGINE_PROCESSORS) <= set(PROCESSORS)
    assert set(PIPELINE_METHODS) <= set(methods.names())
    assert tuple(BASELINE_METHODS) == methods.BASELINES


@pytest.fixture
def session(tmp_path):
    for f in ("imu.csv", "camera.csv"):
        (tmp_path / f).write_text("x\n")
    p = tmp_path / "s.toml"
    p.write_text(
        '[session]\nname = "live"\n[imu]\nformat = "imu_csv"\npath = "imu.csv"\n'
        '[imu.segments]\nforearm_r = "IMU 2"\n[skeleton]\nbody_height_m = 1.75\n'
        '[camera]\nformat = "joint_csv"\npath = "camera.csv"\n[calibration]\nmethod = "none"\n'
        '[method]\nname = "elm-fir"\n'
    )
    return load_session(p)


def test_streaming_a_session_refuses_or_warns_about_calibration(session):
    """The online engine calibrates nothing: an asked-for calibration, axes or root is refused
    (naming each), an implicit one (kinefuse run's default) is a warning kept in the notes."""
    asked = dataclasses.replace(
        session,
        calibration=dataclasses.replace(session.calibration, settings={"method": "static"}),
        skeleton=dataclasses.replace(session.skeleton, root="fixed", axes={"forearm_r": "+e1"}),
    )
    with pytest.raises(
        ConfigError,
        match="calibration 'static'; declared segment axes \\(forearm_r\\); root 'fixed'",
    ):
        stream_config_from_session(asked)
    implicit = dataclasses.replace(
        session, calibration=dataclasses.replace(session.calibration, settings={})
    )
    with pytest.warns(UserWarning, match="calibrates this session \\('vision', the default\\)"):
        sc = stream_config_from_session(implicit)
    assert len(sc.notes) == 1 and 'method = "none"' in sc.notes[0]


@pytest.mark.parametrize("method", methods.names())
def test_streaming_a_session_follows_the_registry(session, method):
    cfg = dataclasses.replace(session, method=MethodConfig(method))
    spec = methods.get(method)
    if spec.online is not None:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            sc = stream_config_from_session(cfg)
        assert sc.processor == spec.online and sc.notes == ()
    elif spec.online_substitute is not None:
        with pytest.warns(UserWarning, match=f"{method!r} has no online form"):
            sc = stream_config_from_session(cfg)
        assert sc.processor == spec.online_substitute
        assert len(sc.notes) == 1 and "instead" in sc.notes[0]
    else:  # e.g. kinefuse, camera-only: never silently the KF-fusion processor
        with pytest.raises(ConfigError, match=f"s.toml: \\[method\\] name = '{method}' has no "):
            stream_config_from_session(cfg)


def test_imu_only_streams_paper_a_with_a_warning():
    with pytest.warns(UserWarning, match="runs the 'paper-a' processor instead"):
        assert online_processor("imu-only")[0] == "paper-a"


def test_stream_file_method_selects_its_online_form(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('[stream]\nname_prefix = "x"\n[method]\nname = "elm-kf"\n')
    assert load_stream_config(p).processor == "elm-kf"
    p.write_text('[stream]\nname_prefix = "x"\n[method]\nname = "kinefuse"\n')
    with pytest.raises(ConfigError, match="'kinefuse' has no online form"):
        load_stream_config(p)
    # an explicit processor is the user's choice
    p.write_text(
        '[stream]\nname_prefix = "x"\nprocessor = "kf-fusion"\n[method]\nname = "kinefuse"\n'
    )
    assert load_stream_config(p).processor == "kf-fusion"
    p.write_text('[stream]\nname_prefix = "x"\nnotes = ["a"]\n')
    with pytest.raises(ConfigError, match="unknown key"):
        load_stream_config(p)


def test_docs_streaming_session_example_loads(tmp_path):
    """docs/streaming.md's live.toml is a valid stream session: paper B online, prefix kinefuse;
    its table of [stream] keys names every key the loader accepts."""
    from pathlib import Path

    from kinefuse.streaming.config import _STREAM_KEYS

    doc = (Path(__file__).parents[1] / "docs" / "streaming.md").read_text(encoding="utf-8")
    block = doc.split("```toml\n", 1)[1].split("```", 1)[0]
    p = tmp_path / "live.toml"
    p.write_text(block, encoding="utf-8")
    cfg = load_stream_config(p)
    assert cfg.processor == "elm-fir" and cfg.name_prefix == "kinefuse" and cfg.notes == ()
    documented = {k.strip("` ") for row in doc.split("## Stream sessions")[1].split("\n| ")[1:]
                  for k in row.split(" | ")[0].split(",")}  # fmt: skip
    assert set(_STREAM_KEYS) <= documented, set(_STREAM_KEYS) - documented
