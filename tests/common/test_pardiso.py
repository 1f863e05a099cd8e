"""MKL PARDISO through ctypes (``toolkit.common.fem.pardiso``): exact solves of the systems
the toolkit factorizes (SPD stiffness, and with an unsymmetric friction part), the
fill-reducing ordering honoured, float32 factors as preconditioners, and its place in
:class:`~toolkit.common.fem.solvers.LinearSolver` (automatic choice, factorizing ahead on a
worker thread)."""

import numpy as np
import pytest
import scipy.sparse as sp

from toolkit.common.fem import pardiso
from toolkit.common.fem.solvers import LinearSolver, SolverError, choose_method, fill_reducing_order

needs_mkl = pytest.mark.skipif(not pardiso.available(), reason="MKL (the 'pardiso' extra) is not installed")


def _stiffness(n):
    """An SPD 3-dof-per-node matrix on an ``n^3`` grid (a 7-point Laplacian coupled to 3
    components per node, nodes numbered lexicographically), as an elasticity stiffness is."""
    one = sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    eye = sp.identity(n)
    lap = sp.kron(sp.kron(one, eye), eye) + sp.kron(sp.kron(eye, one), eye) + sp.kron(sp.kron(eye, eye), one)
    block = np.array([[3.0, 1.0, 0.5], [1.0, 3.0, 1.0], [0.5, 1.0, 3.0]])
    return sp.kron(lap + 0.01 * sp.identity(n ** 3), block).tocsr()


