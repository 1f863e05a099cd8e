"""Linear solvers: the fill-aware automatic choice and the reuse of a factorization across
the solves of an increment."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from toolkit.common.fem.factory import FactorMaker
from toolkit.common.fem.materials import LinearElastic, NeoHookean
from toolkit.common.fem.solvers import (
    AUTO_DIRECT_MAX_ENTRIES,
    REUSED_DIRECT_MAX_ENTRIES,
    LinearSolver,
    choose_method,
    estimate_factor_entries,
)
from toolkit.common.phantoms.phantom import block, face_hex
from toolkit.static.constraints import Constraints
from toolkit.static.problem import StaticProblem
from toolkit.static.stiffness import MaterialAssignment


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
    problem.linear_solver = LinearSolver(method, timed_budget=False)  # a fixed budget of CG iterations: reproducible
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


def test_without_hierarchy_reuse_amg_builds_one_per_new_matrix_and_reuses_it_for_the_same():
    """``reuse_hierarchy=False``: a changed matrix gets a new AMG hierarchy (no CG on the old
    one), the same matrix again is solved on the stored one; the answers are those of a direct
    solve. A linear static problem solves this way (its systems differ by their reduction), a
    Neo-Hookean one reuses hierarchies across Newton's tangents."""
    mesh = block([np.linspace(0, 20, 9), np.linspace(0, 10, 5), np.linspace(0, 10, 5)])
    A = StaticProblem(mesh, MaterialAssignment(LinearElastic(0.003, 0.47))).stiffness.tocsr()
    free = np.arange(3 * 5 * 5, A.shape[0])  # the x = 0 face held
    A = A[free][:, free].tocsr()
    B = (A + sp.diags(np.linspace(0, 1e-3, A.shape[0]))).tocsr()
    b = np.random.default_rng(0).standard_normal(A.shape[0])
    solver = LinearSolver("amg", reuse_hierarchy=False)
    for M in (A, B, B):
        x, _ = solver.solve(M, b)
        ref = spla.spsolve(M.tocsc(), b)
        assert np.abs(x - ref).max() <= 1e-6 * np.abs(ref).max()
    assert solver.factorizations == 2 and solver.reuses == 1
    reusing = LinearSolver("amg", timed_budget=False)
    for M in (A, B):
        reusing.solve(M, b)
    assert reusing.factorizations == 1 and reusing.reuses == 1
    assert not StaticProblem(mesh, MaterialAssignment(LinearElastic()), "amg").linear_solver.options.reuse_hierarchy
    assert StaticProblem(mesh, MaterialAssignment(NeoHookean()), "amg").linear_solver.options.reuse_hierarchy


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


def _grid_laplacian_3d(n):
    """The 3-dof-per-node stiffness pattern of an ``n^3`` grid: a 7-point Laplacian (SPD)
    coupled to 3 components per node, nodes numbered lexicographically."""
    one = sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    eye = sp.identity(n)
    lap = sp.kron(sp.kron(one, eye), eye) + sp.kron(sp.kron(eye, one), eye) + sp.kron(sp.kron(eye, eye), one)
    block = np.array([[3.0, 1.0, 0.5], [1.0, 3.0, 1.0], [0.5, 1.0, 3.0]])
    return sp.kron(lap + 0.01 * sp.identity(n ** 3), block).tocsc()


