"""Static finite-element solver against closed forms: patch tests on distorted hexahedra,
Lame's thick-walled cylinder (O(h^2) convergence, volumetric locking and its cure by the
mean-dilatation element), Neo-Hookean uniaxial stretch, rigid motions, frictionless
sliding, lip contact and Newton's robustness. float64 throughout; units mm, MPa, N."""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from toolkit.common.fem.assembly import SparsePattern
from toolkit.common.fem.materials import (
    LinearElastic,
    NeoHookean,
    TransverselyIsotropic,
    lame,
)
from toolkit.common.fem.solvers import solve
from toolkit.common.meshes.mesh import Mesh
from toolkit.static.constraints import Constraints
from toolkit.static.problem import StaticProblem, solve_with_lip_contact
from toolkit.static.stiffness import (
    MaterialAssignment,
    kinematics,
    linear_stiffness,
    neo_hookean_energy,
    neo_hookean_system,
    small_strain,
)

# VTK hex8 corner order by local (i, j, k) bits
_ORDER = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]


def _hexes(ids: np.ndarray) -> np.ndarray:
    """hex8 connectivity (VTK order) of a structured node-id array ``(ni+1, nj+1, nk+1)``."""
    ni, nj, nk = (s - 1 for s in ids.shape)
    return np.stack([ids[a:ni + a, b:nj + b, c:nk + c].ravel() for a, b, c in _ORDER], axis=1)


def box(n=(3, 3, 3), size=(10.0, 10.0, 10.0), origin=(0.0, 0.0, 0.0)):
    """Structured hex grid of the box ``origin + [0, size]``: points (N, 3) mm, hexes (E, 8)."""
    axes = [np.linspace(0.0, L, k + 1) + o for L, k, o in zip(size, n, origin)]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return P, _hexes(np.arange(P.shape[0]).reshape(tuple(k + 1 for k in n)))


def on_boundary(P, lo, hi):
    return np.any(np.isclose(P, lo) | np.isclose(P, hi), axis=1)


def distorted_box(seed=3, n=(3, 3, 3), size=10.0, amplitude=0.3):
    """A box with its interior nodes moved randomly by up to ``amplitude`` element sizes."""
    rng = np.random.default_rng(seed)
    P, H = box(n, (size,) * 3)
    bnd = np.flatnonzero(on_boundary(P, 0.0, size))
    inner = np.setdiff1d(np.arange(P.shape[0]), bnd)
    P[inner] += rng.uniform(-1, 1, (inner.size, 3)) * amplitude * size / max(n)
    return P, H, bnd, inner


def annulus(nr, nt, a=10.0, b=20.0, h=2.0, nz=1):
    """Full structured annulus a <= r <= b, periodic in theta, ``nz`` layers of height h/nz.
    Local (r, theta, z) bits map to VTK (x, y, z): e_r x e_theta = e_z, positive Jacobians."""
    r, t, z = np.linspace(a, b, nr + 1), np.linspace(0, 2 * np.pi, nt + 1)[:-1], np.linspace(0, h, nz + 1)
    R, T, Z = np.meshgrid(r, t, z, indexing="ij")
    P = np.stack([R * np.cos(T), R * np.sin(T), Z], -1).reshape(-1, 3)
    ids = np.arange(P.shape[0]).reshape(nr + 1, nt, nz + 1)
    return P, _hexes(np.concatenate([ids, ids[:, :1]], axis=1))


def _rows(nodes, normal, value):
    nodes = np.asarray(nodes)
    return nodes, np.tile(normal, (nodes.size, 1)), np.full(nodes.size, float(value))


def _sliding(*groups):
    """Concatenate sliding rows ``(nodes, normals, values)``."""
    return tuple(np.concatenate(parts) for parts in zip(*groups))


# ------------------------------------------------------------------------ patch test
PATCH_MATERIALS = {
    "iso-0.3": LinearElastic(0.003, 0.3),
    "iso-0.47": LinearElastic(0.003, 0.47),
    "iso-0.4999": LinearElastic(0.003, 0.4999),
    "ti-lip-muscle": TransverselyIsotropic(),
    "neo-hookean-0.47": NeoHookean(0.003, 0.47),
    "neo-hookean-0.4999": NeoHookean(0.003, 0.4999),
}


