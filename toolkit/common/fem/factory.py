"""Making the factor of a system for :class:`~toolkit.common.fem.solvers.LinearSolver`: the method
for its size, the ordering shared by the systems of one size, and the refactorization of a
retired PARDISO factor (the *spare*) instead of a new analysis. Safe to call from the solve
thread and the factorize-ahead worker at once."""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from toolkit.common.fem.factors import DIRECT, Refactorizable, amg_hierarchy, choose_method, factorize
from toolkit.common.fem.ordering import fill_reducing_order

__all__ = ["Factorization", "FactorMaker"]


@dataclass(frozen=True, eq=False)
class Factorization:
    """A factor (or AMG hierarchy) just made for a system ``A``.

    Attributes
    ----------
    factor : the :class:`~toolkit.common.fem.factors.Factor`, or pyamg's hierarchy for ``amg``
    kind : the method that made it (:data:`~toolkit.common.fem.factors.METHODS` but ``auto``)
    exact : whether ``factor(b)`` solves ``A`` exactly (not float32, not of a symmetric part)
    local : the part of the solve's ``local`` term the factor holds (None: none)
    """

    factor: object
    kind: str
    exact: bool
    local: sp.spmatrix | None


class FactorMaker:
    """Makes factors with the settings of ``options`` (a
    :class:`~toolkit.common.fem.solvers.SolverOptions`), counting PARDISO refactorizations in
    ``stats.refactorizations``."""

    def __init__(self, options, stats, orderings: dict | None = None):
        self.options, self.stats = options, stats
        # system size -> its nested-dissection ordering (a dict shared with other makers when given)
        self._orderings = {} if orderings is None else orderings
        self._spare = None  # a retired PARDISO factor, for the next one to refactorize
        self._lock = threading.Lock()

    def kind(self, A: sp.spmatrix) -> str:
        """The method for ``A`` (``auto`` resolved)."""
        o = self.options
        return choose_method(o.method, A.shape[0], o.factor_entries, o.direct_max_entries, o.direct)

    def make(self, A: sp.csr_matrix, symmetric: bool, near_nullspace: np.ndarray | None,
             local: sp.spmatrix | None = None, coarse_space=None) -> Factorization:
        """The :class:`Factorization` of ``A``: of ``A`` itself, or of its symmetric part (AMG,
        CHOLMOD on an unsymmetric ``A``; PARDISO with ``symmetric_factor``, whose ``local`` is then
        the symmetric part of ``local``). With PARDISO the spare is refactorized on its analysed
        pattern when that holds all of ``A``, or all but some entries of ``local`` (at most
        ``max_left_out`` of its entries): those are left out of the factor and out of the
        returned ``local``, so that the Woodbury correction takes them. ``coarse_space``: the first
        coarsening of an AMG hierarchy of a symmetric ``A``
        (:func:`~toolkit.common.fem.factors.amg_hierarchy`)."""
        o = self.options
        kind = self.kind(A)
        single = o.single_precision and kind in DIRECT
        halves = kind == "pardiso" and o.symmetric_factor  # LDL^T of the symmetric part
        own = symmetric or (kind in DIRECT and not halves)  # a factor of A itself
        if halves and local is not None:
            local = 0.5 * (local + local.T)
        if kind == "pardiso":
            made = self._refactorized(A, local, single, halves)
            if made is not None:
                factor, left = made
                return Factorization(factor, kind, own and not single and left.nnz == 0,
                                     local - left if left.nnz else local)
        if kind == "amg":
            hierarchy = amg_hierarchy(A, near_nullspace, coarse_space) if symmetric \
                else amg_hierarchy(0.5 * (A + A.T), near_nullspace)
            return Factorization(hierarchy, kind, own, local)
        ordering = self.ordering(A) if kind in DIRECT and o.ordering == "nd" else o.ordering
        factor = factorize(A if own or halves else 0.5 * (A + A.T), kind, single, ordering, symmetric_part=halves)
        return Factorization(factor, kind, own and not single, local)

    def _refactorized(self, A, local, single: bool, halves: bool):
        """``(spare, left out)`` with the spare refactorized for ``A``, or None (no spare, or one
        that does not fit, which is then freed)."""
        with self._lock:
            spare, self._spare = self._spare, None
        if spare is None:
            return None
        if spare.single == single and spare.symmetric == halves and spare.shape == A.shape:
            # without a local term nothing may be left out: A must fit the analysed pattern
            left = spare.refactorize(A, local, 0 if local is None else int(self.options.max_left_out * local.nnz))
            if left is not None:
                with self._lock:  # the worker and a foreground factorization may count at once
                    self.stats.refactorizations += 1
                return spare, left
        spare.close()
        return None

    def retire(self, factor: Refactorizable) -> None:
        """Keep a PARDISO factor no solve uses any more as the spare (one at most; another is
        freed)."""
        with self._lock:
            keep = self._spare is None
            if keep:
                self._spare = factor
        if not keep:
            factor.close()

    def close(self) -> None:
        """Free the spare."""
        with self._lock:
            spare, self._spare = self._spare, None
        if spare is not None:
            spare.close()

    def ordering(self, A: sp.spmatrix) -> np.ndarray:
        """The nested-dissection ordering of ``A``'s size, computed for the first system of that
        size: it serves every later one, as they share the mesh's pattern (the increments of a
        static simulation, on one shared dict). Contact couplings added later cost little fill
        against an ordering of their own, and ordering each system would cost time, most of it
        holding the GIL."""
        perm = self._orderings.get(A.shape[0])
        if perm is None:
            perm = self._orderings[A.shape[0]] = fill_reducing_order(A)
        return perm
