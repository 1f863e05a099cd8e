"""Malformed input files (meshes, plans, scenes) raise the toolkit's own errors, naming the file, the
line or key where it is known, and what was expected: before any computation, never a parser's
bare message (``could not convert string to float``) or a ``SystemExit`` from a third-party reader."""

from __future__ import annotations

import numpy as np
import pytest

from toolkit.common.errors import ToolkitError
from toolkit.common.meshes import io
from toolkit.common.meshes.mesh import Mesh, MeshError
from toolkit.impact.scene import Scene, SceneError
from toolkit.static.plan import PlanError, SurgicalPlan

TET = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 10.0]])
INP = """*HEADING
written by hand
*NODE
1, 0.0, 0.0, 0.0
2, 10.0, 0.0, 0.0
3, 0.0, 10.0, 0.0
4, 0.0, 0.0, 10.0
*ELEMENT, TYPE=C3D4
1, 1, 2, 3, 4
*NSET, NSET=fixed
1, 2
"""


def _raises(cls, path, *fragments, read=io.read):
    """``read(path)`` raises ``cls`` (a ToolkitError and a ValueError) whose message holds the file
    name and every fragment."""
    with pytest.raises(cls) as info:
        read(path)
    assert isinstance(info.value, ToolkitError) and isinstance(info.value, ValueError)
    message = str(info.value)
    for fragment in (path.name, *fragments):
        assert fragment in message, f"{fragment!r} not in {message!r}"
    return message


# ------------------------------------------------------------------ meshes
@pytest.fixture
def inp(tmp_path):
    def make(text: str | bytes, name: str = "face.inp"):
        path = tmp_path / name
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
        return path
    return make


def test_valid_inp_reads(inp):
    mesh = io.read(inp(INP))
    assert mesh.volume_type == "tet4" and mesh.node_sets["fixed"].tolist() == [0, 1]


def test_inp_with_a_word_for_a_number_names_the_line(inp):
    """A coordinate that is not a number: the line and the text are named."""
    _raises(MeshError, inp(INP.replace("2, 10.0, 0.0, 0.0", "2, a, 0.0, 0.0")), "line 5", "'a' is not a number")


def test_inp_of_random_bytes_says_it_is_not_text(inp):
    _raises(MeshError, inp(b"\x81\xa7\x00\xff" * 50), "line 1", "is not text", "Abaqus .inp")


@pytest.mark.parametrize("name, expected", [("face.inp", "Abaqus .inp"), ("face.vtu", "VTU"), ("face.xdmf", "XDMF")])
def test_empty_mesh_file_says_empty(inp, name, expected):
    _raises(MeshError, inp(b"", name), "is empty (0 bytes)", expected)


def test_unknown_mesh_extension_names_the_expected_ones(inp):
    _raises(MeshError, inp(INP, "face.stl"), "'.stl'", "'.inp', '.vtu', '.xdmf'")


def test_mesh_without_volume_cells_is_refused(tmp_path):
    """A surface mesh (triangles only) is not a face model: the blocks found and the volume types
    expected are named; ``require_volume=False`` reads it."""
    path = io.write(tmp_path / "skin.vtu", Mesh(TET, {"tri3": [[0, 1, 2]]}))
    _raises(MeshError, path, "no volume cells", "tri3: 1", "tet4")
    assert io.read(path, require_volume=False).n_cells == 1


def test_inp_without_elements_is_refused(inp):
    _raises(MeshError, inp(INP.split("*ELEMENT")[0]), "no volume cells", "none")


@pytest.mark.parametrize("suffix", [".vtu", ".xdmf"])
def test_truncated_or_garbled_xml_mesh_names_the_parse_error(tmp_path, suffix):
    """Half a VTU (an interrupted copy) or bytes that are not XML: the XML parser's line is kept
    and the message asks whether the file is truncated; meshio's own ``read`` would exit."""
    good = io.write(tmp_path / f"good{suffix}", Mesh(TET, {"tet4": [[0, 1, 2, 3]]}))
    half = tmp_path / f"half{suffix}"
    half.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    _raises(MeshError, half, "cannot be read", "line ", "truncated")
    noise = tmp_path / f"noise{suffix}"
    noise.write_bytes(np.random.default_rng(0).bytes(400))
    _raises(MeshError, noise, "cannot be read", "truncated")


def test_inp_with_an_unknown_element_type_names_the_line(inp):
    _raises(MeshError, inp(INP.replace("C3D4", "C3D99")), "line 8", "C3D99")


def test_inp_element_with_too_few_nodes_is_refused(inp):
    _raises(MeshError, inp(INP.replace("1, 1, 2, 3, 4", "1, 1, 2, 3")), "does not match element type")