@pytest.mark.parametrize("name", list(PATCH_MATERIALS))
def test_patch_test_distorted_hexahedra(name):
    """Patch test: a linear displacement u = G X + c has a uniform strain and stress in a
    homogeneous body, which is in equilibrium with no body force; prescribing it on the
    boundary of a mesh of distorted hexahedra, the interior nodes must reproduce it
    exactly (consistency of the element, including the mean-dilatation split on
    distorted elements and, for Neo-Hookean, a homogeneous deformation with |G| ~ 10%).
    Tolerance 1e-10 of max |u|: round-off amplified by the condition number (lam/mu
    ~ 5e3 at nu = 0.4999) stays below 1e-13 here; Newton stops at rtol 1e-10."""
    rng = np.random.default_rng(7)
    P, H, bnd, inner = distorted_box()
    fibre = np.tile(rng.normal(size=3), (H.shape[0], 1))  # one direction: a homogeneous material
    mesh = Mesh(P, {"hex8": H}, cell_data={"fibre_direction": fibre / np.linalg.norm(fibre[0])})
    assert mesh.scaled_jacobian().min() < 0.9  # really distorted
    G = rng.uniform(-0.1, 0.1, (3, 3))
    U = P @ G.T + rng.uniform(-1, 1, 3)
    problem = StaticProblem(mesh, MaterialAssignment(PATCH_MATERIALS[name]), rtol=1e-10)
    sol = problem.solve(Constraints(P.shape[0], bnd, U[bnd]))
    err = np.abs(sol.displacement[inner] - U[inner]).max() / np.abs(U).max()
    assert err < 1e-10
    # the interior carries no force: the residual vanishes there
    assert np.abs(sol.residual.reshape(-1, 3)[inner]).max() < 1e-10 * np.abs(sol.residual).max()


# ------------------------------------------------------- assembled force and tangent
@pytest.mark.parametrize("sri", [True, False], ids=["mean-dilatation", "full"])
def test_neo_hookean_assembly_is_consistent(sri):
    """Hyperelastic consistency of the assembled system on distorted hexahedra at a random
    finite displacement: the internal force is the gradient of the total energy and the
    tangent the derivative of the force (central differences, h = 1e-6 mm: truncation
    and round-off ~1e-9 relative, tolerance 1e-7), the tangent is symmetric (1e-12), and
    at u = 0 the force vanishes and the tangent equals the small-strain stiffness of the
    same E, nu (1e-12): the mean-dilatation split is the same in both."""
    rng = np.random.default_rng(0)
    P, H, _, _ = distorted_box(seed=2, n=(2, 2, 2))
    mesh = Mesh(P, {"hex8": H})
    groups = MaterialAssignment(NeoHookean(0.003, 0.47)).groups(mesh)
    kin = kinematics(mesh, mean_dilatation=sri)
    pattern = SparsePattern(kin.conn, P.shape[0])
    u = rng.uniform(-0.5, 0.5, P.shape)
    f, K = neo_hookean_system(kin, u, groups, pattern)
    K = K.toarray()
    h = 1e-6
    f_fd, K_fd = np.zeros(u.size), np.zeros((u.size, u.size))
    for i in range(u.size):
        du = np.zeros(u.size)
        du[i] = h
        up, um = u + du.reshape(-1, 3), u - du.reshape(-1, 3)
        f_fd[i] = (neo_hookean_energy(kin, up, groups) - neo_hookean_energy(kin, um, groups)) / (2 * h)
        K_fd[:, i] = (neo_hookean_system(kin, up, groups, pattern, tangent=False)[0]
                      - neo_hookean_system(kin, um, groups, pattern, tangent=False)[0]) / (2 * h)
    assert np.abs(f - f_fd).max() < 1e-7 * np.abs(f).max()
    assert np.abs(K - K_fd).max() < 1e-7 * np.abs(K).max()
    assert np.abs(K - K.T).max() < 1e-12 * np.abs(K).max()
    f0, K0 = neo_hookean_system(kin, np.zeros_like(u), groups, pattern)
    D, lam = MaterialAssignment(LinearElastic(0.003, 0.47)).voigt(mesh)
    K_lin = linear_stiffness(kin, D, lam, pattern).toarray()
    assert np.abs(f0).max() == 0.0
    assert np.abs(K0.toarray() - K_lin).max() < 1e-12 * np.abs(K_lin).max()


# --------------------------------------------------------------- Lame thick cylinder
A_IN, B_OUT, DELTA, E_LAME = 10.0, 20.0, 0.1, 0.003


