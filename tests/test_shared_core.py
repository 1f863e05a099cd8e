"""The two workflows' finite-element paths give the same element stiffness and both pass the
patch test on the tet faces (the hex8 and wedge6 patch tests are in tests/static).

Both map their cells through the shared kinematics (:mod:`toolkit.common.fem.kinematics`).
The static linear path builds stiffness from Voigt B matrices (:mod:`toolkit.static.stiffness`);
the impact workflow integrates finite-strain J2 (:mod:`toolkit.impact.plasticity`) and its
critical time step and quasi-static path use ``element_tangent`` of ``dP/dF``
(:mod:`toolkit.common.fem.assembly`). On the same tet4 and tet10 faces and the same
isotropic material (no yield table, so the J2 material is hyperelastic) the small-strain
limits must agree:

- element matrices: the static ``_block_stiffness`` against the impact ``_element_stiffness``,
  to 1e-12 of the largest entry (round-off); and on distorted hex8, wedge6, tet4 and tet10
  cells, ``element_tangent`` of the isotropic tensor against ``B^T D B``;
- the impact internal force linearised by a central difference with a 1e-6 mm
  displacement against ``K u`` of the static path: the finite-strain terms are quadratic in
  ``u``, so the central difference cancels them up to O(eps^2) ~ 1e-12, and the round-off of
  ``f / eps`` is ~1e-16 / 1e-6 (measured 3e-10 of ``|K u|``); tolerance 1e-7 of ``|K u|``. A
  Poisson's ratio of 0.46 instead of 0.45 in one path moves the element matrices by 0.22.
"""

import os
from unittest import mock

import numpy as np
import pytest
import scipy.sparse as sp

from toolkit.common.fem import TET_EDGES
from toolkit.common.fem.assembly import SparsePattern, add_local, element_tangent
from toolkit.common.fem.jit import HAVE_NUMBA
from toolkit.common.fem.kinematics import deformation_gradient, internal_force, kinematics
from toolkit.common.fem.materials import LinearElastic, NeoHookean, TransverselyIsotropic, isotropic_tangent
from toolkit.common.meshes.mesh import Mesh
from toolkit.common.meshes.topology import triangulated_boundary, wedges_from_hexes
from toolkit.common.phantoms.phantom import block, face_tet
from toolkit.impact.elements import _element_stiffness, tet_kinematics
from toolkit.impact.plasticity import FACE_TABLE, J2Plasticity
from toolkit.static.constraints import Constraints
from toolkit.static.problem import StaticProblem
from toolkit.static.stiffness import MaterialAssignment, _block_stiffness, linear_stiffness

E_MPA, NU = 0.015, 0.45


@pytest.fixture(scope="module", params=[1, 2], ids=["tet4", "tet10"])
def face(request):
    return face_tet("coarse", order=request.param)


def test_element_stiffness_is_the_same_in_both_workflows(face):
    static = kinematics(face)
    D, lam = MaterialAssignment(LinearElastic(E_MPA, NU)).voigt(face)
    K_static = _block_stiffness(static.blocks[0], D, lam)
    material = LinearElastic(E_MPA, NU)
    K_impact = _element_stiffness(tet_kinematics(face), material.lam, material.mu)
    assert K_static.shape == K_impact.shape
    assert np.abs(K_static - K_impact).max() <= 1e-12 * np.abs(K_static).max()


def test_impact_internal_force_linearises_to_the_static_stiffness(face):
    static = kinematics(face)
    D, lam = MaterialAssignment(LinearElastic(E_MPA, NU)).voigt(face)
    K = linear_stiffness(static, D, lam, SparsePattern(static.conns, face.n_points))
    u = np.random.default_rng(0).normal(size=(face.n_points, 3))  # mm, O(1) per node
    kin = tet_kinematics(face)
    material = J2Plasticity(E_MPA, NU, 1e-9, table=None)

    def force(v):
        F = deformation_gradient(kin, v)
        P = material.update(F.reshape(-1, 3, 3), material.initial_state(kin.n_points)).first_piola
        return internal_force(kin, P.reshape(F.shape), face.n_points)

    eps = 1e-6
    linearised = (force(eps * u) - force(-eps * u)) / (2 * eps)
    Ku = (K @ u.reshape(-1)).reshape(-1, 3)
    assert np.abs(linearised - Ku).max() <= 1e-7 * np.abs(Ku).max()


