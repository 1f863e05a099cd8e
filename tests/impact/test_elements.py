"""Tetrahedral elements of the explicit solver: the assembled small-strain stiffness is the
linearisation of the internal forces, HRZ lumped masses follow from the shape-function
integrals, and the critical time step scales like a wave transit time (h / c)."""

import numpy as np
import pytest

from toolkit.common.fem.kinematics import deformation_gradient, internal_force, lumped_mass
from toolkit.common.meshes.mesh import Mesh
from toolkit.common.meshes.topology import tet10_from_tet4
from toolkit.common.phantoms.phantom import block
from toolkit.impact.elements import _element_stiffness, critical_time_step, tet_kinematics
from toolkit.impact.plasticity import J2Plasticity

RHO = 1e-9


def _block(order, jitter=0.3, seed=0):
    """2 x 2 x 1 hexahedra of 2 mm (4 x 4 x 2 mm), 6 Kuhn tets each, nodes jittered by up to ``jitter`` mm."""
    axes = [np.linspace(0, 4, 3), np.linspace(0, 4, 3), np.linspace(0, 2, 2)]
    return block(axes, "tet4" if order == 1 else "tet10", jitter=jitter, seed=seed)


@pytest.mark.parametrize("order", [1, 2], ids=["tet4", "tet10"])
def test_element_stiffness_is_the_linearisation_of_internal_force(order):
    """The small-strain element stiffness (lambda, mu of E = 1 MPa, nu = 0.3) used for the
    eigenvalue time step equals the derivative at u = 0 of the internal forces that the explicit
    solver computes (deformation gradient -> Hencky-J2 material -> int P grad N), because Hencky
    elasticity linearises to Hooke's law. Central differences with a step of 1e-6 of a random
    displacement field (truncation O(1e-12), round-off ~1e-10 relative) must match K w to 1e-7
    of |K w|."""
    E, nu = 1.0, 0.3
    mesh = _block(order)
    kin = tet_kinematics(mesh)
    n = mesh.n_points
    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    material = J2Plasticity(E, nu, RHO)
    w = np.random.default_rng(1).normal(size=(n, 3))

    def f_int(u):
        F = deformation_gradient(kin, u)
        P = material.update(F.reshape(-1, 3, 3), material.initial_state(kin.n_points)).first_piola
        return internal_force(kin, P.reshape(F.shape), n)

    eps = 1e-6
    fd = (f_int(eps * w) - f_int(-eps * w)) / (2 * eps)
    Ke = _element_stiffness(kin, lam, mu)
    we = w[kin.conn].reshape(len(kin.conn), -1)  # (E, 3A), dof order (node, component)
    fe = np.einsum("eij,ej->ei", Ke, we).reshape(kin.conn.shape + (3,))
    Kw = np.stack([np.bincount(kin.conn.ravel(), weights=fe[..., k].ravel(), minlength=n) for k in range(3)], axis=1)
    np.testing.assert_allclose(fd, Kw, rtol=0, atol=1e-7 * np.abs(Kw).max())


def test_lumped_masses_follow_the_shape_function_integrals():
    """tet4: each corner gets rho V / 4 (row sum of the consistent mass). tet10 (HRZ): the diagonal
    of the consistent mass, int rho N_a^2 dV = rho V / 70 at a corner and 8 rho V / 105 at a
    mid-edge node on a straight tetrahedron, scaled so that the element mass is rho V: corners
    1/36, mid-edge nodes 4/27 of rho V (all positive). On a jittered block the nodal masses sum
    to rho times the exact mesh volume (1e-12)."""
    X = np.array([[0.0, 0, 0], [2, 0, 0], [0.5, 1.5, 0], [0.3, 0.4, 1.7]])
    V = abs(np.linalg.det(X[1:] - X[0])) / 6
    m4 = lumped_mass(tet_kinematics(Mesh(X, {"tet4": [[0, 1, 2, 3]]})), RHO, 4)
    np.testing.assert_allclose(m4, RHO * V / 4, rtol=1e-12)
    P10, t10 = tet10_from_tet4(X, np.array([[0, 1, 2, 3]]))
    m10 = lumped_mass(tet_kinematics(Mesh(P10, {"tet10": t10})), RHO, 10)
    diag = np.array([1 / 70] * 4 + [8 / 105] * 6)
    np.testing.assert_allclose(m10[t10[0]], RHO * V * diag / diag.sum(), rtol=1e-12)
    np.testing.assert_allclose(diag / diag.sum(), [1 / 36] * 4 + [4 / 27] * 6, rtol=1e-12)
    for order in (1, 2):
        mesh = _block(order)
        corners = mesh.points[mesh.volume_cells[:, :4]]
        volume = np.abs(np.linalg.det(corners[:, 1:] - corners[:, :1])).sum() / 6
        assert lumped_mass(tet_kinematics(mesh), RHO, mesh.n_points).sum() == pytest.approx(RHO * volume, rel=1e-12)


@pytest.mark.parametrize("order", [1, 2], ids=["tet4", "tet10"])
def test_critical_time_step_scales_with_size_and_sqrt_density(order):
    """Element frequencies are sqrt(stiffness / mass) with stiffness ~ (lambda + 2 mu) h and mass ~
    rho h^3, so the critical step is a wave transit time ~ h sqrt(rho / (lambda + 2 mu)): scaling the
    mesh by 2 doubles it, mass scaling by f multiplies it by sqrt(f) (what Fidelity.mass_scaling
    relies on), and scaling the moduli by 4 halves it, all exactly (1e-12)."""
    mesh = _block(order)
    lam, mu = 0.5, 0.3
    dt = critical_time_step(tet_kinematics(mesh), lam, mu, RHO)[0]
    big = Mesh(2.0 * mesh.points, dict(mesh.cells))
    assert critical_time_step(tet_kinematics(big), lam, mu, RHO)[0] == pytest.approx(2 * dt, rel=1e-12)
    assert critical_time_step(tet_kinematics(mesh), lam, mu, 100 * RHO)[0] == pytest.approx(10 * dt, rel=1e-12)
    assert critical_time_step(tet_kinematics(mesh), 4 * lam, 4 * mu, RHO)[0] == pytest.approx(dt / 2, rel=1e-12)


@pytest.mark.parametrize("order", [1, 2], ids=["tet4", "tet10"])
def test_compiled_element_loops_match_numpy(order, monkeypatch):
    """The compiled deformation-gradient and internal-force loops equal the batched numpy
    versions (``TOOLKIT_JIT=0``) to 1e-13 relative on a jittered block."""
    from toolkit.common.fem.jit import HAVE_NUMBA

    if not HAVE_NUMBA:
        pytest.skip("numba not installed: only the numpy path exists")
    mesh = _block(order)
    kin = tet_kinematics(mesh)
    rng = np.random.default_rng(3)
    u = 0.2 * rng.normal(size=(mesh.n_points, 3))
    P = rng.normal(size=kin.weight.shape + (3, 3))
    F_jit, f_jit = deformation_gradient(kin, u), internal_force(kin, P, mesh.n_points)
    monkeypatch.setenv("TOOLKIT_JIT", "0")
    F_np, f_np = deformation_gradient(kin, u), internal_force(kin, P, mesh.n_points)
    np.testing.assert_allclose(F_jit, F_np, rtol=0, atol=1e-13 * np.abs(F_np).max())
    np.testing.assert_allclose(f_jit, f_np, rtol=0, atol=1e-13 * np.abs(f_np).max())