def _lame_exact(r, nu):
    """Plane-strain Lame: u_r = A r + B / r with u_r(a) = delta and sigma_rr(b) = 0."""
    lam, mu = lame(E_LAME, nu)
    A = DELTA / (A_IN + (lam + mu) * B_OUT**2 / (mu * A_IN))
    B = (lam + mu) * A * B_OUT**2 / mu
    return A * r + B / r, 2 * (lam + mu) * A - 2 * mu * B / r**2


def _lame_solve(nr, nt, nu, sri=True):
    """The annulus with u = delta e_r on the inner face, u_z = 0 everywhere (plane strain:
    sliding rows of normal e_z on every other node), outer face free. Returns points,
    displacement (n, 3) and element-average strains (E, 3, 3); ``sri=False`` integrates
    the volumetric part with the full 2x2x2 rule."""
    P, H = annulus(nr, nt)
    mesh = Mesh(P, {"hex8": H})
    r = np.hypot(P[:, 0], P[:, 1])
    inner = np.flatnonzero(np.isclose(r, A_IN))
    rest = np.setdiff1d(np.arange(P.shape[0]), inner)
    c = Constraints(P.shape[0], inner, DELTA * P[inner] * [1, 1, 0] / A_IN, *_rows(rest, [0, 0, 1.0], 0.0))
    problem = StaticProblem(mesh, MaterialAssignment(LinearElastic(E_LAME, nu)), solver="superlu")
    if sri:
        u = problem.solve(c).displacement
    else:
        D, lam = problem.materials.voigt(mesh)
        K = linear_stiffness(kinematics(mesh, mean_dilatation=False), D, lam, problem.pattern)
        T, u0 = c.reduction()
        v, _ = solve((T.T @ K @ T).tocsr(), -(T.T @ (K @ u0)), method="superlu")
        u = (T @ v + u0).reshape(-1, 3)
    return P, H, u, small_strain(problem.kin, u)


@pytest.mark.parametrize("nu", [0.3, 0.47])
def test_lame_cylinder_converges_at_second_order(nu):
    """Lame's thick-walled cylinder in plane strain (a = 10, b = 20 mm, inner wall pushed
    out by delta = 0.1 mm, outer wall free): u_r = A r + B / r. Trilinear hexahedra
    converge at O(h^2) in the nodal displacement: the log-log slope of the max nodal
    radial error over (n_r, n_theta) = (2, 12), (4, 24), (8, 48) is 2 +/- 0.3. The finest
    error is bounded by delta (1 - cos(pi / n_theta)), the relative sagitta of the
    polygonal circle, i.e. the size of the geometric discretisation error. Axisymmetry:
    no tangential displacement (1e-12 mm) and u_z = 0 exactly."""
    errors, h = [], []
    for nr, nt in [(2, 12), (4, 24), (8, 48)]:
        P, _, u, _ = _lame_solve(nr, nt, nu)
        r = np.hypot(P[:, 0], P[:, 1])
        ur = (u[:, 0] * P[:, 0] + u[:, 1] * P[:, 1]) / r
        ut = (-u[:, 0] * P[:, 1] + u[:, 1] * P[:, 0]) / r
        errors.append(np.abs(ur - _lame_exact(r, nu)[0]).max())
        h.append((B_OUT - A_IN) / nr)
        assert np.abs(ut).max() < 1e-12
        assert np.abs(u[:, 2]).max() == 0.0
    slope = np.polyfit(np.log(h), np.log(errors), 1)[0]
    assert slope == pytest.approx(2.0, abs=0.3)
    assert errors[-1] < DELTA * (1 - np.cos(np.pi / 48))


