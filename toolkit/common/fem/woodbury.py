"""An exact correction of a reused factorization for the part of a matrix that lives on few
dofs and changes a lot (Sherman-Morrison-Woodbury): penalty contact in a Newton tangent.

The quasi-static impact path preconditions each Newton system with the factorization of a
tangent a few iterations old (:class:`~toolkit.common.fem.solvers.LinearSolver` reuses it, and
factorizes newer ones on a second thread). Penalty contact puts stiff springs on few of the
paper face's dofs (docs/solvers.md), far stiffer than the tissue there, and those entries change
at every iteration (contact set, stick and slip). On the paper face, with factors a few systems
old, GMRES needs as few iterations to the linear tolerance with this correction as with a factor
whose contact part is the current one, and far fewer than with the factor as it is; the
correction needs no new factorization.

With ``F`` the factor of ``A_F = K_F + C_F`` and the system ``A = K + C``, the preconditioner
is the exact inverse of ``A_F + E_R D E_R^T``: ``D`` is ``C - C_F`` on the dofs ``R`` where it
is significant (an entry of at least ``threshold`` times its largest; ``E_R`` their unit
columns), so only the material part ``K - K_F`` and the small contact changes stay stale::

    M^-1 r = y - W (I + D G)^-1 D y_R,   y = F^-1 r,   W = F^-1 E_R,   G = W_R

Each column of ``W`` costs a back-solve (done in batches) and is kept for the factor's life,
so a contact zone that moves little costs little. The threshold trades columns for Krylov
iterations: a lower one makes more columns and fewer iterations.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

__all__ = ["LocalCorrection", "MAX_CORRECTED_DOFS"]

#: above this many dofs (a contact zone of ~170 nodes) the correction is skipped: the columns
#: would cost more back-solves than the Krylov iterations they save, and ``W`` 200 MB
MAX_CORRECTED_DOFS = 512


class LocalCorrection:
    """Woodbury corrections of one factor ``F`` (callable ``b -> F^-1 b``, ``b`` (n,) or
    (n, k)) of a matrix whose local part was ``local`` ((n, n) sparse, or None for none).

    :meth:`preconditioner` gives the corrected inverse for a later local part; the columns
    ``F^-1 e_j`` it needs are computed once and kept (``columns`` counts them). ``threshold``:
    dofs whose change is below this fraction of the largest entry of the change are left to
    the Krylov iterations (0: every dof the change touches). ``max_dofs``: a change on more
    dofs is not corrected. ``dtype``: of the stored columns; float32 for a float32 factor,
    whose columns hold no more digits (half the memory and the time of applying them).
    """

    def __init__(self, factor: Callable[[np.ndarray], np.ndarray], n: int, local: sp.spmatrix | None,
                 max_dofs: int = MAX_CORRECTED_DOFS, threshold: float = 0.05, dtype=np.float64):
        self.factor, self.n, self.max_dofs, self.threshold = factor, int(n), int(max_dofs), float(threshold)
        self.local = None if local is None else sp.csr_matrix(local)
        self._slot = np.full(self.n, -1, dtype=np.int64)  # dof -> its column of W
        self._Wt = np.empty((0, self.n), dtype=dtype)  # W transposed: row k is the column in slot k
        self.columns = 0

    def preconditioner(self, local: sp.spmatrix | None) -> Callable[[np.ndarray], np.ndarray] | None:
        """``r -> M^-1 r`` for a matrix whose local part is now ``local`` (None: none), or None
        when the local part has not changed (the factor alone is right) or changed on more than
        ``max_dofs`` dofs."""
        return self.preconditioner_and_solve(local, None)[0]

    def preconditioner_and_solve(self, local: sp.spmatrix | None,
                                 rhs: np.ndarray | None) -> tuple[Callable | None, np.ndarray | None]:
        """:meth:`preconditioner` and ``M^-1 rhs`` (``rhs`` (n,), a Krylov solve's first
        application), whose back-solve joins that of the new columns in one multi-right-hand-side
        call (a column in a batch costs a fraction of a lone back-solve). The second
        is None when ``rhs`` is, when nothing is corrected, or when no column is new."""
        delta = _difference(local, self.local, self.n)
        if delta.nnz == 0:
            return None, None
        dofs = _significant_dofs(delta, self.threshold)
        if dofs.size > self.max_dofs:
            return None, None
        y_rhs = self._add_columns(dofs[self._slot[dofs] < 0], rhs)
        cols = self._slot[dofs]
        G = self._Wt[np.ix_(cols, dofs)].T.astype(np.float64)  # (F^-1)_RR: only the k x k block read
        D = delta[dofs][:, dofs].toarray()
        lu = sla.lu_factor(np.eye(dofs.size) + D @ G)
        Wt = self._Wt[:self.columns]
        factor = self.factor

        def corrected(y: np.ndarray) -> np.ndarray:  # M^-1 r from y = F^-1 r
            z = np.zeros(Wt.shape[0], dtype=Wt.dtype)
            z[cols] = sla.lu_solve(lu, D @ y[dofs])
            return y - z @ Wt

        def apply(r: np.ndarray) -> np.ndarray:
            return corrected(factor(r))

        return apply, None if y_rhs is None else corrected(y_rhs)

    def _add_columns(self, dofs: np.ndarray, rhs: np.ndarray | None = None) -> np.ndarray | None:
        """``F^-1 e_j`` for the new ``dofs``, in one multi-right-hand-side back-solve; returns
        ``F^-1 rhs`` from the same call (None without ``rhs`` or new dofs)."""
        if dofs.size == 0:
            return None
        if self.columns + dofs.size > self._Wt.shape[0]:
            grown = np.empty((max(2 * self._Wt.shape[0], self.columns + dofs.size, 32), self.n), dtype=self._Wt.dtype)
            grown[:self.columns] = self._Wt[:self.columns]
            self._Wt = grown
        k = dofs.size
        E = np.zeros((self.n, k + (rhs is not None)))
        E[dofs, np.arange(k)] = 1.0
        if rhs is not None:
            E[:, k] = rhs
        Y = np.asarray(self.factor(E)).reshape(self.n, E.shape[1])
        self._Wt[self.columns:self.columns + k] = Y[:, :k].T
        self._slot[dofs] = np.arange(self.columns, self.columns + k)
        self.columns += k
        return None if rhs is None else Y[:, k].copy()


def _significant_dofs(M: sp.csr_matrix, threshold: float) -> np.ndarray:
    """The dofs (sorted) whose row or column of ``M`` holds an entry of at least ``threshold``
    times ``M``'s largest in magnitude."""
    size = np.zeros(M.shape[0])
    if M.nnz == 0:
        return np.zeros(0, dtype=np.int64)
    magnitude = np.abs(M.data)
    np.maximum.at(size, np.repeat(np.arange(M.shape[0]), np.diff(M.indptr)), magnitude)
    np.maximum.at(size, M.indices, magnitude)
    return np.flatnonzero((size > 0) & (size >= threshold * magnitude.max()))


def _difference(a: sp.spmatrix | None, b: sp.spmatrix | None, n: int) -> sp.csr_matrix:
    """``a - b`` as CSR without stored zeros (None is the zero matrix)."""
    if a is None and b is None:
        return sp.csr_matrix((n, n))
    if b is None:
        d = sp.csr_matrix(a, copy=True)
    elif a is None:
        d = -sp.csr_matrix(b)
    else:
        d = sp.csr_matrix(a) - sp.csr_matrix(b)
    d.eliminate_zeros()
    return d
