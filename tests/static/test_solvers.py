"""Linear solvers: the fill-aware automatic choice and the reuse of a factorization across
the solves of an increment."""

import numpy as np
import pytest
import scipy.sparse as sp

from toolkit.common.materials import LinearElastic
from toolkit.common.phantom import block, face_hex
from toolkit.static.assembly import MaterialAssignment
from toolkit.static.constraints import Constraints
from toolkit.static.fem import StaticProblem
from toolkit.common.fem.solvers import (
    AUTO_DIRECT_MAX_ENTRIES,
    REUSED_DIRECT_MAX_ENTRIES,
    LinearSolver,
    choose_method,
    estimate_factor_entries,
)


def _entries(mesh):
    problem = StaticProblem(mesh, MaterialAssignment(LinearElastic()))
    return estimate_factor_entries(problem.pattern.node_graph()), 3 * mesh.n_points


def test_auto_chooses_by_expected_fill_not_by_size():
    """A thin shell (the paper face, ~12k dofs) and a bulky block of about the same number of
    dofs (13 x 13 x 13 nodes, 6.6k dofs... 20 x 20 x 20 nodes, 24k dofs) differ in the
    factor's envelope by a factor > 5: auto factorizes the shell and sends the bulky block
    to AMG, although a dof-count rule (40k) would factorize both. The estimate grows like
    n^(5/3) on cubes (a profile factorization of a 3D grid): doubling the side multiplies
    it by ~2^5 = 32 (allowed 20-45)."""
    shell, n_shell = _entries(face_hex("paper").mesh)
    cube, n_cube = _entries(block([np.linspace(0, 100, 21)] * 3))
    assert n_cube > n_shell and cube > 5 * shell
    assert choose_method("auto", n_shell, shell) == "superlu"
    assert choose_method("auto", n_cube, cube) == "amg"
    assert choose_method("auto", n_cube, None) == "superlu"  # what counting dofs alone would do
    small, _ = _entries(block([np.linspace(0, 100, 11)] * 3))
    assert 20 < cube / small < 45
    assert shell < AUTO_DIRECT_MAX_ENTRIES < cube
    # a solver whose factorization will be reused over many systems factorizes larger meshes
    assert choose_method("auto", n_cube, cube, direct_max_entries=REUSED_DIRECT_MAX_ENTRIES) == "superlu"
    assert choose_method("auto", n_cube, 10 * REUSED_DIRECT_MAX_ENTRIES, REUSED_DIRECT_MAX_ENTRIES) == "amg"


@pytest.mark.parametrize("method", ["superlu", "amg"])
def test_reuse_across_solves_equals_fresh_solves(method):
    """Lip-contact style sequence: the same stiffness solved under constraint sets that differ
    by a few tied dofs (equal sizes: tie slaves keep their columns). The second and third
    systems are solved by CG preconditioned with the first factorization or AMG hierarchy
    (reused, no new factorization: tying k dofs changes the matrix by rank <= 2k, so CG
    needs about 2k + 1 iterations) and equal a fresh direct solve (1e-10 relative for
    SuperLU, 1e-7 for AMG-CG at its 1e-9 residual)."""
    mesh = block([np.linspace(0, 20, 9), np.linspace(0, 10, 5), np.linspace(0, 10, 5)])
    problem = StaticProblem(mesh, MaterialAssignment(LinearElastic(0.003, 0.47)), method)
    problem.linear_solver.timed_budget = False  # a fixed budget of 40 CG iterations: reproducible
    x = mesh.points
    bottom, top = np.flatnonzero(x[:, 2] == 0), np.flatnonzero(x[:, 2] == 10)
    mid = np.flatnonzero((x[:, 2] == 5) & (x[:, 0] > 0) & (x[:, 0] < 20))
    base = Constraints(mesh.n_points, np.concatenate([bottom, top]),
                       np.vstack([np.zeros((bottom.size, 3)), np.tile([0.5, 0.0, -1.0], (top.size, 1))]))
    sols = []
    from dataclasses import replace

    for k in (0, 2, 4):  # tie k mid-plane nodes' z to their +x neighbour
        slaves = mid[:k]
        masters = np.array([np.flatnonzero((x[:, 2] == 5) & np.isclose(x[:, 0], x[s, 0] + 2.5)
                                           & np.isclose(x[:, 1], x[s, 1]))[0] for s in slaves], dtype=np.int64)
        c = replace(base, tie_slaves=slaves, tie_masters=masters, tie_offsets=np.zeros(k))
        sols.append((c, problem.solve(c)))
    solver = problem.linear_solver
    assert solver.factorizations == 1 and solver.reuses == 2
    assert [s.solves[0].reused for _, s in sols] == [False, True, True]
    fresh = StaticProblem(mesh, MaterialAssignment(LinearElastic(0.003, 0.47)), "superlu")
    for c, s in sols:
        ref = fresh.solve(c).displacement
        tol = 1e-10 if method == "superlu" else 1e-7
        assert np.abs(s.displacement - ref).max() <= tol * np.abs(ref).max()