def test_lame_nearly_incompressible_mean_dilatation_vs_locking():
    """Volumetric locking at nu = 0.4999 (lam / mu = 5e3): the mean-dilatation element
    gets the outer-wall displacement of Lame's solution within 1e-3 (relative) on the
    (4, 24) mesh and the radial stress at the element centres within 5% of
    sigma_rr(a); the fully integrated element (volumetric part at 2x2x2 points)
    over-constrains the dilatation: its displacement error is > 100 times larger and its
    stress, where lam amplifies the spurious dilatation, is off by more than 100%."""
    nu = 0.4999
    out = {}
    for sri in (True, False):
        P, H, u, eps = _lame_solve(4, 24, nu, sri)
        r = np.hypot(P[:, 0], P[:, 1])
        outer = np.isclose(r, B_OUT)
        ur = (u[:, 0] * P[:, 0] + u[:, 1] * P[:, 1]) / r
        ur_exact = _lame_exact(B_OUT, nu)[0]
        lam, mu = lame(E_LAME, nu)
        sig = 2 * mu * eps + lam * np.trace(eps, axis1=1, axis2=2)[:, None, None] * np.eye(3)
        xc = P[H].mean(axis=1)
        rc = np.hypot(xc[:, 0], xc[:, 1])
        er = xc[:, :2] / rc[:, None]
        srr = np.einsum("ei,eij,ej->e", er, sig[:, :2, :2], er)
        srr_exact = _lame_exact(rc, nu)[1]
        out[sri] = (np.abs(ur[outer] - ur_exact).max() / ur_exact,
                    np.abs(srr - srr_exact).max() / abs(_lame_exact(A_IN, nu)[1]))
    assert out[True][0] < 1e-3 and out[True][1] < 0.05
    assert out[False][0] > 100 * out[True][0]
    assert out[False][1] > 1.0


@pytest.mark.parametrize("nu", [0.47, 0.4999])
def test_linear_solvers_agree_on_lame(nu):
    """The direct (SuperLU, CHOLMOD when installed) and iterative (smoothed-aggregation AMG
    preconditioned CG with the rigid-body modes, relative residual 1e-9) solvers give the
    same Lame displacement on the (8, 48) x 2-layer annulus (~2,600 unknowns, beyond AMG's
    direct coarse level): within 1e-5 delta, the CG tolerance times the conditioning
    (lam / mu up to 5e3 at nu = 0.4999)."""
    P, H = annulus(8, 48, nz=2)
    r = np.hypot(P[:, 0], P[:, 1])
    inner = np.flatnonzero(np.isclose(r, A_IN))
    rest = np.setdiff1d(np.arange(P.shape[0]), inner)
    c = Constraints(P.shape[0], inner, DELTA * P[inner] * [1, 1, 0] / A_IN, *_rows(rest, [0, 0, 1.0], 0.0))
    methods = ["superlu", "amg"]
    try:
        import sksparse.cholmod  # noqa: F401
        methods.append("cholmod")
    except ImportError:
        pass
    u, info = {}, {}
    for method in methods:
        sol = StaticProblem(Mesh(P, {"hex8": H}), MaterialAssignment(LinearElastic(E_LAME, nu)), method).solve(c)
        u[method], info[method] = sol.displacement, sol.solves[0]
        assert info[method].method == method and info[method].residual < 1e-8
    assert info["amg"].iterations > 1  # really iterative, not only the coarse direct solve
    for method in methods[1:]:
        np.testing.assert_allclose(u[method], u["superlu"], rtol=0, atol=1e-5 * DELTA)


# ------------------------------------------------------------ Neo-Hookean uniaxial
@pytest.mark.parametrize("stretch", [1.3, 0.8])
def test_neo_hookean_uniaxial_stretch(stretch):
    """Uniaxial stress of the compressible Neo-Hookean solid: F = diag(s, l, l) with the
    lateral stress P22 = mu (l - 1/l) + lam ln(s l^2) / l = 0, i.e.
    mu (l^2 - 1) + lam ln(s l^2) = 0, and the nominal stress P11 = mu (s - 1/s) + lam ln J / s.
    A 10 mm cube on symmetry planes (x = 0, y = 0, z = 0 sliding; edges carry two rows;
    corners on three planes prescribed) with x = L moved to s L: the homogeneous state is
    the exact discrete solution, so the lateral stretch and the reaction on x = L
    (= P11 A0) match to rel 1e-6 (Newton rtol 1e-10)."""
    L = 10.0
    mat = NeoHookean(0.003, 0.47)
    P, H = box((2, 2, 2), (L, L, L))
    n = P.shape[0]
    x0, xL = np.isclose(P[:, 0], 0), np.isclose(P[:, 0], L)
    y0, z0 = np.isclose(P[:, 1], 0), np.isclose(P[:, 2], 0)
    corner = (x0 | xL) & y0 & z0
    rows = _sliding(_rows(np.flatnonzero(x0 & ~corner), [1.0, 0, 0], 0.0),
                    _rows(np.flatnonzero(xL & ~corner), [1.0, 0, 0], (stretch - 1) * L),
                    _rows(np.flatnonzero(y0 & ~corner), [0, 1.0, 0], 0.0),
                    _rows(np.flatnonzero(z0 & ~corner), [0, 0, 1.0], 0.0))
    corners = np.flatnonzero(corner)
    c = Constraints(n, corners, np.outer(P[corners, 0] / L, [(stretch - 1) * L, 0, 0]), *rows)
    sol = StaticProblem(Mesh(P, {"hex8": H}), MaterialAssignment(mat), rtol=1e-10).solve(c)

    l2 = brentq(lambda l: mat.mu * (l**2 - 1) + mat.lam * np.log(stretch * l**2), 0.5, 1.5)
    J = stretch * l2**2
    P11 = mat.mu * (stretch - 1 / stretch) + mat.lam * np.log(J) / stretch
    exact = P * [stretch - 1, l2 - 1, l2 - 1]
    np.testing.assert_allclose(sol.displacement, exact, rtol=0, atol=1e-6 * np.abs(exact).max())
    assert 1 + sol.displacement[np.isclose(P[:, 1], L), 1].mean() / L == pytest.approx(l2, rel=1e-6)
    force = sol.residual.reshape(-1, 3)[xL, 0].sum()
    assert force == pytest.approx(P11 * L * L, rel=1e-6)
    assert np.sign(force) == np.sign(stretch - 1)  # tension pulls, compression pushes