@pytest.mark.long  # a Dask cluster's start-up / a factorization of a 3D grid: ~8 s each
def test_nested_dissection_keeps_nodes_together_and_fills_less_than_minimum_degree():
    """METIS nested dissection of the node graph: a permutation that keeps each node's three
    dofs consecutive, and a SuperLU factor of a 16^3-node grid (12k dofs) with fewer entries
    than minimum degree gives (nested dissection is the asymptotically optimal order on grids,
    O(N^{4/3}) factor entries in 3D, George 1973; minimum degree is not) and far fewer than the
    lexicographic numbering's band (O(N^{5/3})). The ordered solve is exact to round-off."""
    import scipy.sparse.linalg as spla

    from toolkit.common.fem.solvers import fill_reducing_order, superlu

    A = _grid_laplacian_3d(16)
    perm = fill_reducing_order(A)
    m = A.shape[0]
    assert np.array_equal(np.sort(perm), np.arange(m))
    nodes = perm.reshape(-1, 3)
    assert np.array_equal(nodes % 3, np.tile([0, 1, 2], (m // 3, 1))) and np.all(np.ptp(nodes // 3, axis=1) == 0)

    def entries(M, spec):
        lu = spla.splu(M.tocsc(), permc_spec=spec, diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        return lu.L.nnz + lu.U.nnz

    nd = entries(sp.csr_matrix(A)[perm][:, perm], "NATURAL")
    assert nd < entries(A, "MMD_AT_PLUS_A")
    assert nd < entries(A, "NATURAL") / 3
    b = np.random.default_rng(0).standard_normal(m)
    for ordering in ("nd", "mmd"):
        x = superlu(A, ordering)(b)
        assert np.linalg.norm(A @ x - b) <= 1e-12 * np.linalg.norm(b)
    with pytest.raises(ValueError, match="ordering 'amd'"):
        superlu(A, "amd")


def test_factorizing_ahead_uses_a_background_factor_chosen_by_the_count_of_solves():
    """A Newton-like sequence of SPD systems ``A_k = A + k D`` (a stiffening diagonal). With
    ``factorize_ahead=2`` the solver factorizes ``A_1`` in the foreground, then each reused
    system in a background thread when none is running, and takes that factor into use two
    solves later: after six systems it preconditions with ``A_4``'s factor (submitted at
    solves 2 and 4). Every answer meets the residual, the Krylov iterations on a two-solve-old
    factor stay below those on the first factor, and a second solver makes exactly the same
    choices (the count of solves decides, not timing). ``close`` ends the worker thread."""
    A0 = _grid_laplacian_3d(8)
    m = A0.shape[0]
    D = sp.diags(np.linspace(0.0, 2.0, m))
    systems = [(A0 + k * D).tocsc() for k in range(1, 7)]
    b = np.random.default_rng(1).standard_normal(m)
    runs = []
    for ahead in (2, 2, 0):
        solver = LinearSolver("superlu", reuse_rtol=1e-10, timed_budget=False, factorize_ahead=ahead)
        counts = []
        for S in systems:
            x, info = solver.solve(S, b)
            assert np.linalg.norm(S @ x - b) <= 1e-9 * np.linalg.norm(b)
            counts.append(info.iterations)
        runs.append((counts, solver, solver._stored.A))
        solver.close()
    (first, ahead, used), (second, _, _), (stale, plain, _) = runs
    assert first == second
    assert ahead.factorizations == 1 and ahead.background_factorizations == 2
    assert abs(used - systems[3]).max() == 0
    assert plain.factorizations == 1 and plain.background_factorizations == 0
    assert sum(first[3:]) < sum(stale[3:])
    # closed: the worker has ended, the factors made on it are freed, a new solve starts afresh
    assert not ahead._ahead.running and ahead._stored is None
    x, info = ahead.solve(systems[0], b)
    assert not info.reused and np.linalg.norm(systems[0] @ x - b) <= 1e-9 * np.linalg.norm(b)
    with pytest.raises(ValueError, match="factorize_ahead -1"):
        LinearSolver(factorize_ahead=-1)


def test_factors_made_ahead_are_freed_on_the_thread_that_made_them(monkeypatch):
    """scipy's SuperLU objects freed on another thread than the one that made them keep their
    memory (scipy issue #15921: a paper impact run grew to 13.4 GB). Every factor the worker
    makes, used or dropped, is freed on the worker, by the time ``close`` returns."""
    import threading
    import weakref

    made = []  # (thread that made the factor, thread that freed it)

    original = FactorMaker.make

    def tracked(self, A, symmetric, near_nullspace, local=None, coarse_space=None):
        result = original(self, A, symmetric, near_nullspace, local, coarse_space)
        record = [threading.current_thread().name, None]
        made.append(record)
        weakref.finalize(result.factor, lambda r=record: r.__setitem__(1, threading.current_thread().name))
        return result

    monkeypatch.setattr(FactorMaker, "make", tracked)
    A0 = _grid_laplacian_3d(6)
    D = sp.diags(np.linspace(0.0, 2.0, A0.shape[0]))
    b = np.ones(A0.shape[0])
    solver = LinearSolver("superlu", single_precision=True, timed_budget=False, factorize_ahead=1)
    for k in range(1, 8):
        solver.solve((A0 + k * D).tocsc(), b)
    solver.close()
    ahead = [r for r in made if r[0].startswith("toolkit-factorize-ahead")]
    assert len(ahead) >= 3
    assert all(r[1] is not None and r[1].startswith("toolkit-factorize-ahead") for r in ahead), made


def test_a_solve_may_set_its_own_krylov_tolerance():
    """``solve(..., rtol=)`` replaces the solver's ``rtol`` and ``reuse_rtol`` for that solve
    only (an inexact Newton's forcing term): a reused factor of a nearby system then stops at a
    residual below the given tolerance, in fewer iterations than at the solver's own; the next
    solve is back at the solver's tolerance. A tolerance outside (0, 1) is refused."""
    A0 = _grid_laplacian_3d(8)
    m = A0.shape[0]
    D = sp.diags(np.linspace(0.0, 2.0, m))
    b = np.random.default_rng(2).standard_normal(m)
    solver = LinearSolver("superlu", reuse_rtol=1e-10, timed_budget=False)
    solver.solve(A0.tocsc(), b)
    S = (A0 + D).tocsc()
    x, loose = solver.solve(S, b, rtol=1e-2)
    assert loose.reused and np.linalg.norm(S @ x - b) <= 1e-2 * np.linalg.norm(b)
    x, tight = solver.solve(S, b)
    assert tight.reused and np.linalg.norm(S @ x - b) <= 1e-9 * np.linalg.norm(b)
    assert 1 <= loose.iterations < tight.iterations
    for bad in (0.0, 1.0, -1e-3):
        with pytest.raises(ValueError, match=f"rtol {bad} must lie in"):
            solver.solve(S, b, rtol=bad)


def test_no_factorization_is_made_ahead_after_an_easy_solve():
    """``factorize_ahead_above``: a solve starts a background factorization only when the one
    before it needed more Krylov iterations than that (or factorized); the systems below
    (reused factors need 5-20 iterations) get only the one started after the first
    factorization above 100 and the usual two at 0, every answer meeting the residual; a
    negative count is refused."""
    A0 = _grid_laplacian_3d(8)
    m = A0.shape[0]
    D = sp.diags(np.linspace(0.0, 2.0, m))
    systems = [(A0 + k * D).tocsc() for k in range(1, 7)]
    b = np.random.default_rng(1).standard_normal(m)
    made = {}
    for above in (0, 100):
        solver = LinearSolver("superlu", reuse_rtol=1e-10, timed_budget=False, factorize_ahead=2,
                              factorize_ahead_above=above)
        for S in systems:
            x, info = solver.solve(S, b)
            assert np.linalg.norm(S @ x - b) <= 1e-9 * np.linalg.norm(b)
            assert info.iterations <= 100
        made[above] = solver.background_factorizations
        solver.close()
    assert made == {0: 2, 100: 1}
    with pytest.raises(ValueError, match="factorize_ahead_above -1 must be >= 0"):
        LinearSolver("superlu", factorize_ahead_above=-1)
    with pytest.raises(ValueError, match=r"correction_threshold -0.1 must lie in \[0, 1\)"):
        LinearSolver("superlu", correction_threshold=-0.1)