def test_reuse_gives_up_when_the_matrix_changed_too_much():
    """A system whose matrix has nothing to do with the stored factorization (a 10x stiffer
    material on some elements) would need many CG iterations: the solver refactorizes
    within its budget and still returns the exact answer."""
    A = sp.random(200, 200, density=0.05, random_state=0)
    A = (A @ A.T + sp.eye(200) * 0.1).tocsc()
    B = (A + sp.diags(np.linspace(0, 100, 200))).tocsc()
    b = np.ones(200)
    solver = LinearSolver("superlu")
    solver.solve(A, b)
    x, info = solver.solve(B, b)
    np.testing.assert_allclose(B @ x, b, atol=1e-8)
    assert solver.factorizations + solver.reuses == 2


def _unsymmetric_pair(n=300, rank=12, seed=3):
    """An SPD matrix ``A`` (a 1D Laplacian plus a shift) and ``B = A + U V^T``, an unsymmetric
    low-rank change as a slipping friction contact adds to a tangent."""
    rng = np.random.default_rng(seed)
    A = sp.diags([-np.ones(n - 1), 2.2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tocsc()
    rows = rng.choice(n, rank, replace=False)
    U = sp.csc_matrix((rng.uniform(0.2, 0.5, rank), (rows, np.arange(rank))), shape=(n, rank))
    V = sp.csc_matrix((rng.uniform(-0.5, 0.5, rank), (np.roll(rows, 1), np.arange(rank))), shape=(n, rank))
    return A, (A + U @ V.T).tocsc(), rng.standard_normal(n)


@pytest.mark.parametrize("method", ["superlu", "amg"])
def test_an_unsymmetric_system_is_solved_fresh_and_with_a_reused_factorization(method):
    """SuperLU factorizes the unsymmetric matrix itself, AMG its symmetric part as GMRES's
    preconditioner; a reused symmetric factorization preconditions GMRES (right-preconditioned,
    so its stopping test is the true residual: asserted at rtol). CG on that system would not
    be a valid method, and the solver never uses it there."""
    A, B, b = _unsymmetric_pair()
    rtol = 1e-8
    fresh = LinearSolver(method, rtol=rtol, reuse_rtol=rtol)
    x, _ = fresh.solve(B, b, symmetric=False)
    assert np.linalg.norm(B @ x - b) <= 1.01 * rtol * np.linalg.norm(b)
    reused = LinearSolver(method, rtol=rtol, reuse_rtol=rtol, timed_budget=False)
    reused.solve(A, b)
    x, info = reused.solve(B, b, symmetric=False)
    assert info.reused and reused.factorizations == 1
    assert np.linalg.norm(B @ x - b) <= 1.01 * rtol * np.linalg.norm(b)
    # a rank-12 change needs at most 12 + 1 GMRES iterations on an exact factor of A
    assert method != "superlu" or info.iterations <= 13