def _boundary_nodes(mesh) -> np.ndarray:
    """Every node on the boundary: the corners of the boundary triangles and, for tet10, the
    mid-edge nodes of their edges."""
    tris = triangulated_boundary(mesh.cells)
    nodes = np.unique(tris)
    if "tet10" in mesh.cells:
        cells, n = mesh.cells["tet10"], mesh.n_points
        cell_edges = np.sort(cells[:, TET_EDGES], axis=2)  # (E, 6, 2), mid-node 4 + k on edge k
        tri_edges = np.sort(tris[:, [[0, 1], [1, 2], [0, 2]]], axis=2).reshape(-1, 2)
        on_boundary = np.isin(cell_edges[..., 0] * n + cell_edges[..., 1], tri_edges[:, 0] * n + tri_edges[:, 1])
        nodes = np.union1d(nodes, cells[:, 4:][on_boundary])
    return nodes


def _linear_field(points, seed=3):
    """A displacement ``u = G X + c`` mm with ``|G| ~ 0.1``: uniform strain, in equilibrium."""
    rng = np.random.default_rng(seed)
    G = rng.uniform(-0.1, 0.1, (3, 3))
    return points @ G.T + rng.uniform(-1, 1, 3), G


@pytest.mark.parametrize("material", [LinearElastic(E_MPA, 0.47), NeoHookean(E_MPA, 0.47)],
                         ids=["linear", "neo-hookean"])
def test_static_patch_test_on_the_tet_faces(face, material):
    """Patch test of the static path on the irregular tet4 and tet10 faces (the hex8 and wedge6
    ones are in tests/static): a linear displacement prescribed on the boundary is reproduced
    at every interior node to 1e-9 of max |u| (round-off times the conditioning of a
    nearly incompressible solid; Newton stops at rtol 1e-10)."""
    U, _ = _linear_field(face.points)
    boundary = _boundary_nodes(face)
    inner = np.setdiff1d(np.arange(face.n_points), boundary)
    assert inner.size > 100
    problem = StaticProblem(face, MaterialAssignment(material), rtol=1e-10)
    sol = problem.solve(Constraints(face.n_points, boundary, U[boundary]))
    assert np.abs(sol.displacement[inner] - U[inner]).max() <= 1e-9 * np.abs(U).max()


def test_impact_patch_test_on_the_tet_faces(face):
    """Patch test of the explicit path: under a homogeneous finite deformation F = I + G (|G| ~
    0.1) the finite-strain J2 stress is uniform, so the internal force vanishes at every
    interior node (1e-12 of the largest boundary force: round-off) and the boundary forces
    sum to zero (free body in equilibrium)."""
    U, G = _linear_field(face.points)
    kin = tet_kinematics(face)
    F = deformation_gradient(kin, U)
    np.testing.assert_allclose(F, np.broadcast_to(np.eye(3) + G, F.shape), atol=1e-13)
    material = J2Plasticity(E_MPA, NU, 1e-9, table=None)
    P = material.update(F.reshape(-1, 3, 3), material.initial_state(kin.n_points)).first_piola
    f = internal_force(kin, P.reshape(F.shape), face.n_points)
    boundary = _boundary_nodes(face)
    inner = np.setdiff1d(np.arange(face.n_points), boundary)
    scale = np.abs(f[boundary]).max()
    assert scale > 0
    assert np.abs(f[inner]).max() <= 1e-12 * scale
    assert np.abs(f.sum(axis=0)).max() <= 1e-12 * scale


@pytest.mark.parametrize("ctype", ["hex8", "wedge6", "tet4", "tet10"])
def test_element_tangent_of_the_isotropic_tensor_is_the_voigt_stiffness(ctype):
    """element_tangent (``dP/dF`` contracted with the gradients, what the quasi-static impact path
    and the Neo-Hookean static path use) with the constant isotropic tensor equals the static
    workflow's Voigt ``B^T D B`` stiffness (full integration, no mean dilatation) on distorted
    cells of all four types, to round-off."""
    mesh = _distorted(ctype)
    kb = kinematics(mesh, mean_dilatation=False).blocks[0]
    E, Q = kb.weight.shape
    lam, mu = 0.4, 0.3
    K = element_tangent(kb.grad, kb.weight, np.broadcast_to(isotropic_tangent(lam, mu), (E, Q, 3, 3, 3, 3)))
    material = LinearElastic(mu * (3 * lam + 2 * mu) / (lam + mu), lam / (2 * (lam + mu)))  # lam, mu as above
    D = np.broadcast_to(material.stiffness(), (E, 6, 6))
    K0 = _block_stiffness(kb, D, np.zeros(E))
    assert np.abs(K - K0).max() <= 1e-13 * np.abs(K0).max()