# ------------------------------------------------------------------------ rigid motion
def test_linear_small_rigid_motion_is_strain_free():
    """A linearised rigid motion u = w x X + c has a skew displacement gradient, hence
    zero small strain and zero stress: prescribed on the boundary of a distorted block,
    the interior follows it (1e-10 of max |u|) and every element strain vanishes
    (1e-10 of |w|)."""
    rng = np.random.default_rng(11)
    P, H, bnd, inner = distorted_box(seed=5)
    w, c = rng.uniform(-0.01, 0.01, 3), rng.uniform(-0.5, 0.5, 3)
    U = np.cross(w, P) + c
    problem = StaticProblem(Mesh(P, {"hex8": H}), MaterialAssignment(LinearElastic(0.003, 0.47)))
    sol = problem.solve(Constraints(P.shape[0], bnd, U[bnd]))
    assert np.abs(sol.displacement[inner] - U[inner]).max() < 1e-10 * np.abs(U).max()
    assert np.abs(small_strain(problem.kin, sol.displacement)).max() < 1e-10 * np.abs(w).max()
    assert np.abs(sol.residual).max() < 1e-12 * np.abs(problem.stiffness).max() * np.abs(U).max()


def _rotated_box_field(P, angle_deg, stretch):
    """u = R F0 (X - c) + c + t - X: a rotation by ``angle_deg`` about a tilted axis of the
    homogeneous deformation ``F0 = stretch``, plus a translation."""
    axis = np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
    R = Rotation.from_rotvec(np.deg2rad(angle_deg) * axis).as_matrix()
    centre = P.mean(axis=0)
    return (P - centre) @ (R @ stretch).T + centre + [1.0, -2.0, 0.5] - P


def _green_lagrange(mesh, u):
    kin = kinematics(mesh)
    F = np.eye(3) + np.einsum("eai,eqaj->eqij", u[kin.conn], kin.grad)
    return 0.5 * (np.swapaxes(F, -1, -2) @ F - np.eye(3))


def test_neo_hookean_large_rotation_of_a_stretch():
    """Objectivity: a homogeneous deformation F0 (a few % stretch and shear) followed by a
    60 degree rotation about a tilted axis, prescribed on the boundary of a distorted
    block, is an exact Neo-Hookean equilibrium (F = R F0 uniform): the interior nodes
    follow it (1e-8 of max |u|) and the Green-Lagrange strain is that of F0 alone,
    (F0^T F0 - I) / 2, at every Gauss point (1e-8): the rotation adds no strain. (A
    small-strain model would see a spurious strain of order 1 - cos 60 = 0.5.)"""
    P, H, bnd, inner = distorted_box(seed=9, amplitude=0.2)
    F0 = np.array([[1.05, 0.03, 0.0], [0.0, 0.97, 0.0], [0.0, 0.0, 1.02]])
    U = _rotated_box_field(P, 60.0, F0)
    mesh = Mesh(P, {"hex8": H})
    problem = StaticProblem(mesh, MaterialAssignment(NeoHookean(0.003, 0.47)), rtol=1e-10)
    sol = problem.solve(Constraints(P.shape[0], bnd, U[bnd]))
    assert np.abs(sol.displacement[inner] - U[inner]).max() < 1e-8 * np.abs(U).max()
    green = _green_lagrange(mesh, sol.displacement)
    np.testing.assert_allclose(green, np.broadcast_to(0.5 * (F0.T @ F0 - np.eye(3)), green.shape), rtol=0, atol=1e-8)
    assert np.abs(sol.residual.reshape(-1, 3)[inner]).max() < 1e-8 * np.abs(sol.residual).max()


