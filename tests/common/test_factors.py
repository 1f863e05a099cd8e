"""The factor backends of :mod:`toolkit.common.fem.factors` on their own, and the Krylov
iterations of :mod:`toolkit.common.fem.krylov`: every backend solves a small SPD system and one
with an unsymmetric part (a friction-like block) to round-off, through one interface."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from toolkit.common.errors import ToolkitError
from toolkit.common.fem import pardiso
from toolkit.common.fem.factors import Factor, Refactorizable, SolverError, factorize, superlu
from toolkit.common.fem.krylov import gmres, krylov
from toolkit.common.fem.ordering import fill_reducing_order


def _spd(n=6):
    """A 3-dof-per-node SPD matrix on an ``n^3`` grid (a 7-point Laplacian times a 3x3 block)."""
    one = sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    eye = sp.identity(n)
    lap = sp.kron(sp.kron(one, eye), eye) + sp.kron(sp.kron(eye, one), eye) + sp.kron(sp.kron(eye, eye), one)
    block = np.array([[3.0, 1.0, 0.5], [1.0, 3.0, 1.0], [0.5, 1.0, 3.0]])
    return sp.kron(lap + 0.01 * sp.identity(n ** 3), block).tocsr()


def _unsymmetric(A, seed=0, count=20):
    """``A`` plus rank-one unsymmetric 3x3 blocks on ``count`` nodes' diagonals (slipping friction)."""
    rng = np.random.default_rng(seed)
    nodes = rng.choice(A.shape[0] // 3, count, replace=False)
    m, n = rng.standard_normal((count, 3)), rng.standard_normal((count, 3))
    blocks = 0.2 * m[:, :, None] * n[:, None, :]
    dofs = 3 * nodes[:, None] + np.arange(3)
    rows = np.broadcast_to(dofs[:, :, None], blocks.shape)
    cols = np.broadcast_to(dofs[:, None, :], blocks.shape)
    return (A + sp.csr_matrix((blocks.ravel(), (rows.ravel(), cols.ravel())), shape=A.shape)).tocsr()


needs_mkl = pytest.mark.skipif(not pardiso.available(), reason="MKL (the 'pardiso' extra) is not installed")
BACKENDS = [("superlu", "nd"), ("superlu", "mmd"), pytest.param("pardiso", "nd", marks=needs_mkl)]


@pytest.mark.parametrize("method,ordering", BACKENDS)
@pytest.mark.parametrize("unsymmetric", [False, True])
def test_a_direct_factor_solves_to_round_off(method, ordering, unsymmetric):
    """Backward error below 1e-10 for one and for three right-hand sides, float64 results, and
    the :class:`Factor` interface (``shape``, ``single``, ``solve`` equal to the call)."""
    A = _spd()
    if unsymmetric:
        A = _unsymmetric(A)
        assert abs(A - A.T).max() > 0.01
    factor = factorize(A, method, ordering=fill_reducing_order(A) if ordering == "nd" else ordering)
    assert isinstance(factor, Factor) and factor.shape == A.shape and not factor.single
    b = np.random.default_rng(1).standard_normal((A.shape[0], 3))
    x = factor(b[:, 0])
    assert x.dtype == np.float64 and np.linalg.norm(A @ x - b[:, 0]) <= 1e-10 * np.linalg.norm(b[:, 0])
    X = factor.solve(b)
    assert X.shape == b.shape and np.linalg.norm(A @ X - b) <= 1e-10 * np.linalg.norm(b)
    if method == "pardiso":
        assert isinstance(factor, Refactorizable)
        factor.close()


@pytest.mark.parametrize("method", ["superlu", pytest.param("pardiso", marks=needs_mkl)])
def test_a_float32_factor_is_an_approximate_inverse(method):
    """A float32 factor returns float64 answers within single precision's reach (relative
    residual between round-off and 1e-4), a preconditioner rather than a solver."""
    A = _spd()
    factor = factorize(A, method, single=True, ordering=fill_reducing_order(A))
    b = np.random.default_rng(2).standard_normal(A.shape[0])
    x = factor(b)
    residual = np.linalg.norm(A @ x - b) / np.linalg.norm(b)
    assert factor.single and x.dtype == np.float64 and 1e-12 < residual < 1e-4


def test_superlu_reports_its_entries_and_refuses_a_singular_matrix():
    A = _spd(4)
    assert superlu(A).entries >= A.nnz // 2
    singular = A.tolil()
    singular[5, :] = 0.0
    singular[:, 5] = 0.0
    with pytest.raises(SolverError, match="singular") as caught:
        superlu(singular.tocsr(), "mmd")
    assert isinstance(caught.value, ToolkitError) and isinstance(caught.value, RuntimeError)
    with pytest.raises(ValueError, match="unknown direct method 'amg'"):
        factorize(A, "amg")


def test_cholmod_solves_or_is_refused_with_a_hint():
    """CHOLMOD where scikit-sparse is installed (SPD to round-off), else a :class:`SolverError`
    that says what to install."""
    A, b = _spd(4), np.ones(192)
    try:
        factor = factorize(A, "cholmod")
    except SolverError as exc:
        assert "scikit-sparse" in str(exc)
        return
    assert np.linalg.norm(A @ factor(b) - b) <= 1e-10 * np.linalg.norm(b)


@pytest.mark.parametrize("symmetric", [True, False])
def test_krylov_iterations_reach_the_true_residual(symmetric):
    """CG (SPD) and right-preconditioned GMRES (unsymmetric), preconditioned by the factor of a
    nearby matrix, stop at a true relative residual below ``rtol``; GMRES given ``M^-1 b`` as its
    first application takes the same path."""
    A = _spd(5)
    B = (A + sp.diags(np.linspace(0.0, 0.5, A.shape[0]))).tocsr()
    if not symmetric:
        B = _unsymmetric(B)
    factor = superlu(A)
    M = spla.LinearOperator(A.shape, matvec=factor, dtype=float)
    b = np.random.default_rng(3).standard_normal(A.shape[0])
    x, iterations = krylov(B, b, None, M, 1e-10, 100, symmetric=symmetric)
    assert 1 <= iterations < 100 and np.linalg.norm(B @ x - b) <= 1e-10 * np.linalg.norm(b)
    if not symmetric:
        y, again = gmres(B, b, None, M, 1e-10, 100, first=factor(b))
        assert again == iterations and np.allclose(y, x, rtol=1e-12, atol=0)
        assert gmres(B, b, None, M, 1e-10, 1)[0] is None  # one iteration is not enough