@pytest.mark.skipif(not HAVE_NUMBA, reason="the compiled kernel needs numba")
@pytest.mark.parametrize("symmetric", [False, True])
def test_the_compiled_element_tangent_equals_the_einsum_reference(symmetric):
    """The numba kernel of element_tangent against its numpy reference (two einsums), for an
    unsymmetric random dP/dF on tet10 gradients, to round-off."""
    rng = np.random.default_rng(4)
    E, Q, n = 7, 4, 10
    grad, weight = rng.standard_normal((E, Q, n, 3)), rng.uniform(0.1, 1.0, (E, Q))
    A = rng.standard_normal((E, Q, 3, 3, 3, 3))
    K = element_tangent(grad, weight, A, symmetric)
    with mock.patch.dict(os.environ, {"TOOLKIT_JIT": "0"}):
        K0 = element_tangent(grad, weight, A, symmetric)
    assert np.abs(K - K0).max() <= 1e-13 * np.abs(K0).max()
    assert not symmetric or np.array_equal(K, np.swapaxes(K, 1, 2))


@pytest.mark.parametrize("jit", ["compiled", "numpy"])
@pytest.mark.parametrize("symmetric", [False, True])
def test_the_fused_tangent_assembly_equals_element_tangents_assembled(symmetric, jit):
    """``SparsePattern.assemble_tangent`` (element matrices written straight into the CSR data,
    upper node blocks only when symmetric) equals ``assemble`` of ``element_tangent`` to
    round-off, on a pattern of two element blocks sharing nodes (a tet10 face and a tet4 box
    glued onto its first nodes) with an unsymmetric random ``dP/dF``; symmetric, the result is
    exactly symmetric."""
    rng = np.random.default_rng(6)
    face10 = face_tet("coarse", order=2)
    box = _distorted("tet4")
    k10, k4 = tet_kinematics(face10), kinematics(box, mean_dilatation=False).blocks[0]
    conn4 = box.cells["tet4"] + 5  # shares nodes 5.. with the face
    pattern = SparsePattern([face10.cells["tet10"], conn4], face10.n_points)
    blocks = [(kb.grad, kb.weight, rng.standard_normal(kb.weight.shape + (3, 3, 3, 3))) for kb in (k10, k4)]
    with mock.patch.dict(os.environ, {"TOOLKIT_JIT": "1" if jit == "compiled" else "0"}):
        if jit == "compiled" and not HAVE_NUMBA:
            pytest.skip("the compiled kernel needs numba")
        K = pattern.assemble_tangent(blocks, symmetric)
    K0 = pattern.assemble([element_tangent(g, w, A, symmetric) for g, w, A in blocks])
    assert np.array_equal(K.indptr, K0.indptr) and np.array_equal(K.indices, K0.indices)
    assert np.abs(K.data - K0.data).max() <= 1e-13 * np.abs(K0.data).max()
    assert not symmetric or abs(K - K.T).max() <= 1e-15 * np.abs(K0.data).max()
    assert symmetric or abs(K - K.T).max() > 0.1 * np.abs(K0.data).max()
    with pytest.raises(ValueError, match="1 tangent blocks for a pattern of 2"):
        pattern.assemble_tangent(blocks[:1])