def test_neo_hookean_pure_rigid_rotation_converges():
    """A pure 60 degree rotation plus translation, prescribed on the boundary, is the
    stress-free equilibrium: the solver must return it (interior within 1e-8 of max |u|,
    Green-Lagrange strain < 1e-8). The linear predictor already lands on it exactly (the
    prescribed field is linear in X), so any converged Newton must accept it."""
    P, H, bnd, inner = distorted_box(seed=9, amplitude=0.2)
    U = _rotated_box_field(P, 60.0, np.eye(3))
    mesh = Mesh(P, {"hex8": H})
    sol = StaticProblem(mesh, MaterialAssignment(NeoHookean(0.003, 0.47))).solve(Constraints(P.shape[0], bnd, U[bnd]))
    assert np.abs(sol.displacement[inner] - U[inner]).max() < 1e-8 * np.abs(U).max()
    assert np.abs(_green_lagrange(mesh, sol.displacement)).max() < 1e-8


# ----------------------------------------------------------------- frictionless sliding
def test_block_slides_on_frictionless_plane():
    """A block on the frictionless plane z = 0 (sliding rows: n . u = 0, tangents free)
    with its top moved by (d, 0, -delta): by linearity the answer is the rigid translation
    d e_x (stress free, admissible) plus the compression of the block, which is odd about
    the mid-plane x = L/2 by symmetry; so the bottom nodes stay on the plane (1e-12 mm),
    slide with mean u_x = d (1e-9 mm) and mean u_y = 0, every one of them moves
    (|u_x| > d/2: not stuck), the plane pushes up (total normal reaction > 0, balancing the
    top's), and a frictionless plane exerts no tangential force (1e-9 of the normal one)."""
    L, Hh, d, delta = 10.0, 5.0, 0.5, 0.1
    P, H = box((4, 4, 2), (L, L, Hh))
    bottom, top = np.flatnonzero(np.isclose(P[:, 2], 0)), np.flatnonzero(np.isclose(P[:, 2], Hh))
    c = Constraints(P.shape[0], top, np.tile([d, 0.0, -delta], (top.size, 1)), *_rows(bottom, [0, 0, 1.0], 0.0))
    sol = StaticProblem(Mesh(P, {"hex8": H}), MaterialAssignment(LinearElastic(0.003, 0.47))).solve(c)
    u = sol.displacement
    assert np.abs(u[bottom, 2]).max() < 1e-12
    assert u[bottom, 0].mean() == pytest.approx(d, abs=1e-9)
    assert abs(u[bottom, 1].mean()) < 1e-9
    assert u[bottom, 0].min() > d / 2
    r = sol.residual.reshape(-1, 3)
    normal = c.forces(sol.residual)["sliding"]
    assert normal.sum() > 0 and np.all(normal > -1e-12)
    assert r[bottom, 2].sum() == pytest.approx(-r[top, 2].sum(), rel=1e-9)
    assert np.abs(r[bottom, :2]).max() < 1e-9 * normal.sum()


def test_sliding_on_tilted_plane_admits_tangential_translation():
    """Sliding rows with a general normal n and value g confine a node to the plane
    n . u = g. A block whose bottom slides on a tilted plane and whose top is translated
    by t + g n (t tangent to the plane) has the stress-free rigid translation as its exact
    answer: every node moves by t + g n (1e-12 mm) and no force is needed (1e-12 N
    relative to the stiffness times the motion)."""
    L = 10.0
    P, H = box((2, 2, 2), (L, L, L))
    n = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    t = np.cross(n, [1.0, 0.0, 0.0])
    g = 0.25
    shift = 0.7 * t / np.linalg.norm(t) + g * n
    bottom, top = np.flatnonzero(np.isclose(P[:, 2], 0)), np.flatnonzero(np.isclose(P[:, 2], L))
    c = Constraints(P.shape[0], top, np.tile(shift, (top.size, 1)), *_rows(bottom, n, g))
    problem = StaticProblem(Mesh(P, {"hex8": H}), MaterialAssignment(LinearElastic(0.003, 0.47)))
    sol = problem.solve(c)
    np.testing.assert_allclose(sol.displacement, np.tile(shift, (P.shape[0], 1)), rtol=0, atol=1e-12)
    assert np.abs(sol.residual).max() < 1e-12 * np.abs(problem.stiffness).max()


