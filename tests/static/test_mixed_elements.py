"""Static FEM on wedges and on meshes that mix hexahedra, wedges and tetrahedra, against
closed forms: patch tests on distorted meshes, hyperelastic consistency of the assembled
force and tangent, convergence to Lame's cavity field, a bimaterial bar whose stiff
region spans the three blocks. float64; units mm, MPa, N."""

import numpy as np
import pytest

from toolkit.common.fem import reference_element
from toolkit.common.fem.assembly import SparsePattern
from toolkit.common.fem.materials import LinearElastic, NeoHookean, TransverselyIsotropic
from toolkit.common.meshes.mesh import Mesh, MeshError
from toolkit.common.meshes.topology import triangulated_boundary, wedges_from_hexes
from toolkit.common.phantoms.mixed_bar import mixed_bar
from toolkit.static.constraints import Constraints
from toolkit.static.problem import ConvergenceError, StaticProblem
from toolkit.static.stiffness import (
    MaterialAssignment,
    kinematics,
    linear_stiffness,
    neo_hookean_energy,
    neo_hookean_system,
)

PATCH_MATERIALS = {
    "iso-0.3": LinearElastic(0.003, 0.3),
    "iso-0.47": LinearElastic(0.003, 0.47),
    "iso-0.4999": LinearElastic(0.003, 0.4999),
    "ti-lip-muscle": TransverselyIsotropic(),
    "neo-hookean-0.47": NeoHookean(0.003, 0.47),
    "neo-hookean-0.4999": NeoHookean(0.003, 0.4999),
}


def wedge_box(n=3, size=10.0, amplitude=0.3, seed=3) -> Mesh:
    """A cube of ``2 n^3`` wedges (each grid cube cut in two) with its interior nodes moved
    randomly by up to ``amplitude`` cell sizes."""
    s = np.linspace(0.0, size, n + 1)
    P = np.stack(np.meshgrid(s, s, s, indexing="ij"), -1).reshape(-1, 3)
    ids = np.arange(P.shape[0]).reshape((n + 1,) * 3)
    corners = np.empty((n, n, n, 2, 2, 2), dtype=np.int64)
    for a in (0, 1):
        for b in (0, 1):
            for d in (0, 1):
                corners[..., a, b, d] = ids[a:n + a, b:n + b, d:n + d]
    inner = np.flatnonzero(np.all((P > 0) & (P < size), axis=1))
    P[inner] += np.random.default_rng(seed).uniform(-1, 1, (inner.size, 3)) * amplitude * size / n
    return Mesh(P, {"wedge6": wedges_from_hexes(corners.reshape(-1, 2, 2, 2), P)})


def _patch(mesh: Mesh, material, seed=7) -> tuple[float, float]:
    """Prescribe u = G X + c on the boundary; return the interior error relative to max |u|
    and the largest interior residual relative to the largest reaction."""
    rng = np.random.default_rng(seed)
    P = mesh.points
    fibre = np.tile(rng.normal(size=3), (mesh.n_cells, 1))  # one direction: a homogeneous material
    mesh = mesh.with_cell_data(fibre_direction=fibre / np.linalg.norm(fibre[0]))
    G = rng.uniform(-0.1, 0.1, (3, 3))
    U = P @ G.T + rng.uniform(-1, 1, 3)
    bnd = np.unique(triangulated_boundary(mesh.cells))
    inner = np.setdiff1d(np.arange(mesh.n_points), bnd)
    assert inner.size
    sol = StaticProblem(mesh, MaterialAssignment(material), rtol=1e-10).solve(Constraints(mesh.n_points, bnd, U[bnd]))
    err = np.abs(sol.displacement[inner] - U[inner]).max() / np.abs(U).max()
    force = np.abs(sol.residual.reshape(-1, 3)[inner]).max() / np.abs(sol.residual).max()
    return err, force


@pytest.mark.parametrize("name", list(PATCH_MATERIALS))
def test_patch_test_distorted_wedges(name):
    """Patch test on distorted wedges: a linear displacement u = G X + c (uniform strain,
    |G| ~ 10%, in equilibrium without body force) prescribed on the boundary is reproduced
    at the interior nodes to 1e-10 of max |u|, with no force there: isotropic at nu = 0.3,
    0.47 and 0.4999 with the mean-dilatation split (exact on distorted wedges because the
    averaged gradients still give the exact uniform dilatation), the lip-sliding paper's transversely
    isotropic lip muscle, and Neo-Hookean (a homogeneous finite deformation)."""
    mesh = wedge_box()
    assert mesh.scaled_jacobian().min() < 0.7  # really distorted (ideal cut-cube wedge: 0.82)
    assert kinematics(mesh).blocks[0].sri
    err, force = _patch(mesh, PATCH_MATERIALS[name])
    assert err < 1e-10 and force < 1e-10


