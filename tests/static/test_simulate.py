"""The lip-sliding paper's incremental orthognathic simulation on the coarse phantom: boundary
conditions met exactly, lips that never interpenetrate, physiological extremes, the
small-strain agreement of Neo-Hookean and linear models, and convergence in the number
of increments. Units mm."""

import warnings

import numpy as np
import pytest

from toolkit.common.analysis.surface_distance import closest_points
from toolkit.common.fem.materials import LinearElastic
from toolkit.common.phantoms.phantom import face_hex
from toolkit.static.boundary import BoundaryConditions, NodeType
from toolkit.static.plan import (
    PlanRangeWarning,
    RigidMotion,
    SurgicalPlan,
    default_plan,
)
from toolkit.static.simulate import SimulationError, simulate
from toolkit.static.stiffness import MaterialAssignment


@pytest.fixture(scope="module")
def phantom():
    return face_hex("coarse")


@pytest.fixture(scope="module")
def plan(phantom):
    return default_plan(phantom)


@pytest.fixture(scope="module")
def linear3(phantom, plan):
    """Default plan, 3 increments, the lip-sliding paper's linear materials, mucosa and lip sliding."""
    return simulate(phantom, plan, 3, "linear", "mucosa+lip")


def _lip_penetration(phantom, u):
    """Largest craniocaudal interpenetration (mm, 0 if none) of the closed-mouth lip pairs
    (upper-lip copy below its lower-lip twin) for displacement ``u (n, 3)``."""
    bc = BoundaryConditions.from_mesh(phantom.mesh, phantom.segments)
    x = phantom.mesh.points + u
    gap = x[bc.upper_lip, 2] - x[bc.lower_lip, 2]
    return float(max(0.0, -gap.min()))


def test_default_plan_meets_every_boundary_condition(phantom, plan, linear3):
    """Default bimaxillary plan, 3 increments, linear: after the last increment fixed nodes
    have not moved (exactly), attached nodes sit where their segment's rigid motion puts
    them (1e-9 mm), every mucosa node lies on its moved bone surface (distance to the
    triangles < 1e-9 mm: step 2 projects and prescribes them), and no lip pair
    interpenetrates (<= 1e-9 mm). Every increment is stored (row 0 the pre-operative
    state) and its attached nodes follow the slerp-interpolated plan k/3. The mesh stays
    well shaped (min scaled Jacobian > 0.2)."""
    res = linear3
    X = phantom.mesh.points
    bc = res.boundary
    assert res.displacements.shape == (4, phantom.mesh.n_points, 3)
    assert np.all(res.displacements[0] == 0.0)
    u = res.displacement
    assert np.all(u[bc.nodes(NodeType.FIXED)] == 0.0)
    for k, plan_k in enumerate(plan.increments(3), start=1):
        for name in bc.segment_names:
            ids = bc.segment_nodes(NodeType.MOVING, name)
            np.testing.assert_allclose(X[ids] + res.displacements[k][ids], plan_k.motion(name).apply(X[ids]),
                                       rtol=0, atol=1e-9)
    n_mucosa = 0
    for name in bc.segment_names:
        ids = bc.segment_nodes(NodeType.MUCOSA_SLIDING, name)
        surf = phantom.segments[name].surface
        d = closest_points(X[ids] + u[ids], plan.motion(name).apply(surf.points), surf.cells["tri3"]).distance
        assert d.max() < 1e-9, name
        n_mucosa += ids.size
    released = np.intersect1d(bc.released, phantom.mesh.node_sets["mucosa_sliding"]).size
    assert n_mucosa == phantom.mesh.node_sets["mucosa_sliding"].size - released
    assert _lip_penetration(phantom, u) <= 1e-9
    s = res.summary()
    assert s["max_penetration_mm"] <= 1e-9 and s["max_mucosa_gap_mm"] < 1e-9
    assert s["min_scaled_jacobian"] > 0.2
    assert all(r.min_scaled_jacobian > 0.2 for r in res.reports)
    assert s["increments"] == 3


def test_lip_contact_prevents_interpenetration(phantom):
    """Closing the mouth hard (distal mandible up 3 mm and rotated 5 degrees about the
    transverse axis, chin up) pushes the lower lip into the upper one. With lip contact
    ('mucosa+lip') the pairs are tied craniocaudally: interpenetration <= 1e-6 mm (the
    active-set tolerance), measured from the displacements themselves. Without it
    ('mucosa') the lower lip passes through the upper one by more than 0.1 mm (millimetres
    in fact): the contrast shows the contact is what holds the lips apart."""
    distal = RigidMotion.from_rotation_vector([5.0, 0, 0], [0, 0, 3.0], phantom.segments["distal"].pivot)
    closing = SurgicalPlan.for_phantom(phantom, distal=distal)
    with_lips = simulate(phantom, closing, 3, "linear", "mucosa+lip")
    without = simulate(phantom, closing, 3, "linear", "mucosa")
    assert with_lips.summary()["max_penetration_mm"] <= 1e-6
    assert _lip_penetration(phantom, with_lips.displacement) <= 1e-6
    assert any(r.active_lip_pairs > 0 for r in with_lips.reports)
    assert _lip_penetration(phantom, without.displacement) > 0.1