# ----------------------------------------------------------------------- lip contact
def _two_blocks(n=(3, 3, 2), size=(10.0, 10.0, 4.0), gap=0.0):
    """Two stacked blocks, the upper one ``gap`` mm above the lower one, with distinct
    interface nodes (coincident when gap = 0). Returns points, hexes, lower-bottom,
    upper-top, slaves (upper bottom), masters (lower top, paired with the slaves)."""
    P1, H1 = box(n, size)
    P2, H2 = box(n, size, origin=(0, 0, size[2] + gap))
    m = P1.shape[0]
    P, H = np.vstack([P1, P2]), np.vstack([H1, H2 + m])
    masters = np.flatnonzero(np.isclose(P1[:, 2], size[2]))
    slaves = m + np.flatnonzero(np.isclose(P2[:, 2], size[2] + gap))
    assert np.allclose(P[slaves] - [0, 0, gap], P[masters])
    bottom = np.flatnonzero(np.isclose(P1[:, 2], 0))
    top = m + np.flatnonzero(np.isclose(P2[:, 2], 2 * size[2] + gap))
    return P, H, bottom, top, slaves, masters


def _stacked(gap=0.0):
    P, H, bottom, top, slaves, masters = _two_blocks(gap=gap)
    problem = StaticProblem(Mesh(P, {"hex8": H}), MaterialAssignment(LinearElastic(0.003, 0.47)))

    def run(top_u):
        presc = np.concatenate([bottom, top])
        vals = np.vstack([np.zeros((bottom.size, 3)), np.tile(top_u, (top.size, 1))])
        return solve_with_lip_contact(problem, Constraints(P.shape[0], presc, vals), slaves, masters)

    return SimpleNamespace(points=P, slaves=slaves, masters=masters, run=run)


@pytest.fixture(scope="module")
def stacked():
    return _stacked()


def test_lip_contact_compression_keeps_pairs_tied(stacked):
    """Pushing the upper block down into the lower one (clamped bottom): every pair stays
    in contact (no tension, no interpenetration: gap >= -1e-9 mm), the contact forces
    are compressive, and the two identical blocks are mirror images about the interface
    (after a rigid shift by -delta/2), so the interface sinks by exactly delta/2 and the
    faces do not slide relative to each other (1e-9 mm)."""
    slaves, masters = stacked.slaves, stacked.masters
    delta = 0.4
    res = stacked.run([0.0, 0.0, -delta])
    u = res.solution.displacement
    assert res.active.all()
    assert res.gaps.min() >= -1e-9 and res.max_penetration <= 1e-9
    np.testing.assert_allclose(u[slaves, 2], -delta / 2, atol=1e-9)
    np.testing.assert_allclose(u[slaves, :2], u[masters, :2], atol=1e-9)
    force = res.solution.residual.reshape(-1, 3)[slaves, 2]  # > 0: pushes the upper lip up
    assert force.sum() > 0