@pytest.mark.parametrize("jit", ["compiled", "numpy"])
def test_adding_a_local_term_equals_scipys_sum(jit):
    """``add_local(K, C)`` for an assembled tangent and a contact-like term on a few rows (inside
    and outside ``K``'s pattern, unsorted with duplicates, first and last rows included) equals
    scipy's ``K + C`` entry for entry, with sorted indices; the pattern's matrices are flagged
    canonical and truly are (a copy without the flag passes scipy's own check)."""
    face10 = face_tet("coarse", order=2)
    pattern = SparsePattern([face10.cells["tet10"]], face10.n_points)
    rng = np.random.default_rng(7)
    K = pattern.assemble([rng.standard_normal((face10.cells["tet10"].shape[0], 30, 30))])
    assert K.has_canonical_format
    unflagged = sp.csr_matrix((K.data.copy(), K.indices.copy(), K.indptr.copy()), shape=K.shape)
    assert unflagged.has_canonical_format  # scipy's O(nnz) check
    m = K.shape[0]
    rows = np.concatenate([[0, m - 1], rng.integers(0, m, 40)])
    rows = np.concatenate([rows, rows])  # duplicates
    cols = np.concatenate([rng.integers(0, m, rows.size // 2), rows[: rows.size // 2]])  # far and diagonal
    C = sp.coo_matrix((rng.standard_normal(rows.size), (rows, cols)), shape=K.shape)
    with mock.patch.dict(os.environ, {"TOOLKIT_JIT": "1" if jit == "compiled" else "0"}):
        if jit == "compiled" and not HAVE_NUMBA:
            pytest.skip("the compiled merge needs numba")
        S = add_local(K, C)
    R = (K + C.tocsr()).tocsr()
    R.sum_duplicates()
    assert np.array_equal(S.indptr, R.indptr) and np.array_equal(S.indices, R.indices)
    assert np.abs(S.data - R.data).max() <= 1e-14 * np.abs(R.data).max()
    assert add_local(K, sp.csr_matrix(K.shape)).nnz == K.nnz
    with pytest.raises(ValueError, match="shapes differ"):
        add_local(K, sp.csr_matrix((3, 3)))
    with pytest.raises(ValueError, match="sorted, unique indices"):
        add_local(sp.csr_matrix((np.ones(2), [1, 0], [0, 2, 2]), shape=(2, 2)), sp.csr_matrix((2, 2)))


def _distorted(ctype):
    """A 2 x 2 x 2 box of 1 mm cells of ``ctype`` with nodes jittered by 0.1 mm."""
    axes = [np.linspace(0, 2, 3)] * 3
    if ctype != "wedge6":
        return block(axes, ctype, jitter=0.1, seed=3)
    hexes = block(axes, "hex8", jitter=0.1, seed=3)
    return Mesh(hexes.points, {"wedge6": wedges_from_hexes(hexes.cells["hex8"])})


def _contract_cases():
    """(name, material, state, F) with F at finite strain (20 % stretches and shears, and
    enough for J2 to yield on the face table), 6 points each."""
    rng = np.random.default_rng(5)
    F = np.eye(3) + 0.2 * rng.standard_normal((6, 3, 3))
    fibres = rng.standard_normal((6, 3))
    j2 = J2Plasticity(E_MPA, NU, 1e-9, table=FACE_TABLE.scaled(0.1))  # yields at 0.0015 MPa
    return [("linear", LinearElastic(E_MPA, NU), None, F),
            ("transversely isotropic", TransverselyIsotropic(), TransverselyIsotropic().initial_state(fibres), F),
            ("Neo-Hookean", NeoHookean(E_MPA, NU), None, F),
            ("J2", j2, j2.initial_state(6), F)]


@pytest.mark.parametrize("case", range(4), ids=["linear", "transversely_isotropic", "neo_hookean", "j2"])
def test_every_material_tangent_is_the_derivative_of_its_update(case):
    """One contract for the four materials: ``tangent(F, state)`` returns the update and
    ``dP/dF``, which must equal central differences of ``update(F, state).first_piola``.
    With a step h = 1e-6 the truncation error is ~h^2 times the third derivative (~1e-12
    relative) and the round-off ~1e-16 / h = 1e-10; every tangent is in closed form (J2's from
    the compiled kernel), so the tolerance is 1e-7 of the largest entry."""
    name, material, state, F = _contract_cases()[case]
    result, A = material.tangent(F, state)
    np.testing.assert_allclose(result.first_piola, material.update(F, state).first_piola, rtol=0, atol=1e-15)
    h = 1e-6
    fd = np.empty_like(A)
    for k in range(3):
        for L in range(3):
            step = np.zeros((3, 3))
            step[k, L] = h
            fd[..., k, L] = (material.update(F + step, state).first_piola
                             - material.update(F - step, state).first_piola) / (2 * h)
    assert np.abs(A - fd).max() <= 1e-7 * np.abs(fd).max(), name
    if name == "J2":
        assert result.plastic.any(), "the J2 case must exercise the return mapping"
