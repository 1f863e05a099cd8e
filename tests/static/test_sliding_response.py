"""The face's linear response under the FE's boundary conditions: the same constrained linear
solve as the FE's first solve of a step, by another method (a reduced basis and the lip ties'
Schur complement instead of the FE's elimination and refactorization per active set)."""

import numpy as np
import pytest

from toolkit.common.phantoms.phantom import face_hex
from toolkit.static import default_plan
from toolkit.static.baselines import InfluenceMatrix
from toolkit.static.constraints import Constraints
from toolkit.static.database import bone_increment
from toolkit.static.plan import SurgicalPlan
from toolkit.static.problem import StaticProblem, solve_with_lip_contact
from toolkit.static.simulate import material_assignment
from toolkit.static.sliding_response import SlidingResponse


@pytest.fixture(scope="module")
def phantom():
    return face_hex("coarse")


@pytest.fixture(scope="module")
def response(phantom):
    return SlidingResponse.build(phantom, "mucosa+lip")


def fe_solve(phantom, response, bone):
    """The FE's constrained solve of one increment on the pre-operative mesh: moving nodes
    follow the bone, fixed nodes stay, mucosa nodes keep the bone's normal displacement, lip
    pairs in the FE's active set."""
    bc = response.bc
    fixed = np.flatnonzero(bc.types == 2)
    nodes = np.concatenate([fixed, response.moving])
    values = np.vstack([np.zeros((fixed.size, 3)), bone[response.moving]])
    g = np.einsum("ij,ij->i", response.normals, bone[response.mucosa])
    c = Constraints(phantom.mesh.n_points, nodes, values, response.mucosa, response.normals, g)
    problem = StaticProblem(phantom.mesh, material_assignment("linear", phantom.mesh), "superlu")
    return solve_with_lip_contact(problem, c, bc.upper_lip, bc.lower_lip, threshold=response.lip_threshold)


@pytest.mark.parametrize("motion", ["default", "mandible down", "mandible up"])
def test_equals_the_fe_constrained_solve(phantom, response, motion):
    """For the packaged plan, a mandible moved 6 mm down (lips open: every tie pulls and is
    released) and 4 mm up (lips pressed: ties hold), the response equals the FE's own solve of
    the same constraints to 1e-8 of the largest displacement, and ends with the same tied pairs."""
    vertical = {"mandible down": -6.0, "mandible up": 4.0}
    plan = (default_plan(phantom) if motion == "default" else
            SurgicalPlan.from_dict({"distal": {"translation_mm": [0.0, 0.0, vertical[motion]]}}, phantom=phantom))
    X = phantom.mesh.points
    bone = bone_increment(X, response.bc, plan)
    got = response.increment(bone, X)
    fe = fe_solve(phantom, response, bone)
    scale = np.abs(fe.solution.displacement).max()
    np.testing.assert_allclose(got, fe.solution.displacement, rtol=0, atol=1e-8 * scale)
    # the contact conditions hold: no pair interpenetrates, tied pairs close their gap
    gap = (X + got)[response.upper, 2] - (X + got)[response.lower, 2]
    assert gap.min() >= -1e-6
    np.testing.assert_allclose(gap[fe.active], 0.0, atol=1e-8 * scale)
    if motion == "mandible down":
        assert not fe.active.any() and gap.min() > 0
    if motion == "mandible up":
        assert fe.active.sum() >= response.upper.size // 2


def test_without_sliding_or_lips_it_is_the_influence_matrix(phantom):
    """With no sliding model every mucosa node moves with its bone and no lip pair is tied:
    the response is the influence matrix's superposition of the same prescribed motion (1e-9)."""
    resp = SlidingResponse.build(phantom, "none")
    assert resp.mucosa.size == 0 and resp.upper.size == 0
    bone = bone_increment(phantom.mesh.points, resp.bc, default_plan(phantom))
    im = InfluenceMatrix.build(phantom.mesh, resp.moving, np.flatnonzero(resp.bc.types == 2))
    want = im.predict(np.where((resp.bc.types == 1)[:, None], bone, 0.0))
    np.testing.assert_allclose(resp.increment(bone), want, rtol=0, atol=1e-9 * np.abs(want).max())


def test_trajectory_steps_from_the_reached_positions_and_adds_the_correction(phantom, response):
    plan = default_plan(phantom)
    X = phantom.mesh.points
    U, bones = response.trajectory(plan, 1)
    np.testing.assert_array_equal(U[0], 0.0)
    np.testing.assert_allclose(U[1], response.increment(bone_increment(X, response.bc, plan), X))
    correction = np.full((2,) + X.shape, 0.1)
    U2, bones2 = response.trajectory(plan, 2, correction)
    step = plan.increments(2)
    second = response.increment(bone_increment(X + U2[1], response.bc, step[1], step[0]), X + U2[1])
    np.testing.assert_allclose(U2[2] - U2[1], second + 0.1)
    assert U2.shape == (3,) + X.shape and bones2.shape == (2,) + X.shape


def test_a_bone_motion_of_the_wrong_shape_is_refused(response):
    with pytest.raises(ValueError, match=r"bone motion has shape \(5, 3\); expected"):
        response.increment(np.zeros((5, 3)))
