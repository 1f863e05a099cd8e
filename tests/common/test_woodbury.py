"""The Woodbury correction of a reused factorization for a changing term on few dofs
(``toolkit.common.fem.woodbury``), alone and inside :class:`LinearSolver`: exact on what it
corrects, columns computed once per factor, and the limits that switch it off."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from toolkit.common.fem.solvers import LinearSolver
from toolkit.common.fem.woodbury import LocalCorrection

N = 240


def _stiffness(seed=0):
    """An SPD tridiagonal-plus-random stiffness ``(N, N)`` (well conditioned)."""
    rng = np.random.default_rng(seed)
    R = sp.random(N, N, density=0.01, random_state=seed)
    return (sp.diags([-np.ones(N - 1), 4.0 * np.ones(N), -np.ones(N - 1)], [-1, 0, 1]) + 0.1 * (R @ R.T)
            + sp.diags(rng.uniform(0.0, 0.5, N))).tocsr()


def _contact(dofs, seed, scale=50.0):
    """A stiff unsymmetric term on ``dofs`` (penalty-like: 50x the stiffness's diagonal)."""
    rng = np.random.default_rng(seed)
    k = len(dofs)
    block = scale * (np.eye(k) + 0.3 * rng.standard_normal((k, k)))
    rows, cols = np.meshgrid(dofs, dofs, indexing="ij")
    return sp.csr_matrix((block.ravel(), (rows.ravel(), cols.ravel())), shape=(N, N))


def test_the_correction_inverts_the_factored_matrix_plus_the_change_exactly():
    """With an exact factor of ``K + C1``, the corrected preconditioner for ``C2`` is the
    inverse of ``K + C2`` (threshold 0: every touched dof): ``M^-1 (K + C2) x = x`` to 1e-10.
    Columns are computed once per dof: a later change on dofs already seen costs none."""
    K = _stiffness()
    C1, C2 = _contact([3, 4, 5, 60, 61], 1), _contact([4, 5, 6, 100, 101, 102], 2)
    lu = spla.splu((K + C1).tocsc())
    correction = LocalCorrection(lu.solve, N, C1, threshold=0.0)
    apply = correction.preconditioner(C2)
    x = np.random.default_rng(3).standard_normal(N)
    assert np.abs(apply((K + C2) @ x) - x).max() <= 1e-10 * np.abs(x).max()
    assert correction.columns == 9  # the union of both terms' dofs: 3-6, 60, 61, 100-102
    C3 = _contact([3, 60, 100], 4)
    apply = correction.preconditioner(C3)
    assert correction.columns == 9
    assert np.abs(apply((K + C3) @ x) - x).max() <= 1e-10 * np.abs(x).max()
    assert correction.preconditioner(C1) is None  # no change: the factor alone is right


def test_a_first_solve_joins_the_back_solve_of_the_new_columns():
    """``preconditioner_and_solve`` gives the preconditioner and ``M^-1 rhs`` from one call of
    the factor (the new columns and ``rhs`` together), equal to applying the preconditioner to
    ``rhs`` (1e-12); with no new column it leaves the first solve to the caller."""
    K = _stiffness()
    C1, C2 = _contact([3, 4, 5, 60, 61], 1), _contact([4, 5, 6, 100, 101, 102], 2)
    lu = spla.splu((K + C1).tocsc())
    calls = []

    def factor(b):
        calls.append(np.shape(b))
        return lu.solve(b)

    correction = LocalCorrection(factor, N, C1, threshold=0.0)
    rhs = np.random.default_rng(5).standard_normal(N)
    apply, first = correction.preconditioner_and_solve(C2, rhs)
    assert calls == [(N, 10)]  # 9 columns and rhs
    assert np.abs(first - apply(rhs)).max() <= 1e-12 * np.abs(first).max()
    apply, first = correction.preconditioner_and_solve(_contact([4, 60], 3), rhs)
    assert apply is not None and first is None and len(calls) == 2  # no new column: nothing solved


def test_float32_columns_of_a_float32_factor_correct_as_well_as_float64_ones():
    """Columns kept in float32 (``dtype``, for a float32 factor) give the preconditioner of
    float64 columns to float32 round-off (measured 6e-8), and the corrected float32 factor
    inverts ``K + C2`` to its own float32 accuracy (measured 1.1e-6 with either)."""
    K = _stiffness()
    C1, C2 = _contact([3, 4, 5, 60, 61], 1), _contact([4, 5, 6, 100, 101, 102], 2)
    lu32 = spla.splu((K + C1).astype(np.float32).tocsc())

    def factor(b):
        return lu32.solve(np.asarray(b, dtype=np.float32)).astype(np.float64)

    x = np.random.default_rng(4).standard_normal(N)
    y = {dtype: LocalCorrection(factor, N, C1, threshold=0.0, dtype=dtype).preconditioner(C2)((K + C2) @ x)
         for dtype in (np.float32, np.float64)}
    assert np.abs(y[np.float32] - y[np.float64]).max() <= 1e-6 * np.abs(x).max()
    assert np.abs(y[np.float32] - x).max() <= 1e-5 * np.abs(x).max()


def test_small_changes_are_left_to_the_krylov_iterations_and_large_zones_are_not_corrected():
    K = _stiffness()
    C1 = _contact([10, 11, 12], 5)
    C2 = C1 + _contact([10, 11, 12], 6, scale=5.0) + _contact([200], 7, scale=1e-3)
    correction = LocalCorrection(spla.splu((K + C1).tocsc()).solve, N, C1, threshold=0.05)
    assert correction.preconditioner(C2) is not None
    assert correction.columns == 3  # dof 200 changed by 1e-4 of the largest change
    wide = LocalCorrection(spla.splu(K.tocsc()).solve, N, None, max_dofs=20)
    assert wide.preconditioner(_contact(list(range(30)), 8)) is None and wide.columns == 0


@pytest.mark.parametrize("method", ["superlu", "pardiso"])
def test_a_reused_factor_with_the_local_term_corrected_converges_at_once(method):
    """Newton-like: the first system ``K + C1`` is factorized; the second, ``K + C2`` with
    a stiff contact term moved to other dofs, reuses that factor. Told the local term, the
    solver corrects it exactly (one GMRES iteration with SuperLU's exact factor, a few with
    PARDISO's float32 one); not told, it needs many more."""
    if method == "pardiso":
        from toolkit.common.fem import pardiso

        if not pardiso.available():
            pytest.skip("MKL (the 'pardiso' extra) is not installed")
    K = _stiffness()
    C1, C2 = _contact([20, 21, 22, 150, 151], 9), _contact([22, 23, 24, 152, 153, 154], 10)
    b = np.random.default_rng(11).standard_normal(N)
    counts = {}
    for told in (True, False):
        solver = LinearSolver(method, reuse_rtol=1e-10, timed_budget=False, single_precision=method == "pardiso")
        solver.solve(K + C1, b, symmetric=False, local=C1 if told else None)
        x, info = solver.solve(K + C2, b, symmetric=False, local=C2 if told else None)
        assert info.reused and np.linalg.norm((K + C2) @ x - b) <= 1e-9 * np.linalg.norm(b)
        counts[told] = info.iterations
        assert solver.correction_columns == (10 if told else 0)  # 20-24, 150-154
    assert counts[True] <= (1 if method == "superlu" else 4) < counts[False], counts


def test_a_symmetric_factor_with_the_skew_part_corrected_preconditions_as_the_lu_does():
    """The LDL^T of the symmetric part of ``K + C1`` (``C1`` unsymmetric, a friction tangent),
    with the correction told that the factor holds the symmetric part of ``C1``, is the exact
    inverse of ``K + C2`` for any later ``C2`` on the corrected dofs: the skew part, local as
    friction's is, costs no accuracy."""
    K = _stiffness()
    C1, C2 = _contact([3, 4, 5, 60, 61], 1), _contact([4, 5, 6, 60, 100, 101, 102], 2)
    S1 = 0.5 * (C1 + C1.T)
    factor = spla.splu((K + S1).tocsc())  # the factor of the symmetric part
    correction = LocalCorrection(factor.solve, N, S1, threshold=0.0)
    x = np.random.default_rng(5).standard_normal(N)
    for C in (C1, C2):
        apply = correction.preconditioner(C)
        assert np.abs(apply((K + C) @ x) - x).max() <= 1e-10 * np.abs(x).max()
