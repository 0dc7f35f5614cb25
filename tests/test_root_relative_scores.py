"""A root-relative IMU-only output in the reference's world frame is scored against the
reference made relative to its own root joints (evaluation only: no alignment, no other use)."""

from dataclasses import replace

import numpy as np
import pytest

import kinefuse.io as kio
from kinefuse.pipelines.run.process import process_recording


@pytest.fixture(scope="module")
def neura(shared_data):
    return kio.load(shared_data / "neura_sparse_sample")


def _run(rec):
    params = {"calibration": "functional", "root": "pelvis"}
    return process_recording(rec, "imu-only", params, body_height_m=1.75)


def test_pelvis_rooted_output_is_scored_against_the_reference_minus_its_mid_hip(neura):
    out = _run(neura)
    assert out.frame == f"{neura.reference.frame}, relative to the pelvis (mid-hip)"
    assert "scored relative to the reference's mid-hip" in out.tag
    ref = neura.reference
    t = out.t_s

    def at(j):  # the reference joint on the output timeline (closed form: linear interpolation)
        return np.stack([np.interp(t, ref.t_s, ref.position(j)[:, k]) for k in range(3)], -1)

    mid = (at("hip_l") + at("hip_r")) / 2
    for i, j in enumerate(out.joints):
        np.testing.assert_allclose(out.reference[:, i], at(j) - mid, atol=1e-12)
    ev = out.evaluation()
    assert ev is not None and np.all(np.isfinite(ev.errors[0]))
    assert tuple(ev.axes) == ("X", "Y", "Z")  # a Vicon frame: not east, north, up


def test_scores_do_not_move_with_the_reference_s_world_position(neura):
    """Translating the whole reference (a lab origin elsewhere) changes no score: nothing but
    the reference's own root joints makes it relative; moving only its hips does."""
    base = _run(neura).evaluation()
    ref = neura.reference
    moved = replace(neura, reference=replace(ref, position_m=ref.position_m + [3.0, -2.0, 0.5]))
    again = _run(moved).evaluation()
    np.testing.assert_allclose(again.errors, base.errors, rtol=0, atol=1e-9)
    hips = [ref.joints.index(j) for j in ("hip_l", "hip_r")]
    p = ref.position_m.copy()
    p[:, hips] += [0.0, 0.0, 0.05]  # the reference's hips 5 cm up: its knees 5 cm lower
    shifted = _run(replace(neura, reference=replace(ref, position_m=p))).evaluation()
    assert not np.allclose(shifted.errors, base.errors)


def test_rigid_alignment_of_a_root_relative_output_aligns_to_the_relative_reference(neura):
    """align = 'rigid' on a pelvis-rooted output: the moving origin cannot be mapped onto world
    positions, so the output is aligned to the reference made relative to its mid-hip (before:
    aligned to the world positions, about 1.4 m off). Oracle: the Kabsch fit of the output
    onto that relative reference leaves the residual of the unaligned relative scores or less."""
    plain = _run(neura)
    params = {"calibration": "functional", "root": "pelvis", "align_to_reference": "rigid"}
    out = process_recording(neura, "imu-only", params, body_height_m=1.75)
    assert "scored relative to the reference's mid-hip" in out.tag
    assert "aligned to reference" in out.tag
    np.testing.assert_allclose(out.reference, plain.reference, atol=1e-12)
    rms = lambda a, b: np.sqrt(np.nanmean(np.sum((a - b) ** 2, axis=-1)))  # noqa: E731
    assert rms(out.position, out.reference) <= rms(plain.position, plain.reference) + 1e-12
    assert rms(out.position, out.reference) < 0.1  # metres off when aligned to world positions


def test_rigid_alignment_is_refused_when_the_reference_cannot_be_made_relative(neura):
    """A pelvis-rooted output and a reference without hip joints: not scored, and the warning
    says why a rigid alignment cannot help (no silent metres-off scores)."""
    ref = neura.reference
    keep = [j for j in ref.joints if not j.startswith("hip_")]
    rec = replace(neura, reference=ref.subset(keep))
    params = {"calibration": "functional", "root": "pelvis", "align_to_reference": "rigid"}
    out = process_recording(rec, "imu-only", params, body_height_m=1.75)
    assert out.reference is None and out.evaluation() is None
    assert any(
        "a rigid alignment cannot map an output whose origin moves" in w for w in out.warnings
    )