def test_inp_element_naming_a_missing_node_names_the_line(inp):
    _raises(MeshError, inp(INP.replace("1, 1, 2, 3, 4", "1, 1, 2, 3, 9")), "line 9", "node or element 9")


def test_inp_node_set_naming_a_missing_node_names_the_line(inp):
    _raises(MeshError, inp(INP.replace("*NSET, NSET=fixed\n1, 2", "*NSET, NSET=fixed\n1, 22")), "line 11", "22")


def test_inp_node_id_defined_twice_is_refused(inp):
    """meshio keeps the last of two nodes with one id and renumbers the rest; the reader refuses."""
    _raises(MeshError, inp(INP.replace("3, 0.0, 10.0", "2, 0.0, 10.0")), "line 6", "node id 2 is defined twice",
            "line 5")


def test_inp_node_with_two_coordinates_names_the_line(inp):
    _raises(MeshError, inp(INP.replace("2, 10.0, 0.0, 0.0", "2, 10.0, 0.0")), "line 5", "holds 2 coordinates",
            "line 4 holds 3")


def test_inp_comments_inside_the_node_block_are_read(inp):
    """``**`` comment lines do not end a keyword block: the checks still see every node line."""
    text = INP.replace("*NODE\n", "*NODE\n** nodes in mm\n")
    assert io.read(inp(text)).n_points == 4
    _raises(MeshError, inp(text.replace("3, 0.0, 10.0", "2, 0.0, 10.0")), "node id 2 is defined twice")


def test_folder_for_a_mesh_file_is_refused(tmp_path):
    folder = tmp_path / "face.vtu"
    folder.mkdir()
    _raises(MeshError, folder, "is a folder")


def test_xdmf_without_its_h5_names_the_missing_file(tmp_path):
    """An XDMF copied without its HDF5 data file: the message names the .h5 it needs."""
    io.write(tmp_path / "face.xdmf", Mesh(TET, {"tet4": [[0, 1, 2, 3]]}))
    (tmp_path / "face.h5").unlink()
    _raises(MeshError, tmp_path / "face.xdmf", "face.h5", "beside the .xdmf")


def test_inp_with_nan_coordinates_is_refused(inp):
    _raises(MeshError, inp(INP.replace("2, 10.0, 0.0", "2, nan, 0.0")), "NaN/inf", "[1]")


def test_metres_mesh_names_the_python_and_the_command_line_remedy(tmp_path):
    path = io.write(tmp_path / "face_m.vtu", Mesh(TET * 1e-3, {"tet4": [[0, 1, 2, 3]]}))
    _raises(io.UnitsError, path, "units='m'", "--units m")


# ------------------------------------------------------------------ plans
PLAN_CASES = {
    "syntax": ("[lefort]\ntranslation_mm = [1, 2,\n\n[distal]\n", ["not valid TOML", "line 4"]),
    "unknown key": ("[lefort]\ntranslaton_mm = [1, 2, 3]\n", ["'lefort'", "'translaton_mm'",
                                                             "did you mean 'translation_mm'?"]),
    "unknown segment": ("[lefrot]\ntranslation_mm = [1, 2, 3]\n", ["'lefrot'", "did you mean 'lefort'?"]),
    "misspelt force": ("froce = true\n[lefort]\ntranslation_mm = [1, 2, 3]\n", ["did you mean 'force'?"]),
    "word for a vector": ("[lefort]\ntranslation_mm = 'abc'\n", ["'lefort'", "translation_mm = 'abc'",
                                                                "expected 3 numbers"]),
    "word in a vector": ("[lefort]\ntranslation_mm = [1, 'a', 3]\n", ["translation_mm", "expected 3 numbers"]),
    "two numbers": ("[lefort]\ntranslation_mm = [1, 2]\n", ["translation_mm", "expected (3,)"]),
    "missing pivot": ("[lefort]\nrotation_vector_deg = [3, 0, 0]\n", ["'lefort'", "pivot_mm is missing"]),
    "empty": ("", ["is empty"]),
    "number for a table": ("lefort = 3\n", ["'lefort'", "expected a table"]),
    "force as a word": ("force = 'yes'\n[lefort]\ntranslation_mm = [1, 2, 3]\n", ["force = 'yes'",
                                                                                 "expected true or false"]),
    "bytes": (b"\x00\xff\xfe\x81abc", ["line 1", "is not text"]),
}


@pytest.mark.parametrize("case", sorted(PLAN_CASES))
def test_bad_plan_files_name_file_key_and_expectation(tmp_path, case):
    text, fragments = PLAN_CASES[case]
    path = tmp_path / "plan.toml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    _raises(PlanError, path, *fragments, read=SurgicalPlan.read)