def _with_friction(A, seed=0, count=40):
    """``A`` plus unsymmetric 3x3 blocks on ``count`` nodes' diagonals (the consistent tangent of
    slipping Coulomb friction, ``mu k m n^T``, is such a block: rank one, not symmetric)."""
    rng = np.random.default_rng(seed)
    nodes = rng.choice(A.shape[0] // 3, count, replace=False)
    m, n = rng.standard_normal((count, 3)), rng.standard_normal((count, 3))
    blocks = 0.2 * m[:, :, None] * n[:, None, :]
    rows = np.broadcast_to((3 * nodes[:, None] + np.arange(3))[:, :, None], blocks.shape)
    cols = np.broadcast_to((3 * nodes[:, None] + np.arange(3))[:, None, :], blocks.shape)
    return (A + sp.csr_matrix((blocks.ravel(), (rows.ravel(), cols.ravel())), shape=A.shape)).tocsr()


@needs_mkl
@pytest.mark.parametrize("ordering", ["nested dissection", "pardiso's metis"])
@pytest.mark.parametrize("unsymmetric", [False, True])
def test_a_float64_factor_solves_to_round_off(ordering, unsymmetric):
    """Backward error at round-off (relative residual <= 1e-12) for one and for several
    right-hand sides, with the toolkit's ordering or PARDISO's own, SPD or with a friction part."""
    A = _stiffness(10)
    if unsymmetric:
        A = _with_friction(A)
        assert abs(A - A.T).max() > 0.01
    perm = fill_reducing_order(A) if ordering == "nested dissection" else None
    factor = pardiso.PardisoFactor(A, perm)
    b = np.random.default_rng(1).standard_normal((A.shape[0], 3))
    x = factor(b[:, 0])
    assert x.shape == (A.shape[0],) and x.dtype == np.float64
    assert np.linalg.norm(A @ x - b[:, 0]) <= 1e-12 * np.linalg.norm(b[:, 0])
    X = factor(b)
    assert X.shape == b.shape
    assert np.linalg.norm(A @ X - b) <= 1e-12 * np.linalg.norm(b)
    assert factor.perturbed == 0


@needs_mkl
def test_the_ordering_given_is_the_one_used():
    """PARDISO reads ``perm[i]`` as the new position of unknown ``i``, SuperLU's ``perm_c``
    convention the other way round; the module converts. With the toolkit's nested dissection
    the factor has as many entries as SuperLU's on the same ordering (within 10 %: both are
    supernodal LU of the same pattern); read the wrong way round, the permutation would be a
    scrambled one with over 5x the fill (measured 12x on a 25^3 grid)."""
    import scipy.sparse.linalg as spla

    A = _stiffness(14)
    perm = fill_reducing_order(A)
    lu = spla.splu(sp.csc_matrix(A[perm][:, perm]), permc_spec="NATURAL", diag_pivot_thresh=0.0,
                   options={"SymmetricMode": True})
    superlu_entries = lu.L.nnz + lu.U.nnz - A.shape[0]  # SuperLU stores the unit diagonal of L
    entries = pardiso.PardisoFactor(A, perm).entries
    assert abs(entries - superlu_entries) <= 0.1 * superlu_entries, (entries, superlu_entries)
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(perm.size)
    assert pardiso.PardisoFactor(A, inverse).entries > 2 * entries


@needs_mkl
def test_a_float32_factor_preconditions_to_any_tolerance():
    """A float32 factor alone leaves a residual near float32's precision times the condition
    (here 1e-7..1e-4), and as the preconditioner of the solver's Krylov iterations it reaches a
    1e-10 residual in a few iterations (each contracts the error by ~that residual)."""
    A = _with_friction(_stiffness(10))
    b = np.random.default_rng(2).standard_normal(A.shape[0])
    x = pardiso.PardisoFactor(A, single=True)(b)
    residual = np.linalg.norm(A @ x - b) / np.linalg.norm(b)
    assert 1e-9 < residual < 1e-4
    solver = LinearSolver("pardiso", single_precision=True, rtol=1e-10)
    x, info = solver.solve(A, b, symmetric=False)
    assert np.linalg.norm(A @ x - b) <= 1e-10 * np.linalg.norm(b)
    assert info.method == "pardiso" and 1 <= info.iterations <= 4


@needs_mkl
def test_factorizing_ahead_with_pardiso_gives_superlus_answers():
    """The Newton-like sequence of the SuperLU test (``A + k D``, unsymmetric here) through a
    solver that factorizes ahead on its worker thread: every answer meets the residual, the
    factor in use is chosen by the count of solves (the same Krylov iteration counts as with
    SuperLU, whose factors are equally exact), and ``close`` frees them."""
    A0 = _with_friction(_stiffness(8))
    D = sp.diags(np.linspace(0.0, 2.0, A0.shape[0]))
    systems = [(A0 + k * D).tocsr() for k in range(1, 8)]
    b = np.random.default_rng(3).standard_normal(A0.shape[0])
    counts = {}
    for method in ("pardiso", "superlu"):
        solver = LinearSolver(method, reuse_rtol=1e-10, timed_budget=False, factorize_ahead=2)
        counts[method] = []
        for S in systems:
            x, info = solver.solve(S, b, symmetric=False)
            assert np.linalg.norm(S @ x - b) <= 1e-9 * np.linalg.norm(b)
            counts[method].append(info.iterations)
        assert solver.background_factorizations >= 2
        solver.close()
    assert np.abs(np.subtract(counts["pardiso"], counts["superlu"])).max() <= 1, counts


@needs_mkl
def test_bad_input_and_a_closed_factor_are_refused():
    A = _stiffness(4)
    with pytest.raises(ValueError, match=r"shape \(3,\); expected a permutation of shape \(192,\)"):
        pardiso.PardisoFactor(A, np.arange(3))
    with pytest.raises(ValueError, match="nonempty square"):
        pardiso.PardisoFactor(sp.csr_matrix(np.ones((3, 4))))
    factor = pardiso.PardisoFactor(A)
    with pytest.raises(ValueError, match="right-hand side has 5 rows; expected 192"):
        factor(np.ones(5))
    factor.close()
    with pytest.raises(pardiso.PardisoError, match="closed"):
        factor(np.ones(192))


@needs_mkl
def test_a_singular_system_is_reported_by_the_solver():
    """PARDISO perturbs tiny pivots instead of refusing a singular matrix (an under-constrained
    model: here a free-floating body, whose stiffness has a rigid-body null space); the
    solver's residual check turns the answer into a :class:`SolverError`."""
    one = sp.diags([-np.ones(3), np.r_[1.0, 2.0, 2.0, 1.0], -np.ones(3)], [-1, 0, 1])  # free ends
    eye = sp.identity(4)
    lap = sp.kron(sp.kron(one, eye), eye) + sp.kron(sp.kron(eye, one), eye) + sp.kron(sp.kron(eye, eye), one)
    A = sp.kron(lap, np.eye(3)).tocsr()  # constant displacements cost nothing
    assert np.abs(A @ np.ones(A.shape[0])).max() < 1e-12
    b = np.random.default_rng(4).standard_normal(A.shape[0])
    with pytest.raises(SolverError, match="singular"):
        LinearSolver("pardiso").solve(A, b)


def test_auto_takes_pardiso_only_where_mkl_is_installed(monkeypatch):
    """``direct="pardiso"`` asks ``auto`` for PARDISO; without MKL it keeps SuperLU (with the
    same limits on the expected fill), and an explicit ``"pardiso"`` names the missing package."""
    monkeypatch.setattr(pardiso, "available", lambda: False)
    assert choose_method("auto", 1000, 10, direct="pardiso") == "superlu"
    assert choose_method("auto", 10 ** 6, 10 ** 10, direct="pardiso") == "amg"
    monkeypatch.setattr(pardiso, "available", lambda: True)
    assert choose_method("auto", 1000, 10, direct="pardiso") == "pardiso"
    assert choose_method("auto", 1000, 10) == "superlu"
    with pytest.raises(ValueError, match="unknown direct solver 'mumps'"):
        choose_method("auto", 1000, 10, direct="mumps")


def test_without_mkl_pardiso_names_the_package(monkeypatch):
    monkeypatch.setattr(pardiso, "_library", lambda: None)
    with pytest.raises(SolverError, match=r"pip install 'facial-biomech-toolkit\[pardiso\]'"):
        LinearSolver("pardiso").solve(_stiffness(3), np.ones(81))


@needs_mkl
def test_a_refactorization_reuses_the_analysis_and_leaves_out_only_what_it_may():
    """``refactorize`` factorizes a new matrix on the analysed pattern (exact solves after),
    refuses an entry outside the pattern unless it belongs to the droppable term (then that
    entry is left out of the factor and returned), and refuses more left-out entries than
    ``max_left``; a refused refactorization leaves the factor as it was. The matrices given
    stay as they were (a float64 factor once held the caller's values array and overwrote it)."""
    A1 = _stiffness(5)
    m = A1.shape[0]
    b = np.random.default_rng(6).standard_normal(m)
    original = A1.data.copy()
    factor = pardiso.PardisoFactor(A1, fill_reducing_order(A1))
    A2 = (A1 + sp.diags(np.linspace(0.0, 2.0, m))).tocsr()
    left = factor.refactorize(A2)
    assert left.nnz == 0 and np.linalg.norm(A2 @ factor(b) - b) <= 1e-12 * np.linalg.norm(b)
    assert np.array_equal(A1.data, original)
    coupling = sp.csr_matrix(([5.0, 5.0], ([0, m - 1], [m - 1, 0])), shape=(m, m))  # far apart: not in A1
    A3 = (A2 + coupling).tocsr()
    assert factor.refactorize(A3) is None  # not droppable
    assert factor.refactorize(A3, droppable=coupling, max_left=1) is None  # two to leave out
    assert np.linalg.norm(A2 @ factor(b) - b) <= 1e-12 * np.linalg.norm(b)  # unchanged
    left = factor.refactorize(A3, droppable=coupling)
    assert abs(left - coupling).max() == 0
    assert np.linalg.norm((A3 - left) @ factor(b) - b) <= 1e-12 * np.linalg.norm(b)


@needs_mkl
def test_factors_made_ahead_are_refactorized_and_the_local_term_left_out_is_corrected():
    """A Newton-like sequence ``K_k + C_k`` whose contact-like term ``C_k`` moves to new dofs
    (entries outside the first pattern): with the term passed as ``local``, the solver's
    background factors after the first two are refactorizations of retired ones, the moved
    couplings left out and taken by the Woodbury correction, and every answer meets the
    residual."""
    K0 = _stiffness(6)
    m = K0.shape[0]
    D = sp.diags(np.linspace(0.0, 1.0, m))
    b = np.random.default_rng(7).standard_normal(m)
    solver = LinearSolver("pardiso", single_precision=True, reuse_rtol=1e-10, timed_budget=False, factorize_ahead=1)
    for k in range(8):
        nodes = np.array([k, k + 40, 2 * k + 100])
        dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
        rows, cols = np.meshgrid(dofs, dofs, indexing="ij")
        C = sp.csr_matrix((np.full(rows.size, 2.0) + np.eye(dofs.size).ravel() * 20.0, (rows.ravel(), cols.ravel())),
                          shape=(m, m))
        A = (K0 + k * D + C).tocsr()
        x, info = solver.solve(A, b, symmetric=False, local=C)
        assert np.linalg.norm(A @ x - b) <= 1e-9 * np.linalg.norm(b)
    assert solver.refactorizations >= 4 and solver.correction_columns > 0
    solver.close()


@needs_mkl
def test_factors_made_ahead_without_a_local_term_are_refactorized():
    """Systems of one pattern and no local term (an impact run before contact): every
    background factor is a refactorization (the first of the spare the worker made beside the
    first foreground factorization, the others of retired ones), and the answers and Krylov
    iteration counts are those of fresh factors."""
    A0 = _with_friction(_stiffness(6))
    D = sp.diags(np.linspace(0.0, 1.0, A0.shape[0]))
    systems = [(A0 + k * D).tocsr() for k in range(8)]
    b = np.random.default_rng(8).standard_normal(A0.shape[0])
    counts = {}
    for refactorize in (True, False):
        solver = LinearSolver("pardiso", reuse_rtol=1e-10, timed_budget=False, factorize_ahead=2)
        if not refactorize:
            solver._maker.retire = lambda factor: factor.close()  # no spare: every factor fresh
        counts[refactorize] = []
        for S in systems:
            x, info = solver.solve(S, b, symmetric=False)
            assert np.linalg.norm(S @ x - b) <= 1e-9 * np.linalg.norm(b)
            counts[refactorize].append(info.iterations)
        solver.close()  # waits for the factor started at the last solve, which no solve takes
        assert solver.refactorizations == (solver.background_factorizations + 1 if refactorize else 0)
    assert solver.background_factorizations >= 3
    assert counts[True] == counts[False]


@pytest.mark.parametrize("structurally_symmetric", [True, False])
def test_the_upper_symmetric_part_keeps_the_pattern(structurally_symmetric):
    """``symmetric_upper`` is scipy's ``triu((A + A^T) / 2)`` (to round-off), keeps a stored zero
    of a structurally symmetric ``A`` (a refactorization's pattern must not shrink) and takes
    any other pattern too."""
    A = _with_friction(_stiffness(4), seed=3)
    A = A.tolil()
    A[5, 7] = 0.0  # a stored zero in both triangles
    A[7, 5] = 0.0
    if not structurally_symmetric:
        A[0, 40] = 2.5  # no partner at (40, 0)
    A = A.tocsr()
    U = pardiso.symmetric_upper(A)
    assert U.has_sorted_indices and sp.tril(U, k=-1).nnz == 0
    assert abs(U - sp.triu(0.5 * (A + A.T))).max() <= 1e-15
    if structurally_symmetric:
        assert U.nnz == sp.triu(A).nnz  # the zero at (5, 7) kept


@needs_mkl
@pytest.mark.parametrize("single", [False, True])
def test_a_symmetric_factor_solves_the_symmetric_part_with_half_the_entries(single):
    """``symmetric=True``: LDL^T of ``(A + A^T) / 2``, exact to round-off in float64 (to float32's
    1e-5 otherwise) for an unsymmetric ``A``, with about half the factor entries of LU; a
    refactorization leaves out droppable entries in both triangles and returns them so."""
    A = _with_friction(_stiffness(8))
    S = 0.5 * (A + A.T)
    perm = fill_reducing_order(A)
    b = np.random.default_rng(9).standard_normal(A.shape[0])
    factor = pardiso.PardisoFactor(A, perm, single=single, symmetric=True)
    tol = 1e-5 if single else 1e-12
    assert factor.symmetric and np.linalg.norm(S @ factor(b) - b) <= tol * np.linalg.norm(b)
    assert factor.entries <= 0.6 * pardiso.PardisoFactor(A, perm, single=single).entries
    m = A.shape[0]
    coupling = sp.csr_matrix(([5.0, 1.0], ([0, m - 1], [m - 1, 0])), shape=(m, m))  # outside A's pattern
    A2 = (A + sp.diags(np.linspace(0.0, 2.0, m)) + coupling).tocsr()
    assert factor.refactorize(A2) is None
    left = factor.refactorize(A2, droppable=coupling)
    assert abs(left - 0.5 * (coupling + coupling.T)).max() == 0
    S2 = 0.5 * (A2 + A2.T) - left
    assert np.linalg.norm(S2 @ factor(b) - b) <= tol * np.linalg.norm(b)


@needs_mkl
def test_a_refactorization_ignores_stored_zeros_outside_the_pattern():
    """An entry outside the analysed pattern whose value is zero changes nothing: refactorizing
    is not refused for it, and nothing is returned as left out."""
    A = _stiffness(4)
    m = A.shape[0]
    factor = pardiso.PardisoFactor(A, fill_reducing_order(A))
    A2 = sp.csr_matrix((np.concatenate([A.data, [0.0, 0.0]]),
                        (np.concatenate([A.tocoo().row, [0, m - 1]]), np.concatenate([A.tocoo().col, [m - 1, 0]]))),
                       shape=(m, m))
    A2.sum_duplicates()
    assert A2.nnz == A.nnz + 2  # two stored zeros, at entries the analysis never saw
    left = factor.refactorize(A2)
    assert left is not None and left.nnz == 0


@needs_mkl
def test_a_symmetric_factor_made_ahead_meets_the_residual_with_the_lu_s_iterations():
    """``LinearSolver(symmetric_factor=True)`` along a Newton-like sequence with an unsymmetric
    local term (friction-like, moving): every answer meets the residual, GMRES needs at most one
    iteration more per solve than with LU factors (the Woodbury correction takes the skew part
    exactly)."""
    K0 = _stiffness(6)
    m = K0.shape[0]
    D = sp.diags(np.linspace(0.0, 0.3, m))
    b = np.random.default_rng(7).standard_normal(m)
    rng = np.random.default_rng(11)
    locals_ = []
    for k in range(10):
        nodes = np.array([k // 3, 40 + k // 3, 100])
        dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
        block = 2.0 * rng.standard_normal((dofs.size, dofs.size)) + 20.0 * np.eye(dofs.size)
        rows, cols = np.meshgrid(dofs, dofs, indexing="ij")
        locals_.append(sp.csr_matrix((block.ravel(), (rows.ravel(), cols.ravel())), shape=(m, m)))
    counts = {}
    for symmetric_factor in (False, True):
        solver = LinearSolver("pardiso", single_precision=True, reuse_rtol=1e-10, timed_budget=False,
                              factorize_ahead=2, symmetric_factor=symmetric_factor)
        counts[symmetric_factor] = []
        for k, C in enumerate(locals_):
            A = (K0 + k * D + C).tocsr()
            x, info = solver.solve(A, b, symmetric=False, local=C)
            assert np.linalg.norm(A @ x - b) <= 1e-9 * np.linalg.norm(b)
            counts[symmetric_factor].append(info.iterations)
        solver.close()
        assert solver.background_factorizations >= 3
    assert np.all(np.subtract(counts[True], counts[False]) <= 1), counts
