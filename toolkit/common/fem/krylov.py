"""Preconditioned Krylov iterations on a sparse system: conjugate gradients for a symmetric one,
right-preconditioned GMRES (judged by the true residual) for an unsymmetric one."""

from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla

__all__ = ["krylov", "gmres"]


def krylov(A, b, x0, M, rtol: float, maxiter: int, symmetric: bool) -> tuple[np.ndarray | None, int]:
    """Preconditioned CG (``symmetric``) or :func:`gmres` to the relative residual ``rtol``
    in at most ``maxiter`` iterations; ``(x, iterations)``, ``x`` None when it did not converge."""
    if not symmetric:
        return gmres(A, b, x0, M, rtol, maxiter)
    count = [0]

    def callback(_):
        count[0] += 1

    x, info = spla.cg(A, b, x0=x0, rtol=rtol, maxiter=maxiter, M=M, callback=callback)
    return (x, count[0]) if info == 0 else (None, count[0])


def gmres(A, b, x0, M, rtol: float, maxiter: int, first: np.ndarray | None = None) -> tuple[np.ndarray | None, int]:
    """Right-preconditioned GMRES without restarts: ``x = x0 + M^-1 V y`` minimizes the true
    residual ``|b - A x|`` over the Krylov space, so it stops when that residual is below
    ``rtol |b|``. (scipy's ``gmres`` preconditions on the left and judges the preconditioned
    residual, which a stale factorization makes a poor proxy: with one restart cycle it fails
    most reuses on the coarse impact face, which this one solves in a few iterations each.)
    ``first``: ``M^-1 b`` when already known (``x0`` must then be None). Returns
    ``(x, iterations)``, ``x`` None after ``maxiter`` iterations."""
    if first is not None and x0 is not None:
        raise ValueError("first is M^-1 b, the first application only without x0")
    x = np.zeros_like(b) if x0 is None else np.array(x0, dtype=float)
    r = b - A @ x
    beta, target = float(np.linalg.norm(r)), rtol * float(np.linalg.norm(b))
    if beta <= target:
        return x, 0
    V = np.empty((maxiter + 1, b.size))  # orthonormal Krylov basis
    Z = np.empty((maxiter, b.size))  # its preconditioned images
    H = np.zeros((maxiter + 1, maxiter))  # Hessenberg matrix of the Arnoldi process
    V[0] = r / beta
    for k in range(maxiter):
        Z[k] = first / beta if k == 0 and first is not None else M.matvec(V[k])
        w = A @ Z[k]
        for _ in range(2):  # classical Gram-Schmidt, twice (as accurate as modified, vectorised)
            h = V[:k + 1] @ w
            w -= h @ V[:k + 1]
            H[:k + 1, k] += h
        H[k + 1, k] = np.linalg.norm(w)
        rhs = np.zeros(k + 2)
        rhs[0] = beta
        y = np.linalg.lstsq(H[:k + 2, :k + 1], rhs, rcond=None)[0]
        residual = float(np.linalg.norm(H[:k + 2, :k + 1] @ y - rhs))
        if residual <= target or H[k + 1, k] <= 1e-14 * beta:
            return x + y @ Z[:k + 1], k + 1
        V[k + 1] = w / H[k + 1, k]
    return None, maxiter
