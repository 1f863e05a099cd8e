"""The command line a new user meets first."""

import json
import subprocess
import sys

import pytest

from toolkit.cli import main
from toolkit.common import io


def test_demo_writes_validated_phantoms(tmp_path):
    """``toolkit demo`` writes the three coarse phantoms as .inp and .vtu with all sets,
    PNG previews and a summary, and runs the static workflow on the coarse face."""
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
    assert summary["static"]["increments"] == 3 and summary["static"]["max_penetration_mm"] <= 1e-9
    assert (out / "static" / "result.vtu").exists() and (out / "static" / "preview.png").exists()
    assert summary["impact"]["energy_error"] < 0.02 and (out / "impact" / "face.xdmf").exists()


@pytest.mark.parametrize("argv", [["--help"], ["demo", "--help"], ["phantom", "--help"], ["static", "--help"],
                                  ["static", "simulate", "--help"]])
def test_every_command_has_help(argv):
    done = subprocess.run([sys.executable, "-m", "toolkit.cli", *argv], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "usage: toolkit" in done.stdout


def test_phantom_command_and_clear_errors(tmp_path, capsys):
    assert main(["phantom", "face-tet4", "--seed", "3", "--out", str(tmp_path / "f.vtu")]) == 0
    assert io.read(tmp_path / "f.vtu").volume_type == "tet4"
    assert main(["phantom", "face-hex", "--mouth-open", "40", "--out", str(tmp_path / "g.vtu")]) == 2
    assert "mouth_open = 40.0 mm is outside the validated range [0.0, 12.0]" in capsys.readouterr().err


def test_static_simulate_writes_the_documented_outputs(tmp_path):
    """``toolkit static simulate`` with no arguments but --out runs the packaged plan on the
    coarse phantom and writes result.vtu (displacement, boundary_type), the increments as
    XDMF, summary.json with the documented keys, and preview.png."""
    out = tmp_path / "static"
    assert main(["static", "simulate", "--out", str(out)]) == 0
    result = io.read(out / "result.vtu")
    assert result.point_data["displacement"].shape == (result.n_points, 3)
    assert set(result.point_data["boundary_type"].tolist()) <= {0, 1, 2, 3, 4}
    series = io.read_time_series(out / "increments.xdmf")
    assert series.point_data["displacement"].shape == (4, result.n_points, 3)
    summary = json.loads((out / "summary.json").read_text())
    for key in ("nodes", "elements", "increments", "wall_time_s", "max_displacement_mm", "min_scaled_jacobian",
                "max_penetration_mm"):
        assert key in summary, key
    assert summary["increments"] == 3 and summary["min_scaled_jacobian"] > 0
    assert (out / "preview.png").stat().st_size > 0


def test_static_simulate_from_a_mesh_file_and_plan(tmp_path):
    """A face read from Abaqus with a plan file (pivots given) runs the same workflow."""
    from toolkit.common import face_hex
    from toolkit.static import default_plan

    ph = face_hex("coarse")
    io.write(tmp_path / "face.inp", ph.mesh)
    default_plan(ph).write(tmp_path / "plan.toml")
    out = tmp_path / "run"
    assert main(["static", "simulate", "--mesh", str(tmp_path / "face.inp"), "--plan", str(tmp_path / "plan.toml"),
                 "--sliding", "mucosa", "--no-preview", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["nodes"] == ph.mesh.n_points and summary["min_scaled_jacobian"] > 0


def test_static_dataset_on_a_local_dask_cluster(tmp_path, capsys):
    """`--dask local` runs the simulations on a LocalCluster and fills the same database index
    as in-process generation."""
    pytest.importorskip("distributed")
    from toolkit.static.dataset import read_samples

    common = ["static", "dataset", "--resolution", "coarse", "--plans", "2"]
    assert main([*common, "--workers", "1", "--dask", "local", "--out", str(tmp_path / "dask.h5")]) == 0
    assert main([*common, "--workers", "0", "--out", str(tmp_path / "local.h5")]) == 0
    a, b = read_samples(tmp_path / "dask.h5"), read_samples(tmp_path / "local.h5")
    assert len(a) == 6 and (a.status == "ok").all()
    assert a[["key", "increment", "lefort_tx", "distal_ry"]].equals(b[["key", "increment", "lefort_tx", "distal_ry"]])