@pytest.mark.parametrize("name", list(PATCH_MATERIALS))
def test_patch_test_mixed_blocks(name):
    """The same patch test on a distorted mesh of hex8, wedge6 and tet4 blocks meeting on
    conforming quad (hex-wedge) and triangle (wedge-tet) interfaces: one assembled system
    over the three blocks reproduces the uniform strain exactly (1e-10)."""
    mesh = mixed_bar(2, jitter=0.5, seed=1)
    assert mesh.scaled_jacobian().min() < 0.5
    err, force = _patch(mesh, PATCH_MATERIALS[name])
    assert err < 1e-10 and force < 1e-10


@pytest.mark.parametrize("sri", [True, False], ids=["mean-dilatation", "full"])
def test_neo_hookean_assembly_is_consistent_on_mixed_blocks(sri):
    """Hyperelastic consistency over hex8 + wedge6 + tet4 blocks at a random finite
    displacement: the internal force is the gradient of the total energy and the tangent
    the derivative of the force (central differences on 40 random dofs, h = 1e-6 mm,
    tolerance 1e-7 relative), the tangent is symmetric (1e-12), and at u = 0 it equals the
    small-strain stiffness with the same split (1e-12)."""
    rng = np.random.default_rng(0)
    mesh = mixed_bar(1, jitter=0.4, seed=2)
    groups = MaterialAssignment(NeoHookean(0.003, 0.47), {"upper": NeoHookean(0.009, 0.45)}).groups(mesh)
    kin = kinematics(mesh, mean_dilatation=sri)
    pattern = SparsePattern(kin.conns, mesh.n_points)
    u = rng.uniform(-0.5, 0.5, mesh.points.shape)
    f, K = neo_hookean_system(kin, u, groups, pattern)
    K = K.toarray()
    h = 1e-6
    for i in rng.choice(u.size, 40, replace=False):
        du = np.zeros(u.size)
        du[i] = h
        up, um = u + du.reshape(-1, 3), u - du.reshape(-1, 3)
        f_fd = (neo_hookean_energy(kin, up, groups) - neo_hookean_energy(kin, um, groups)) / (2 * h)
        K_fd = (neo_hookean_system(kin, up, groups, pattern, tangent=False)[0]
                - neo_hookean_system(kin, um, groups, pattern, tangent=False)[0]) / (2 * h)
        assert abs(f[i] - f_fd) < 1e-7 * np.abs(f).max()
        assert np.abs(K[:, i] - K_fd).max() < 1e-7 * np.abs(K).max()
    assert np.abs(K - K.T).max() < 1e-12 * np.abs(K).max()
    _, K0 = neo_hookean_system(kin, np.zeros_like(u), groups, pattern)
    linear = MaterialAssignment(LinearElastic(0.003, 0.47), {"upper": LinearElastic(0.009, 0.45)})
    K_lin = linear_stiffness(kin, *linear.voigt(mesh), pattern).toarray()
    assert np.abs(K0.toarray() - K_lin).max() < 1e-12 * np.abs(K_lin).max()


#: centre of the spherical cavity, mm (outside the bar, 12 mm from its x = 0 end)
CAVITY_CENTRE = np.array([-12.0, 5.0, 7.5])
CAVITY_B = 20.0  # p a^3 / (4 mu), mm^3


def _cavity(P):
    """Lame's pressurised spherical cavity in an infinite solid: u = B e_r / r^2 with
    B = p a^3 / (4 mu); divergence-free, so the same for every nu."""
    d = P - CAVITY_CENTRE
    return (CAVITY_B / np.linalg.norm(d, axis=1) ** 3)[:, None] * d


def test_mixed_blocks_converge_to_lame_cavity_field():
    """Lame's field around a pressurised spherical cavity, u_r = p a^3 / (4 mu r^2),
    prescribed on the whole boundary of the hex8/wedge6/tet4 bar (20 mm long, 12 to 32 mm
    from the cavity centre; the unique solution inside is the same field). nu = 0.3.
    Linear elements converge at O(h^2) in the nodal displacement: the log-log slope of the
    max nodal error over h = 5, 2.5, 1.25 mm is 2 +/- 0.3 (measured 1.8: the coarsest mesh
    is pre-asymptotic, the last halving gives 2.0), and the finest error is below 0.5% of
    max |u|."""
    errors, h = [], []
    for n in (1, 2, 4):
        mesh = mixed_bar(n, length=20.0)
        U = _cavity(mesh.points)
        bnd = np.unique(triangulated_boundary(mesh.cells))
        u = StaticProblem(mesh, MaterialAssignment(LinearElastic(0.003, 0.3))).solve(
            Constraints(mesh.n_points, bnd, U[bnd])).displacement
        errors.append(np.linalg.norm(u - U, axis=1).max() / np.linalg.norm(U, axis=1).max())
        h.append(5.0 / n)
    slope = np.polyfit(np.log(h), np.log(errors), 1)[0]
    assert slope == pytest.approx(2.0, abs=0.3)
    assert errors[-1] < 5e-3


