"""docs/streaming.md shows the LSL configuration kinefuse ships, with its sections, and a
command that writes a machine-local one; a key in the wrong section is named as such."""

from __future__ import annotations

import re
import subprocess
import sys
from importlib.resources import files

from conftest import REPO_ROOT
from kinefuse.streaming.config import check_lsl_config

DOC = REPO_ROOT / "docs" / "streaming.md"


def test_streaming_docs_show_the_shipped_lsl_config_in_full():
    shipped = files("kinefuse.streaming").joinpath("lslapi.cfg").read_text("utf-8")
    blocks = re.findall(r"```ini\n(.*?)```", DOC.read_text(encoding="utf-8"), re.S)
    assert [b.strip() for b in blocks] == [shipped.strip()]
    for section in ("[ports]", "[multicast]", "[lab]", "[log]"):
        assert f"\n{section}\n" in blocks[0], section


def test_streaming_docs_command_writes_a_machine_local_config(tmp_path):
    text = DOC.read_text(encoding="utf-8")
    (command,) = re.findall(r'^python -c "(.*)" > lsl_api\.cfg$', text, re.M)
    out = subprocess.run([sys.executable, "-c", command], capture_output=True, text=True,
                         check=True, timeout=60).stdout  # fmt: skip
    (tmp_path / "lsl_api.cfg").write_text(out, encoding="utf-8")
    info = check_lsl_config(tmp_path / "lsl_api.cfg")
    assert info["local"], info["problems"]


def test_lsl_config_key_in_the_wrong_section_is_named(tmp_path):
    cfg = tmp_path / "lab.cfg"
    cfg.write_text(
        "[ports]\nIPv6 = disable\n[lab]\nResolveScope = machine\nMachineAddresses = {127.0.0.1}\n",
        encoding="utf-8",
    )
    info = check_lsl_config(cfg)
    assert not info["local"]
    assert info["problems"] == [
        "[multicast] ResolveScope = machine expected, got None (it is under [lab])",
        "[multicast] MachineAddresses = {127.0.0.1} expected, got None (it is under [lab])",
    ]
