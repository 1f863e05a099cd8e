"""``load_case``: the face, plan and bony segments a static simulation takes, from the
phantom or from files, as the command line and the notebooks build them."""

import warnings

import meshio
import numpy as np
import pytest
from scipy.spatial import cKDTree

from toolkit.common.meshes.io import write
from toolkit.common.meshes.mesh import Mesh
from toolkit.common.phantoms.phantom import FacePhantom, FaceShape, face_hex
from toolkit.static import StaticCase, SurgicalPlan, default_plan, load_case, simulate


@pytest.fixture(scope="module")
def phantom():
    return face_hex("coarse")


@pytest.fixture
def files(phantom, tmp_path):
    """The phantom written as an Abaqus mesh, its Le Fort I and distal bone surfaces as STL, and
    the default plan (pivots included) as TOML."""
    write(tmp_path / "face.inp", phantom.mesh)
    bones = {}
    for name, stem in (("lefort", "maxilla"), ("distal", "mandible")):
        surface = phantom.segments[name].surface
        bones[name] = tmp_path / f"{stem}.stl"
        meshio.write(bones[name], meshio.Mesh(surface.points, [("triangle", surface.cells["tri3"])]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        default_plan(phantom).write(tmp_path / "plan.toml")
    return tmp_path / "face.inp", tmp_path / "plan.toml", bones


def test_phantom_with_the_default_plan(phantom):
    """Without arguments but a resolution: the phantom, the packaged plan on it and the phantom's
    own segments; simulating the case equals simulating those three by hand (same displacement)."""
    case = load_case(resolution="coarse")
    assert isinstance(case, StaticCase) and isinstance(case.subject, FacePhantom)
    assert case.mesh.n_points == phantom.mesh.n_points
    np.testing.assert_array_equal(case.mesh.points, phantom.mesh.points)
    assert case.plan.to_dict() == default_plan(phantom).to_dict() and not case.plan.force
    assert set(case.segments) == set(case.subject.segments)
    assert all(case.segments[k] is s for k, s in case.subject.segments.items())
    mine = case.simulate(increments=1, sliding="mucosa")
    by_hand = simulate(phantom, default_plan(phantom), 1, "linear", "mucosa", segments=dict(phantom.segments))
    np.testing.assert_array_equal(mine.displacement, by_hand.displacement)


def test_phantom_shape_and_force():
    """``shape`` draws the phantom of another subject; ``force`` marks the default plan or a
    given plan as accepting movements beyond twice the physiological range."""
    shape = FaceShape.sample(3)
    case = load_case(resolution="coarse", shape=shape, force=True)
    assert case.subject.shape == shape and case.plan.force
    again = load_case(resolution="coarse", plan=case.plan.scaled(0.5), force=True)
    assert again.plan.force and again.plan.to_dict()["lefort"] == case.plan.scaled(0.5).to_dict()["lefort"]


def test_phantom_with_a_plan_file(phantom, tmp_path):
    """A plan file read for the phantom: its motions, and the phantom's pivots."""
    plan = default_plan(phantom).scaled(0.5)
    plan.write(tmp_path / "half.toml")
    case = load_case(resolution="coarse", plan=tmp_path / "half.toml")
    assert case.plan.to_dict() == SurgicalPlan.read(tmp_path / "half.toml", phantom=phantom).to_dict()
    np.testing.assert_allclose(case.plan.motions["lefort"].translation, plan.motions["lefort"].translation)
    assert load_case(resolution="coarse", plan=str(tmp_path / "half.toml"), force=True).plan.force


def test_mesh_file_with_bone_files(phantom, files):
    """A face read from Abaqus with two bone surfaces from STL: the mesh is the subject, the
    files give the Le Fort I and distal surfaces (the phantom's points, mm), and every moving
    segment's pivot is the plan's."""
    mesh, plan, bones = files
    case = load_case(mesh, plan=plan, bones=bones)
    assert isinstance(case.subject, Mesh) and case.mesh is case.subject
    np.testing.assert_allclose(case.subject.points, phantom.mesh.points)
    assert {"lefort", "distal"} <= set(case.segments)
    for name in ("lefort", "distal"):  # STL keeps float32 coordinates and its own vertex order
        mine, theirs = case.segments[name].surface.points, phantom.segments[name].surface.points
        assert mine.shape == theirs.shape and cKDTree(theirs).query(mine)[0].max() < 1e-4
    for name, motion in case.plan.motions.items():
        np.testing.assert_allclose(case.segments[name].pivot, motion.pivot)


def test_mesh_file_without_bone_files(phantom, files):
    """Without ``bones`` the segments are rebuilt from the mesh's own bone-side faces."""
    mesh, plan, _ = files
    case = load_case(mesh, plan=plan)
    assert {"lefort", "distal"} <= set(case.segments)
    assert all(s.surface.n_cells > 0 for s in case.segments.values())


def test_mesh_needs_a_plan_and_no_shape(files):
    """Only the phantom has a default plan (its pivots); a shape applies to the phantom only."""
    mesh, plan, _ = files
    with pytest.raises(ValueError, match=r"face.inp' needs a plan \(with pivot_mm for every rotating segment\)"):
        load_case(mesh)
    with pytest.raises(ValueError, match="a shape applies to the phantom only"):
        load_case(mesh, plan=plan, shape=FaceShape())


def test_plan_remedies_name_the_command_line(files, tmp_path):
    """A mesh without a plan and a plan file that does not exist say so, naming --plan; a plan
    file beyond twice the physiological range is read with ``force`` applied (``--force``)."""
    mesh, _, _ = files
    with pytest.raises(ValueError, match=r"give plan= \(command line: --plan FILE\)"):
        load_case(mesh)
    with pytest.raises(FileNotFoundError, match=r"plan file '.*missing.toml' does not exist.*--plan"):
        load_case(resolution="coarse", plan=tmp_path / "missing.toml")
    big = tmp_path / "big.toml"
    big.write_text("force = false\n[lefort]\ntranslation_mm = [0.0, 14.0, 0.0]\n")
    with pytest.raises(ValueError, match=r"force=True \(command line: --force\)"):
        load_case(resolution="coarse", plan=big)
    with pytest.warns(UserWarning, match="accepted because force=True"):
        case = load_case(resolution="coarse", plan=big, force=True)
    assert case.plan.force and case.plan.motions["lefort"].translation_mm == pytest.approx(14.0)


def test_case_checks_its_fields(phantom):
    with pytest.raises(TypeError, match="subject is a str; expected a FacePhantom or a Mesh"):
        StaticCase("face.inp", default_plan(phantom), {})
    with pytest.raises(TypeError, match="plan is a dict; expected a SurgicalPlan"):
        StaticCase(phantom, {}, {})
