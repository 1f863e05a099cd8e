"""Anatomical axes: every phantom is a face in the toolkit's axes (x left, y anterior, z superior);
the same face mirrored front to back (LPS), upside down or with y and z exchanged is refused with
the conversion that fits; LPS and RAS convert back exactly, with cells that stay positive."""

import numpy as np
import pytest

from toolkit.common import face_hex, face_tet
from toolkit.common.meshes import io
from toolkit.common.meshes.axes import (
    AXES,
    AxesError,
    check_anatomical_axes,
    check_mesh_axes,
    mesh_to_toolkit,
    to_toolkit,
)
from toolkit.common.phantoms.mixed_bar import mixed_bar
from toolkit.common.phantoms.phantom import FaceShape
from toolkit.mesh.phantom import phantom_surfaces

#: file coordinates -> the toolkit's, for a file that is: mirrored front to back (LPS), upside
#: down, with y and z exchanged (a face lying on its back); the remedy each message names
WRONG = {
    "y mirrored (LPS)": (np.diag([1.0, -1.0, 1.0]), 'axes="LPS" (command line: --axes LPS)'),
    "z flipped": (np.diag([1.0, 1.0, -1.0]), "toolkit (x, y, z) = (x, y, -z)"),
    "y and z swapped": (np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]]), "toolkit (x, y, z) = (x, z, y)"),
}


@pytest.fixture(scope="module")
def surfaces():
    return phantom_surfaces(face_hex("coarse"))


def _moved(points, m):
    return np.asarray(points) @ m.T


@pytest.mark.parametrize("resolution", ["coarse", "paper"])
def test_every_phantom_is_a_face_in_the_toolkits_axes(resolution):
    """The hexahedral phantom with its segments, the impact phantom (skin and bone sets only),
    the segmentation-like surfaces with and without their bones, and sampled subjects pass."""
    ph = face_hex(resolution)
    check_mesh_axes(ph.mesh, {k: s.surface for k, s in ph.segments.items()})
    check_mesh_axes(face_tet(resolution, order=1))
    s = phantom_surfaces(ph)
    check_anatomical_axes(s.tissue.points, {k: b.points for k, b in s.bones.items()})
    check_anatomical_axes(s.tissue.points)
    for seed in (1, 2, 3):
        subject = face_hex("coarse", FaceShape.sample(seed))
        check_mesh_axes(subject.mesh, {k: s.surface for k, s in subject.segments.items()})


@pytest.mark.parametrize("bones", ["named", "unnamed", "none"])
@pytest.mark.parametrize("wrong", list(WRONG))
def test_a_face_in_other_axes_is_refused_with_the_conversion_that_fits(surfaces, wrong, bones):
    """Mirrored front to back the face's front is its wide posterior edge and lies behind the
    bones; upside down the mandible is above the maxilla (or, skin alone, the face widens toward
    the chin and its lowest part stands farthest forward); with y and z exchanged the front is the
    top cut, across the whole width. The message names the file, what it found and the remedy."""
    m, remedy = WRONG[wrong]
    named = {k: _moved(b.points, m) for k, b in surfaces.bones.items()}
    given = {"named": named, "unnamed": np.concatenate(list(named.values())), "none": None}[bones]
    with pytest.raises(AxesError, match="not in the toolkit's axes") as info:
        check_anatomical_axes(_moved(surfaces.tissue.points, m), given, source="tissue.stl")
    text = str(info.value)
    assert text.startswith("tissue.stl is not") and "expected" in text and remedy in text


def test_a_left_right_mirror_is_told_only_by_the_named_sides(surfaces):
    """A face is left-right symmetric: RAS read as the toolkit's axes passes on the skin and on
    unnamed bones, and is refused by the proximal segments' sides, naming --axes RAS."""
    m = np.diag([-1.0, 1.0, 1.0])
    named = {k: _moved(b.points, m) for k, b in surfaces.bones.items()}
    check_anatomical_axes(_moved(surfaces.tissue.points, m), np.concatenate(list(named.values())))
    with pytest.raises(AxesError, match=r"proximal_left's centre is at x = -\d.*--axes RAS"):
        check_anatomical_axes(_moved(surfaces.tissue.points, m), named)


def test_a_wrong_declaration_is_refused_with_the_right_one(surfaces):
    """Toolkit files declared LPS are mirrored by the conversion: the remedy is the default."""
    tissue = to_toolkit(surfaces.tissue.points, "LPS")
    bones = {k: to_toolkit(b.points, "LPS") for k, b in surfaces.bones.items()}
    with pytest.raises(AxesError, match=r'axes="toolkit" \(command line: --axes toolkit, the default\)'):
        check_anatomical_axes(tissue, bones, axes="LPS")


