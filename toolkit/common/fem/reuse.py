"""Reusing a factorization over later systems: the factor in use (:class:`StoredFactor`), which
solves its own system directly and preconditions the Krylov iterations of later ones, and the
counts that decide when to give a reuse up or to factorize ahead (:class:`ReusePolicy`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from toolkit.common.fem.factors import DIRECT
from toolkit.common.fem.factory import Factorization
from toolkit.common.fem.krylov import gmres, krylov
from toolkit.common.fem.woodbury import LocalCorrection

__all__ = ["StoredFactor", "ReusePolicy"]

#: Krylov iterations of a solve on a factor made for its own system that is not exact (float32,
#: of the symmetric part, or an AMG hierarchy)
FRESH_MAX_ITERATIONS = 500


class StoredFactor:
    """The :class:`~toolkit.common.fem.factory.Factorization` ``made`` of the system ``A``
    (``symmetric``: SPD), in use as the solver's preconditioner. ``background``: made on the
    factorize-ahead worker. A reused direct factor is corrected for the change of the solve's
    ``local`` term by a :class:`~toolkit.common.fem.woodbury.LocalCorrection` (``threshold``; its
    columns in float32 when ``single``), made at the first solve that needs it."""

    def __init__(self, made: Factorization, A: sp.csr_matrix, symmetric: bool, background: bool,
                 threshold: float, single: bool):
        self.factor, self.kind, self.exact, self.local = made.factor, made.kind, made.exact, made.local
        self.A, self.symmetric, self.background = A, symmetric, background
        self._threshold, self._single = threshold, single
        self._correction = None

    @property
    def columns(self) -> int:
        """Back-solves spent on the Woodbury correction's columns."""
        return 0 if self._correction is None else self._correction.columns

    def holds(self, A: sp.csr_matrix) -> bool:
        """Whether ``A`` equals the matrix the factor is of (same pattern and values)."""
        return (A.nnz == self.A.nnz and np.array_equal(A.indptr, self.A.indptr)
                and np.array_equal(A.indices, self.A.indices) and np.array_equal(A.data, self.A.data))

    def solve_own(self, A, b, x0, rtol: float, local=None) -> tuple[np.ndarray, int]:
        """Solve the factor's own system ``A``: directly when exact, else by Krylov iterations to
        ``rtol`` (NaN when they do not converge, for the caller's residual check to refuse)."""
        if self.kind == "amg" and self.symmetric:
            residuals = []
            x = self.factor.solve(b, x0=x0, tol=rtol, accel="cg", maxiter=FRESH_MAX_ITERATIONS, residuals=residuals)
            return x, len(residuals) - 1
        if self.exact:
            return self.factor(b), 0
        x, count = self.iterate(A, b, x0, self.symmetric, local, rtol, FRESH_MAX_ITERATIONS)
        return (x, count) if x is not None else (np.full_like(b, np.nan), count)

    def iterate(self, A, b, x0, symmetric: bool, local, rtol: float, maxiter: int) -> tuple[np.ndarray | None, int]:
        """Krylov iterations on ``A`` preconditioned by the factor: for a direct factor, corrected
        exactly for the difference between ``local`` and the local term it holds (GMRES); else CG
        when ``A`` and the factor are symmetric, GMRES otherwise. ``(x, iterations)``, ``x`` None
        when they do not reach ``rtol`` in ``maxiter``."""
        if self.kind in DIRECT and (local is not None or self.local is not None):
            if self._correction is None:
                self._correction = LocalCorrection(self.factor, A.shape[0], self.local, threshold=self._threshold,
                                                   dtype=np.float32 if self._single else np.float64)
            # with no x0, GMRES's first application is to b: solved with the new columns
            corrected, first = self._correction.preconditioner_and_solve(local, b if x0 is None else None)
            if corrected is not None:
                M = spla.LinearOperator(A.shape, matvec=corrected, dtype=float)
                return gmres(A, b, x0, M, rtol, maxiter, first=first)
        return krylov(A, b, x0, self.preconditioner(A.shape), rtol, maxiter, symmetric=symmetric and self.symmetric)

    def preconditioner(self, shape) -> spla.LinearOperator:
        """The factor or hierarchy as an approximate inverse."""
        if self.kind == "amg":
            return self.factor.aspreconditioner(cycle="V")
        return spla.LinearOperator(shape, matvec=self.factor, dtype=float)


@dataclass
class ReusePolicy:
    """When a solve gives a reuse up, and when it factorizes ahead; every choice depends on counts
    of solves and Krylov iterations (and, with ``timed_budget``, on a factorization's measured
    cost).

    Attributes
    ----------
    max_iterations : the Krylov iterations after which a reuse is abandoned for a new factorization
    timed_budget : also cap them by what a new factorization costs, in preconditioner applications
    ahead : solves after which a factor made ahead is taken into use (0: none made ahead)
    ahead_above : a factorization ahead starts only after a solve that needed more Krylov
        iterations than this, or factorized
    """

    max_iterations: int
    timed_budget: bool
    ahead: int
    ahead_above: int
    count: int = 0  # solves so far
    last_iterations: int | None = None  # the Krylov iterations of the last solve (None: it factorized)
    budget: int = 0  # the Krylov iterations a reuse may spend

    def due(self, started: int) -> bool:
        """Whether a factorization ahead started at solve ``started`` is due at the current one."""
        return self.count - started >= self.ahead

    def stale(self) -> bool:
        """Whether the factor in use is worth replacing ahead: the last solve needed more than
        ``ahead_above`` Krylov iterations, or factorized."""
        return self.last_iterations is None or self.last_iterations > self.ahead_above

    def factorized(self, factor_s: float, apply_s: float, iterations: int) -> None:
        """Set the budget of the reuses after a solve that factorized (``factor_s`` seconds) and
        solved on the new factor (``apply_s`` seconds, ``iterations``): a failed reuse never costs
        more than one extra factorization."""
        per_application = apply_s / max(iterations, 1)
        cost = factor_s + apply_s
        self.budget = int(min(self.max_iterations, cost / max(per_application, 1e-9))) \
            if self.timed_budget else self.max_iterations

    def solved(self, iterations: int, reused: bool) -> None:
        """Record the solve just made."""
        self.last_iterations = iterations if reused else None
