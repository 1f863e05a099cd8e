"""The command line a new user meets first."""

import json
import subprocess
import sys

import pytest

from toolkit.cli import main
from toolkit.common import io


def test_demo_writes_validated_phantoms(tmp_path):
    """``toolkit demo`` writes the three coarse phantoms as .inp and .vtu with all sets,
    PNG previews and a summary."""
    out = tmp_path / "demo-output"
    assert main(["demo", "--out", str(out)]) == 0
    for name in ("face_hex", "face_tet10", "ball"):
        for suffix in (".inp", ".vtu", ".png"):
            assert (out / f"{name}{suffix}").stat().st_size > 0, name + suffix
    face = io.read(out / "face_hex.inp", require_node_sets=["fixed", "maxilla", "mandible", "mucosa_sliding",
                                                            "lip_sliding", "skin"], require_element_sets=["lip_muscle"])
    face.check()
    assert io.read(out / "face_tet10.vtu").volume_type == "tet10"
    summary = json.loads((out / "summary.json").read_text())
    assert {r["mesh"] for r in summary["meshes"]} == {"face_hex", "face_tet10", "ball"}
    assert all(r["min_scaled_jacobian"] > 0 for r in summary["meshes"])


@pytest.mark.parametrize("argv", [["--help"], ["demo", "--help"], ["phantom", "--help"]])
def test_every_command_has_help(argv):
    done = subprocess.run([sys.executable, "-m", "toolkit.cli", *argv], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "usage: toolkit" in done.stdout


def test_phantom_command_and_clear_errors(tmp_path, capsys):
    assert main(["phantom", "face-tet4", "--seed", "3", "--out", str(tmp_path / "f.vtu")]) == 0
    assert io.read(tmp_path / "f.vtu").volume_type == "tet4"
    assert main(["phantom", "face-hex", "--mouth-open", "40", "--out", str(tmp_path / "g.vtu")]) == 2
    assert "mouth_open = 40.0 mm is outside the validated range [0.0, 12.0]" in capsys.readouterr().err
