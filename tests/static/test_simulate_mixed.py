"""The static output path on a mixed face mesh (hexahedra and wedges, as hex-dominant meshers
give), from the command line: every output is written and reads back. Units mm."""

import json

import meshio
import numpy as np

from toolkit.cli import main
from toolkit.common.meshes import io
from toolkit.common.phantoms.face_variants import remeshed
from toolkit.common.phantoms.phantom import face_hex
from toolkit.static.plan import default_plan


def test_static_simulate_writes_every_output_of_a_mixed_mesh(tmp_path):
    """``toolkit static simulate --mesh mixed.inp`` on the coarse phantom with 40% of its
    columns split into wedges: result.vtu, postop.vtu, summary.json and increments.xdmf (one
    XDMF Mixed topology) are written; the series has the mesh's two blocks and 4 frames whose
    last equals result.vtu's displacement, and meshio reads it as ParaView would."""
    phantom = remeshed(face_hex("coarse"), "mixed")
    assert list(phantom.mesh.cells) == ["hex8", "wedge6"]
    io.write(tmp_path / "mixed.inp", phantom.mesh)
    default_plan(phantom).write(tmp_path / "plan.toml")
    out = tmp_path / "out"
    assert main(["static", "simulate", "--mesh", str(tmp_path / "mixed.inp"), "--plan", str(tmp_path / "plan.toml"),
                 "--out", str(out), "--no-preview"]) == 0
    result = io.read(out / "result.vtu")
    assert set(result.cells) == {"hex8", "wedge6"}
    series = io.read_time_series(out / "increments.xdmf")
    assert {k: v.shape for k, v in series.mesh.cells.items()} == {k: v.shape for k, v in phantom.mesh.cells.items()}
    assert series.times.size == 4
    u = series.point_data["displacement"]
    assert np.allclose(u[-1], result.point_data["displacement"], atol=1e-9) and np.abs(u[0]).max() == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["increments"] == 3 and summary["elements"] == phantom.mesh.n_cells
    with meshio.xdmf.TimeSeriesReader(out / "increments.xdmf") as reader:
        _, cells = reader.read_points_cells()
        _, pdata, _ = reader.read_data(3)
    assert [c.type for c in cells] == ["hexahedron", "wedge"]
    assert np.allclose(pdata["displacement"], u[-1])