def _extreme_plan(phantom, factor, force=False):
    """Le Fort I as in the default plan (4 mm advance, 2 mm impaction, 3 degrees) and the
    distal mandible at the lip-sliding paper's limits: 11.5 mm advance and 13.3 degrees about the
    transverse axis; both times ``factor``."""
    lefort = RigidMotion.from_rotation_vector([3.0 * factor, 0, 0], [0, 4.0 * factor, -2.0 * factor],
                                              phantom.segments["lefort"].pivot)
    distal = RigidMotion.from_rotation_vector([-13.3 * factor, 0, 0], [0, 11.5 * factor, 0],
                                              phantom.segments["distal"].pivot)
    return SurgicalPlan.for_phantom(phantom, lefort=lefort, distal=distal, force=force)


def test_physiological_extreme_converges(phantom):
    """The distal mandible at the edge of the lip-sliding paper's range (11.5 mm, 13.3 degrees) with a
    Le Fort I inside its range is a plan the simulation must handle: it converges, the
    post-operative mesh has positive Jacobians, attached nodes reach their targets
    (1e-9 mm) and the lips do not interpenetrate (1e-6 mm)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", PlanRangeWarning)  # really within the range
        plan = _extreme_plan(phantom, 1.0)
    res = simulate(phantom, plan, 3, "linear", "mucosa+lip")
    assert res.summary()["min_scaled_jacobian"] > 0
    X, bc = phantom.mesh.points, res.boundary
    ids = bc.segment_nodes(NodeType.MOVING, "distal")
    np.testing.assert_allclose(X[ids] + res.displacement[ids], plan.motions["distal"].apply(X[ids]), atol=1e-9)
    assert res.summary()["max_penetration_mm"] <= 1e-6


def test_twice_the_physiological_range_fails_cleanly_or_converges(phantom):
    """Twice the range (built with force=True; warned as beyond the range) is beyond what the
    coarse soft-tissue mesh can follow in 3 increments: the simulation either converges
    with positive Jacobians, or raises SimulationError naming the increment, the worst
    element and a suggestion; it never returns an inverted mesh."""
    with pytest.warns(PlanRangeWarning, match="beyond the physiological range"):
        plan = _extreme_plan(phantom, 2.0, force=True)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PlanRangeWarning)  # the increments' plans warn again
            res = simulate(phantom, plan, 3, "linear", "mucosa+lip")
    except SimulationError as exc:
        msg = str(exc)
        assert 1 <= exc.increment <= 3 and msg.startswith(f"increment {exc.increment}:")
        assert "Suggestion:" in msg and exc.suggestion and exc.suggestion in msg
        assert exc.element is None or f"element {exc.element}" in msg
    else:
        assert res.summary()["min_scaled_jacobian"] > 0


def test_neo_hookean_agrees_with_linear_at_small_strain(phantom, plan):
    """Small strains: Neo-Hookean linearises to Hooke's law with the same E and nu, so for
    a small plan (default plan scaled 0.2, ~1 mm bone motion) the two give nearly the same
    skin displacement: relative L2 difference < 5%. The difference is of the order of the
    strain, so it grows with the plan (scale 0.5 differs more). Both isotropic
    (E = 0.003 MPa, nu = 0.47) so that only the kinematics differ. The Neo-Hookean run
    converges with positive Jacobians and needs Newton iterations."""
    skin = phantom.mesh.node_sets["skin"]
    diffs = []
    for scale in (0.2, 0.5):
        p = plan.scaled(scale)
        lin = simulate(phantom, p, 3, MaterialAssignment(LinearElastic(0.003, 0.47)), "mucosa+lip")
        neo = simulate(phantom, p, 3, "neo-hookean", "mucosa+lip")
        assert neo.summary()["min_scaled_jacobian"] > 0
        assert all(r.newton_iterations > 0 for r in neo.reports)
        a, b = lin.displacement[skin], neo.displacement[skin]
        diffs.append(np.linalg.norm(a - b) / np.linalg.norm(b))
    assert diffs[0] < 0.05
    assert diffs[0] < diffs[1]


def test_neo_hookean_default_plan_converges(phantom, plan):
    """The full default plan with Neo-Hookean (total Lagrangian, increments as load steps):
    3 increments converge, positive Jacobians, fixed nodes still, attached nodes on target
    (1e-9 mm), mucosa on the moved bone (1e-9 mm), lips not interpenetrating (1e-6 mm)."""
    res = simulate(phantom, plan, 3, "neo-hookean", "mucosa+lip")
    X, bc, u = phantom.mesh.points, res.boundary, res.displacement
    s = res.summary()
    assert s["min_scaled_jacobian"] > 0.2
    assert np.all(u[bc.nodes(NodeType.FIXED)] == 0.0)
    for name in bc.segment_names:
        ids = bc.segment_nodes(NodeType.MOVING, name)
        np.testing.assert_allclose(X[ids] + u[ids], plan.motion(name).apply(X[ids]), rtol=0, atol=1e-9)
    assert s["max_mucosa_gap_mm"] < 1e-9 and s["max_penetration_mm"] <= 1e-6


def test_more_increments_change_the_answer_less(phantom, plan):
    """Consistency of the incremental (updated-geometry, small-strain per step) scheme:
    as the number of increments grows the answer converges, so 10 increments differ from
    3 less than 3 differ from 1: |u10 - u3| < |u3 - u1|. A scheme first order in the step
    1/n has |u10 - u3| / |u3 - u1| ~ (1/3 - 1/10) / (1 - 1/3) = 0.35; allowed 0.2-0.5."""
    u = {n: simulate(phantom, plan, n, "linear", "mucosa+lip").displacement for n in (1, 3, 10)}
    d_hi = np.linalg.norm(u[10] - u[3])
    d_lo = np.linalg.norm(u[3] - u[1])
    assert d_hi < d_lo
    assert 0.2 < d_hi / d_lo < 0.5


def test_points_beyond_the_rim_of_an_open_surface_go_onto_the_edge_plane():
    """Unit square z = 0 in two triangles: a point above the inside projects straight down
    (unchanged closest point); a point past the edge x = 1 projects onto the plane z = 0 at
    its own x, y (not onto the edge line); past the corner as well."""
    from toolkit.common.analysis.surface_distance import beyond_rim_onto_plane, closest_points
    from toolkit.common.meshes.topology import rim_edges

    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    assert sorted(map(tuple, rim_edges(tris).tolist())) == [(0, 1), (0, 3), (1, 2), (2, 3)]
    q = np.array([[0.3, 0.6, 0.5], [1.4, 0.5, -0.2], [1.5, 1.5, 0.3]])
    cp = closest_points(q, pts, tris)
    ext, beyond = beyond_rim_onto_plane(q, cp, pts, tris)
    assert beyond.tolist() == [False, True, True]
    np.testing.assert_allclose(ext.point, [[0.3, 0.6, 0.0], [1.4, 0.5, 0.0], [1.5, 1.5, 0.0]], atol=1e-12)
    np.testing.assert_allclose(ext.distance, [0.5, 0.2, 0.3], atol=1e-12)
    np.testing.assert_allclose(cp.point[1], [1.0, 0.5, 0.0], atol=1e-12)  # the plain closest point: on the edge


@pytest.mark.parametrize("guess", ["linear run", "inverting"])
def test_a_newton_run_from_an_initial_guess_reaches_the_same_equilibrium(phantom, plan, linear3, guess):
    """Neo-Hookean increments started from another run's displacements (the linear one: close),
    or from a guess that inverts elements (Newton cannot start there and starts from the previous
    equilibrium instead), end at the cold run's equilibrium to 1e-6 mm."""
    cold = simulate(phantom, plan, 3, "neo-hookean", "mucosa+lip")
    start = linear3.displacements if guess == "linear run" else 50.0 * linear3.displacements
    warm = simulate(phantom, plan, 3, "neo-hookean", "mucosa+lip", initial_guess=start)
    np.testing.assert_allclose(warm.displacements, cold.displacements, rtol=0, atol=1e-6)
    assert all(r.newton_iterations > 0 for r in warm.reports)


def test_an_initial_guess_of_the_wrong_shape_is_refused(phantom, plan):
    with pytest.raises(ValueError, match=r"initial_guess has shape \(3, 5, 3\); expected finite \(4, 771, 3\)"):
        simulate(phantom, plan, 3, "neo-hookean", "mucosa+lip", initial_guess=np.zeros((3, 5, 3)))
    with pytest.raises(ValueError, match="expected finite"):
        simulate(phantom, plan, 3, "neo-hookean", "mucosa+lip", initial_guess=np.full((4, 771, 3), np.nan))
