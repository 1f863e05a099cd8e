"""Sparse symmetric positive definite solvers for the static FE systems.

Options (measured in ``benchmarks/static_solvers.py``; SPEC.md has this machine's figures):

- ``"superlu"``: scipy's direct solver; installs everywhere; fast up to ~50k dofs,
  unusable at 150k dofs (> 3 min, > 5 GB).
- ``"amg"``: pyamg smoothed aggregation (rigid-body near-nullspace) as a
  preconditioner for conjugate gradients; the fine phantom's choice.
- ``"cholmod"``: scikit-sparse's CHOLMOD when it is installed (needs the system
  SuiteSparse); otherwise refused with a hint.
- ``"auto"``: ``superlu`` below :data:`AUTO_DIRECT_MAX_DOFS` unknowns, else ``amg``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = ["solve", "SolveInfo", "SolverError", "rigid_body_modes", "AUTO_DIRECT_MAX_DOFS", "METHODS"]

AUTO_DIRECT_MAX_DOFS = 40_000
METHODS = ("auto", "superlu", "amg", "cholmod")


class SolverError(RuntimeError):
    """A linear solve failed (singular system, no convergence)."""


@dataclass(frozen=True)
class SolveInfo:
    """What a solve did: method, iterations (0 for direct), relative residual, seconds."""

    method: str
    iterations: int
    residual: float
    seconds: float


def rigid_body_modes(points: np.ndarray) -> np.ndarray:
    """The 6 rigid-body displacement modes ``(3n, 6)`` of nodes at ``points (n, 3)``."""
    x = points - points.mean(axis=0)
    n = x.shape[0]
    B = np.zeros((n, 3, 6))
    B[:, 0, 0] = B[:, 1, 1] = B[:, 2, 2] = 1.0
    B[:, 1, 3], B[:, 2, 3] = -x[:, 2], x[:, 1]
    B[:, 0, 4], B[:, 2, 4] = x[:, 2], -x[:, 0]
    B[:, 0, 5], B[:, 1, 5] = -x[:, 1], x[:, 0]
    return B.reshape(3 * n, 6)


def solve(A: sp.spmatrix, b: np.ndarray, method: str = "auto", near_nullspace: np.ndarray | None = None,
          x0: np.ndarray | None = None, rtol: float = 1e-9) -> tuple[np.ndarray, SolveInfo]:
    """Solve ``A x = b`` for SPD ``A``.

    Parameters
    ----------
    A : (m, m) sparse SPD
    b : (m,)
    method : one of :data:`METHODS`
    near_nullspace : (m, k) rigid-body modes for AMG (in the reduced variables)
    x0 : initial guess for the iterative solver
    rtol : relative residual for AMG-CG

    Returns
    -------
    x : (m,) and :class:`SolveInfo`
    """
    if method not in METHODS:
        raise ValueError(f"unknown solver {method!r}; expected one of {METHODS}")
    if not np.isfinite(b).all():
        raise SolverError("right-hand side holds NaN/inf")
    m = A.shape[0]
    if method == "auto":
        method = "superlu" if m <= AUTO_DIRECT_MAX_DOFS else "amg"
    t0 = time.perf_counter()
    A = sp.csr_matrix(A)
    iterations = 0
    if m == 0:
        return np.zeros(0), SolveInfo(method, 0, 0.0, 0.0)
    if method == "superlu":
        try:
            # SPD: symmetric mode with diagonal pivots keeps the minimum-degree ordering of A + A^T
            # (4x faster than partial pivoting on the paper face, same fill)
            x = spla.splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                          options={"SymmetricMode": True}).solve(b)
        except RuntimeError as exc:
            raise SolverError(f"SuperLU failed ({exc}): the system is singular — is the model under-constrained?"
                              ) from exc
    elif method == "cholmod":
        try:
            from sksparse.cholmod import cholesky
        except ImportError as exc:
            raise SolverError("solver 'cholmod' needs scikit-sparse (pip install 'scikit-sparse<0.5' after "
                              "apt-get install libsuitesparse-dev); use 'amg' or 'superlu'") from exc
        x = cholesky(A.tocsc())(b)
    else:
        import pyamg

        B = near_nullspace if near_nullspace is not None else np.ones((m, 1))
        ml = pyamg.smoothed_aggregation_solver(A, B=B, symmetry="symmetric", max_coarse=500,
                                               strength=("symmetric", {"theta": 0.0}))
        residuals = []
        x = ml.solve(b, x0=x0, tol=rtol, accel="cg", maxiter=500, residuals=residuals)
        iterations = len(residuals) - 1
    bn = np.linalg.norm(b)
    res = float(np.linalg.norm(A @ x - b) / bn) if bn > 0 else 0.0
    if not np.isfinite(x).all() or res > max(1e-5, 1e3 * rtol):
        raise SolverError(f"{method} solve did not converge: relative residual {res:.2e} after {iterations} "
                          f"iterations; the system may be singular (under-constrained model)")
    return x, SolveInfo(method, iterations, res, time.perf_counter() - t0)