def test_lip_contact_pull_releases_every_pair(stacked):
    """Pulling the upper block up: the ties would pull, so every pair is released (active
    set), the lower block is unloaded (u = 0 up to round-off) and the upper one, held by
    its top face only, translates rigidly: the faces separate by exactly the pull."""
    P = stacked.points
    delta = 0.3
    res = stacked.run([0.0, 0.0, delta])
    u = res.solution.displacement
    assert not res.active.any()
    lower = np.arange(P.shape[0] // 2)
    upper = np.arange(P.shape[0] // 2, P.shape[0])
    assert np.abs(u[lower]).max() < 1e-12
    np.testing.assert_allclose(u[upper], np.tile([0.0, 0.0, delta], (upper.size, 1)), atol=1e-12)
    np.testing.assert_allclose(res.gaps, delta, atol=1e-12)


def test_neo_hookean_lip_contact_pull_releases_every_pair():
    """Same pull as above with Neo-Hookean blocks: released pairs, the lower block at rest
    and the upper block lifted rigidly (1e-9 mm) are the exact answer for any material."""
    P, H, bottom, top, slaves, masters = _two_blocks()
    problem = StaticProblem(Mesh(P, {"hex8": H}), MaterialAssignment(NeoHookean(0.003, 0.47)))
    vals = np.vstack([np.zeros((bottom.size, 3)), np.tile([0, 0, 0.3], (top.size, 1))])
    res = solve_with_lip_contact(problem, Constraints(P.shape[0], np.concatenate([bottom, top]), vals), slaves, masters)
    assert not res.active.any()
    u = res.solution.displacement
    np.testing.assert_allclose(u[P.shape[0] // 2:], np.tile([0, 0, 0.3], (P.shape[0] // 2, 1)), atol=1e-9)


def test_lip_contact_shear_slides_tangentially(stacked):
    """Top of the upper block moved sideways by d while pressed down by delta: the
    frictionless contact transmits no shear, so the answer is the compression (mirror
    symmetric, no relative sliding) plus a rigid translation d of the upper block: every
    slave slides past its master by exactly d in x (1e-9 mm) with zero gap."""
    slaves, masters = stacked.slaves, stacked.masters
    d, delta = 0.8, 0.2
    res = stacked.run([d, 0.0, -delta])
    u = res.solution.displacement
    assert res.active.all()
    np.testing.assert_allclose(res.gaps, 0.0, atol=1e-9)
    np.testing.assert_allclose(u[slaves, 0] - u[masters, 0], d, atol=1e-9)
    np.testing.assert_allclose(u[slaves, 1] - u[masters, 1], 0.0, atol=1e-9)


def test_lip_contact_closes_an_initial_gap():
    """Blocks 0.5 mm apart (beyond the 0.2 mm detection threshold: no pair active at
    first), upper top pushed down by 1 mm: the upper block first moves rigidly by the gap,
    then the pairs that would interpenetrate are activated and the remaining 0.5 mm is
    shared by the two identical blocks (mirror symmetry): master u_z = -0.25 mm, slave
    u_z = -0.75 mm, gap closed to within the active-set tolerance (1e-6 mm)."""
    gap, delta = 0.5, 1.0
    blocks = _stacked(gap)
    slaves, masters = blocks.slaves, blocks.masters
    res = blocks.run([0.0, 0.0, -delta])
    u = res.solution.displacement
    assert res.active.all() and res.iterations >= 2
    assert res.max_penetration <= 1e-6
    np.testing.assert_allclose(res.gaps, 0.0, atol=1e-9)
    np.testing.assert_allclose(u[masters, 2], -(delta - gap) / 2, atol=1e-9)
    np.testing.assert_allclose(u[slaves, 2], -(delta - gap) / 2 - gap, atol=1e-9)


# ------------------------------------------------------------------------- Newton
def test_neo_hookean_block_compressed_40_percent_in_one_load():
    """Robustness of Newton with line search and load sub-stepping: a Neo-Hookean cube
    (nu = 0.47) clamped at the bottom, its top pushed down 40% in a single call, converges;
    the compressed mesh has only positive Jacobians, the top carries a compressive
    reaction balanced by the bottom's (1e-8 relative, equilibrium), and the material
    bulges (the mid-height side moves outwards) as a nearly incompressible solid must."""
    L = 10.0
    P, H = box((3, 3, 3), (L, L, L))
    bottom, top = np.flatnonzero(np.isclose(P[:, 2], 0)), np.flatnonzero(np.isclose(P[:, 2], L))
    mesh = Mesh(P, {"hex8": H})
    c = Constraints(P.shape[0], np.concatenate([bottom, top]),
                    np.vstack([np.zeros((bottom.size, 3)), np.tile([0, 0, -0.4 * L], (top.size, 1))]))
    sol = StaticProblem(mesh, MaterialAssignment(NeoHookean(0.003, 0.47))).solve(c)
    assert mesh.translated(sol.displacement).scaled_jacobian().min() > 0
    r = sol.residual.reshape(-1, 3)
    assert r[top, 2].sum() < 0
    assert r[top, 2].sum() == pytest.approx(-r[bottom, 2].sum(), rel=1e-8)
    side = np.isclose(P[:, 0], L) & ~np.isin(np.arange(P.shape[0]), np.concatenate([bottom, top]))
    assert sol.displacement[side, 0].min() > 0
