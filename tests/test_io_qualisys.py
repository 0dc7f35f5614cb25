"""Qualisys QTM TSV export (io.qualisys): the reader recipe of CONTRIBUTING.md done once.

The files are written here in QTM's TSV layout (header keys, MARKER_NAMES, TRAJECTORY_TYPES,
tab-separated millimetres; the newer Frame/Time column header), with values of our own.
"""

from __future__ import annotations

import numpy as np
import pytest

import kinefuse.io as kio
from kinefuse.exceptions import FormatError

_HEADER = (
    "NO_OF_FRAMES\t4\n"
    "NO_OF_CAMERAS\t13\n"
    "NO_OF_MARKERS\t3\n"
    "FREQUENCY\t120\n"
    "NO_OF_ANALOG\t0\n"
    "ANALOG_FREQUENCY\t0\n"
    "DESCRIPTION\t--\n"
    "TIME_STAMP\t2024-04-15, 10:39:38.777\t406646.66137317\n"
    "DATA_INCLUDED\t3D\n"
    "MARKER_NAMES\tWrist_L\tHip_L\tToe_Marker\n"
    "TRAJECTORY_TYPES\tMeasured\tMeasured\tMeasured\n"
)
_ROWS = [
    [-470.5, 190.0, 610.25, -677.0, 164.5, 615.5, -138.5, 187.25, 53.5],
    [-471.0, 190.5, 610.0, -677.0, 164.5, 615.25, 0.0, 0.0, 0.0],
    [-471.5, 191.0, 609.75, -677.25, 164.75, 615.0, -138.25, 187.0, 53.25],
    [-472.0, 191.5, 609.5, -677.5, 164.75, 614.75, -138.0, 187.0, 53.0],
]


def _write(tmp_path, *, timed=False, name="walk.tsv"):
    lines = []
    if timed:
        cols = [f"{m} {a}" for m in ("Wrist_L", "Hip_L", "Toe_Marker") for a in "XYZ"]
        lines.append("\t".join(["Frame", "Time", *cols]))
    for k, r in enumerate(_ROWS):
        vals = [f"{v:.3f}" for v in r]
        lines.append("\t".join(([str(k + 1), f"{k / 120:.5f}"] if timed else []) + vals))
    p = tmp_path / name
    p.write_text(_HEADER + "\n".join(lines) + "\n")
    return p


@pytest.mark.parametrize("timed", [False, True])
def test_read_qualisys_tsv(tmp_path, timed):
    p = _write(tmp_path, timed=timed)
    assert kio.detect_format(p) == "qualisys_tsv"
    rec = kio.load(p)
    ref = rec.reference
    assert ref.joints == ("wrist_l", "hip_l", "Toe_Marker")
    np.testing.assert_allclose(ref.position_m[0, 0], [-0.4705, 0.19, 0.61025], atol=1e-12)
    np.testing.assert_allclose(
        ref.t_s, np.round(np.arange(4) / 120, 5 if timed else 17), atol=1e-12
    )
    assert ref.available[1].tolist() == [True, True, False]  # 0 0 0 = not tracked
    assert ref.frame == "qualisys_lab" and rec.metadata["rate_hz"] == 120.0
    assert rec.metadata["header"]["TIME_STAMP"] == ["2024-04-15, 10:39:38.777", "406646.66137317"]
    assert rec.metadata["n_zero_samples"] == 1
    assert rec.metadata["time_source"] == ("Time column" if timed else "frame / FREQUENCY")


def test_qualisys_errors(tmp_path):
    p = tmp_path / "six_d.tsv"
    p.write_text(_HEADER.replace("DATA_INCLUDED\t3D", "DATA_INCLUDED\t6D") + "0\t0\t0\n")
    with pytest.raises(FormatError, match="DATA_INCLUDED 3D"):
        kio.read_qualisys_tsv(p)
    p = tmp_path / "short.tsv"
    p.write_text(_HEADER + "1.0\t2.0\n")
    with pytest.raises(FormatError, match=r"line 12: expected 9 fields per row, found 2"):
        kio.read_qualisys_tsv(p)
    p = tmp_path / "names.tsv"
    p.write_text(_HEADER.replace("NO_OF_MARKERS\t3", "NO_OF_MARKERS\t4") + "0\t" * 8 + "0\n")
    with pytest.raises(FormatError, match="expected 4 MARKER_NAMES"):
        kio.read_qualisys_tsv(p)
    p = tmp_path / "inf.tsv"
    p.write_text(_HEADER + "\t".join(["1.0"] * 8 + ["inf"]) + "\n")
    with pytest.raises(FormatError, match="line 12: expected finite numbers"):
        kio.read_qualisys_tsv(p)