@pytest.mark.parametrize("text, fragments", [
    ('{"lefort": {"translation_mm": [1, 2, 3],}}', ["line 1, column 41", "not valid JSON"]),
    ("[1, 2]", ["JSON list", "expected an object"]),
])
def test_bad_json_plans_name_the_line(tmp_path, text, fragments):
    path = tmp_path / "plan.json"
    path.write_text(text)
    _raises(PlanError, path, *fragments, read=SurgicalPlan.read)


# ------------------------------------------------------------------ scenes
SCENE_CASES = {
    "typo": ("[ball]\nvelocty = 30.0\n", ["[ball] has no key 'velocty'", "expected one of", "'velocity'",
                                          "did you mean 'velocity'?"]),
    "word for a number": ("[ball]\nvelocity = 'fast'\n", ["[ball] velocity = 'fast': expected a number (mm/s)"]),
    "top-level typo": ("durration = 0.3\n", ["has no key 'durration'", "did you mean 'duration'?"]),
    "string modulus": ("[face.material]\nE = '0.015'\nnu = 0.49\ndensity = 1e-9\n",
                       ["[face.material] E = '0.015': expected a number (MPa)"]),
    "missing material keys": ("[face.material]\nE = 0.015\n", ["[face.material] lacks ['nu', 'density']"]),
    "short direction": ("[ball]\ndirection = [0, -1]\n", ["[ball] direction = [0, -1]: expected 3 numbers"]),
    "word for a flag": ("[ball]\nrigid = 'yes'\n", ["[ball] rigid = 'yes': expected true or false"]),
    "fractional order": ("[fidelity]\norder = 1.5\n", ["[fidelity] order = 1.5: expected an integer"]),
    "number for a table": ("ball = 3\n", ["ball = 3: expected a table"]),
    "flat yield table": ("[face.material]\nE = 0.015\nnu = 0.49\ndensity = 1e-9\nyield_table = [1, 2]\n",
                         ["yield_table = [1, 2]", "pairs"]),
    "syntax": ("[ball]\nvelocity = [1, 2\n", ["not valid TOML"]),
    "bytes": (b"\xff\xfe\x00", ["line 1", "is not text"]),
    # values of the right type outside their range
    "zero radius": ("[ball]\nradius = 0.0\n", ["ball radius 0.0 mm must be positive"]),
    "negative gap": ("[ball]\ngap = -5.0\n", ["ball gap -5.0 mm must be >= 0"]),
    "driven fraction": ("[ball]\ndriven_fraction = 2.0\n", ["driven_fraction 2.0 must be in [0, 1)"]),
    "ball resolution": ("[ball]\nresolution = 'medium'\n", ["ball resolution 'medium'", "'coarse', 'paper'"]),
    "face resolution": ("[face]\nresolution = 'medium'\n", ["face resolution 'medium'", "'coarse', 'paper'"]),
    "fixed fraction": ("[face]\nlower_fixed_fraction = 1.5\n", ["lower_fixed_fraction 1.5 must be in (0, 1)"]),
    "negative friction": ("[contact]\nfriction = -0.2\n", ["contact friction -0.2 must be >= 0"]),
    "zero dt fraction": ("[contact]\ndt_fraction = 0.0\n", ["dt_fraction 0.0 must be in (0, 1]"]),
    "negative dt": ("[fidelity]\ndt = -1e-4\n", ["dt must be a positive time step (s)", "-0.0001"]),
    "negative yield stress": ("[face.material]\nE = 0.015\nnu = 0.49\ndensity = 1e-9\n"
                              "yield_table = [[-1, 0], [0.02, 0.1]]\n", ["yield_table", "-1.0 MPa must be positive"]),
}


@pytest.mark.parametrize("case", sorted(SCENE_CASES))
def test_bad_scene_files_name_file_table_key_and_expectation(tmp_path, case):
    text, fragments = SCENE_CASES[case]
    path = tmp_path / "scene.toml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    _raises(SceneError, path, *fragments, read=Scene.read)


def test_missing_set_is_a_toolkit_error_and_a_key_error(inp):
    """A node set the caller needs and the file lacks: the message lists the sets it has, unquoted,
    and the error is caught as a ToolkitError, a ValueError or (for lookups) a KeyError."""
    from toolkit.common.meshes.mesh import MissingSetError

    with pytest.raises(MissingSetError) as info:
        io.read(inp(INP), require_node_sets=["skin"])
    assert isinstance(info.value, ToolkitError) and isinstance(info.value, KeyError)
    assert str(info.value).startswith("face.inp lacks the sets ['skin']; it has node sets ['fixed']")
    with pytest.raises(MissingSetError, match="^no node set 'skin'; the mesh has \\['fixed'\\]$"):
        io.read(inp(INP)).node_set("skin")