def test_material_region_spanning_blocks_bimaterial_tension():
    """A bar stretched by strain eps along x, upper layer (z > 5 mm: hexahedra, wedges and
    the tetrahedral flange) three times stiffer than the lower layer, same nu: both layers
    take the same uniform strain (u = eps (x, -nu y, -nu z), compatible because the
    interface normal is z), so the axial force is eps (E1 A1 + E2 A2) with A1 = 50 mm^2
    (below z = 5) and A2 = 75 mm^2 (above) - exact to round-off (1e-10)."""
    mesh = mixed_bar(1)
    blocks_in_upper = {b.ctype for b in mesh.volume_blocks if b.local(mesh.element_set("upper")).size}
    assert blocks_in_upper == {"hex8", "wedge6", "tet4"}
    E1, E2, nu, eps = 0.003, 0.009, 0.45, 0.01
    P = mesh.points
    U = eps * P * [1.0, -nu, -nu]
    ends = np.concatenate([mesh.node_sets["end0"], mesh.node_sets["end1"]])
    problem = StaticProblem(mesh, MaterialAssignment(LinearElastic(E1, nu), {"upper": LinearElastic(E2, nu)}))
    sol = problem.solve(Constraints(mesh.n_points, ends, U[ends]))
    assert np.abs(sol.displacement - U).max() < 1e-10 * np.abs(U).max()
    force = sol.residual.reshape(-1, 3)[mesh.node_sets["end1"], 0].sum()
    assert force == pytest.approx(eps * (E1 * 50.0 + E2 * 75.0), rel=1e-10)


def test_kinematics_per_block_and_global_indices():
    """One kinematics block per volume block, with the quadrature of each type (hex8 8,
    wedge6 6, tet4 1 points) and mean dilatation for hex8 and wedge6; the element volumes
    add up to the bar's 125 mm^2 x 20 mm; single-block accessors name the blocks."""
    mesh = mixed_bar(1, length=20.0)
    kin = kinematics(mesh)
    assert [(b.ctype, b.offset, b.grad.shape[1], b.sri) for b in kin.blocks] == [
        ("hex8", 0, 8, True), ("wedge6", 8, 6, True), ("tet4", 24, 1, False)]
    assert kin.volume.sum() == pytest.approx(125.0 * 20.0, rel=1e-12)
    with pytest.raises(MeshError, match=r"single volume block.*\['hex8', 'wedge6', 'tet4'\]"):
        _ = kin.grad


def test_inverted_wedge_is_refused_by_global_index():
    """A wedge turned inside out (triangles swapped) has det J < 0: the problem refuses
    the configuration and names the element by its global index."""
    mesh = mixed_bar(1)
    cells = dict(mesh.cells)
    wedges = cells["wedge6"].copy()
    wedges[5] = wedges[5][[3, 4, 5, 0, 1, 2]]
    cells["wedge6"] = wedges
    with pytest.raises(ConvergenceError, match=r"first: \[21\]"):
        StaticProblem(Mesh(mesh.points, cells), MaterialAssignment())


def test_regulation_corner_tables_follow_the_reference_records():
    """Mesh regulation's corner tables (corner, three edge ends) give a positive
    determinant on every positive reference cell and cover all its corners, so they agree
    with the node order of the reference records (wedge6: Abaqus C3D6)."""
    from toolkit.static.regulation import CORNERS

    for ctype, table in CORNERS.items():
        ref = reference_element(ctype)
        x = ref.nodes
        det = np.linalg.det(x[table[:, 1:]] - x[table[:, :1]])
        assert (det > 0).all(), ctype
        edges = {tuple(sorted(e)) for e in ref.edges.tolist()}
        assert all(tuple(sorted((c, e))) in edges for c, *ends in table.tolist() for e in ends), ctype
        if ctype not in ("tet4", "tet10"):  # one corner is enough: a corner tetrahedron's Jacobian is constant
            assert sorted(table[:, 0].tolist()) == ref.corners.tolist(), ctype