@pytest.mark.parametrize("axes", ["LPS", "RAS"])
def test_conversions_give_back_the_toolkits_points_exactly(surfaces, axes):
    """A mirror is its own inverse: converting the mirrored points gives the points bit for bit,
    and the surface's triangles their winding (the same cells)."""
    mirrored = to_toolkit(surfaces.tissue.points, axes)
    assert not np.array_equal(mirrored, surfaces.tissue.points)
    assert np.array_equal(to_toolkit(mirrored, axes), surfaces.tissue.points)
    back = mesh_to_toolkit(mesh_to_toolkit(surfaces.tissue, axes), axes)
    assert np.array_equal(back.points, surfaces.tissue.points)
    assert np.array_equal(back.cells["tri3"], surfaces.tissue.cells["tri3"])
    assert mesh_to_toolkit(surfaces.tissue, "toolkit") is surfaces.tissue


@pytest.mark.parametrize("mesh", ["hex8", "tet10", "hex8+wedge6"])
def test_a_mirrored_volume_mesh_keeps_positive_cells(mesh):
    """Each cell's nodes are reflected on its reference element: every scaled Jacobian stays
    positive (a mirror alone turns them all negative) and vectors mirror with the points."""
    m = {"hex8": face_hex("coarse").mesh, "tet10": face_tet("coarse", order=2), "hex8+wedge6": mixed_bar(1)}[mesh]
    m = m.with_point_data(arrow=np.tile([1.0, 2.0, 3.0], (m.n_points, 1)))
    for axes in ("LPS", "RAS"):
        out = mesh_to_toolkit(m, axes)
        assert out.scaled_jacobian().min() == pytest.approx(m.scaled_jacobian().min())
        assert np.array_equal(out.point_data["arrow"][0], to_toolkit([1.0, 2.0, 3.0], axes))
        assert all(np.array_equal(out.node_sets[k], v) for k, v in m.node_sets.items())


def test_unknown_axes_are_refused_with_the_choices():
    with pytest.raises(AxesError, match=r"axes = 'RAI'; expected one of toolkit, LPS, RAS \(command line: --axes\)"):
        to_toolkit(np.zeros((1, 3)), "RAI")


def test_the_command_lines_choices_are_the_librarys():
    from toolkit.cli._common import AXES as CLI_AXES

    assert CLI_AXES == AXES


def test_load_case_converts_and_checks_a_mesh_file(tmp_path):
    """A face mesh written in LPS: refused as it is, read back to the phantom's points with
    axes="LPS" (its plan stays in the toolkit's axes); the phantom takes no axes."""
    from toolkit.static import default_plan, load_case

    ph = face_hex("coarse")
    io.write(tmp_path / "face_lps.vtu", mesh_to_toolkit(ph.mesh, "LPS"))
    plan = default_plan(ph)
    with pytest.raises(AxesError, match=r"face_lps.vtu is not in the toolkit's axes.*--axes LPS"):
        load_case(tmp_path / "face_lps.vtu", plan=plan)
    case = load_case(tmp_path / "face_lps.vtu", plan=plan, axes="LPS")
    assert np.array_equal(case.mesh.points, ph.mesh.points)
    assert case.mesh.scaled_jacobian().min() > 0
    with pytest.raises(AxesError, match="built-in phantom"):
        load_case(resolution="coarse", axes="LPS")


def test_an_impact_scene_converts_and_checks_its_mesh(tmp_path):
    """The impact phantom written in LPS (skin and bone sets, no segments): refused by the face
    mesh reader, read back with the scene's ``axes``."""
    from toolkit.impact.scene import Scene, SceneError
    from toolkit.impact.simulate import face_mesh

    tet = face_tet("coarse", order=1)
    io.write(tmp_path / "tet_lps.vtu", mesh_to_toolkit(tet, "LPS"))
    scene = Scene().with_face(mesh=str(tmp_path / "tet_lps.vtu")).with_fidelity(order=1)
    with pytest.raises(AxesError, match="tet_lps.vtu is not in the toolkit's axes"):
        face_mesh(scene)
    assert np.allclose(face_mesh(scene.with_face(axes="LPS")).points, tet.points)
    with pytest.raises(SceneError, match="face axes 'LSP'"):
        scene.with_face(axes="LSP")


def test_a_static_database_on_a_mesh_converts_and_checks_it(tmp_path):
    """``DatabaseConfig.for_mesh(..., axes=)``: the subject is refused in the wrong axes and read
    back in the toolkit's with them; the configuration of a face in the toolkit's axes has no
    ``axes`` key (as databases made without one)."""
    from toolkit.static.database import DatabaseConfig, database_subject

    ph = face_hex("coarse")
    io.write(tmp_path / "face_lps.vtu", mesh_to_toolkit(ph.mesh, "LPS"))
    with pytest.raises(AxesError, match="--axes LPS"):
        database_subject(DatabaseConfig.for_mesh(tmp_path / "face_lps.vtu", plans=1), 0)
    config = DatabaseConfig.for_mesh(tmp_path / "face_lps.vtu", axes="LPS", plans=1)
    assert np.array_equal(database_subject(config, 0).mesh.points, ph.mesh.points)
    assert config.to_dict()["axes"] == "LPS" and "axes" not in DatabaseConfig().to_dict()
