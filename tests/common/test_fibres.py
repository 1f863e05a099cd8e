"""The lip muscle's fibres on meshes that carry none (``toolkit.common.fem.fibres``)."""

import warnings

import numpy as np
import pytest

from toolkit.common import face_hex
from toolkit.common.fem.fibres import superior_fibres, with_lip_fibres
from toolkit.common.meshes.mesh import Mesh


def _tet(skin):
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    return Mesh(points, {"tet4": np.array([[0, 1, 2, 3]])}, node_sets={"skin": np.array(skin)})


def test_fibre_is_the_superior_axis_in_the_skin_plane():
    # skin x + y + z = 1 (normal (1,1,1)/sqrt 3): z minus its normal part is (-1,-1,2)/sqrt 6
    assert np.allclose(superior_fibres(_tet([1, 2, 3]), np.array([1, 2, 3])), np.array([[-1, -1, 2]]) / 6 ** 0.5)
    # skin x = 0 (vertical): the fibre is +z itself
    assert np.allclose(superior_fibres(_tet([0, 2, 3]), np.array([0, 2, 3])), [[0, 0, 1]])
    # skin z = 0 (horizontal): no tangent superior direction, +z
    assert np.allclose(superior_fibres(_tet([0, 1, 2]), np.array([0, 1, 2])), [[0, 0, 1]])


def test_rule_follows_the_phantoms_own_fibres():
    """Over the phantom's lip muscle the rule lies within 10 degrees of the phantom's fibres at
    the median (measured 6.8) and 30 at worst (22): the phantom's fibres follow its grid lines,
    which curve with the face's profile as the skin's tangent does."""
    m = face_hex("coarse").mesh
    lip = m.element_sets["lip_muscle"]
    cos = np.abs(np.sum(superior_fibres(m, m.node_sets["skin"])[lip] * m.cell_data["fibre_direction"][lip], axis=1))
    angle = np.degrees(np.arccos(np.clip(cos, 0, 1)))
    assert np.median(angle) < 10 and angle.max() < 30, (np.median(angle), angle.max())


def test_a_mesh_without_fibres_gets_them_on_loading_and_warns_when_simulated_without():
    from toolkit.static import load_case
    from toolkit.static.simulate import material_assignment

    phantom = face_hex("coarse")
    bare = phantom.mesh.without_fields()  # as an Abaqus file reads: sets, no cell fields
    assert with_lip_fibres(phantom.mesh) is phantom.mesh
    with pytest.warns(UserWarning, match="lip muscle is isotropic"):
        assert material_assignment("linear", bare).regions in ({}, None)
    case = load_case(bare, plan=load_case(resolution="coarse").plan)
    assert case.subject.cell_data["fibre_direction"].shape == (bare.n_cells, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert set(material_assignment("linear", case.subject).regions) == {"lip_muscle"}
