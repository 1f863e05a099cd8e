"""Sparse linear solves for the FE systems of both workflows (the static face and the
quasi-static impact path): symmetric positive definite, or unsymmetric with a dominant SPD part
(the consistent tangent of slipping Coulomb friction).

:class:`LinearSolver` composes small parts, each in its own module:

- the factor backends and the choice among them (:mod:`~toolkit.common.fem.factors`: SuperLU,
  MKL PARDISO, CHOLMOD, AMG; ``auto`` by the expected fill of the factor) and the orderings
  (:mod:`~toolkit.common.fem.ordering`);
- making a system's factor, with the refactorization of a retired PARDISO factor
  (:class:`~toolkit.common.fem.factory.FactorMaker`);
- the factor in use, its direct solve and the Krylov iterations it preconditions on later
  systems, with the Woodbury correction of a ``local`` term
  (:class:`~toolkit.common.fem.reuse.StoredFactor`, :mod:`~toolkit.common.fem.woodbury`,
  :mod:`~toolkit.common.fem.krylov`);
- when to give a reuse up and when to factorize ahead
  (:class:`~toolkit.common.fem.reuse.ReusePolicy`), and the worker thread that factorizes ahead
  (:class:`~toolkit.common.fem.ahead.FactorizeAhead`).

A later system of the same size (the next lip-contact iteration, the next Newton iteration) is
solved by conjugate gradients preconditioned with the last factorization, which converges in a
few iterations when the matrix changed little (a few tied lip pairs, an updated tangent); when it
does not converge within the budget the solver refactors. An unsymmetric system
(``symmetric=False``) is solved by right-preconditioned GMRES instead.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, fields

import numpy as np
import scipy.sparse as sp

from toolkit.common.fem.ahead import FactorizeAhead
from toolkit.common.fem.factors import (
    AUTO_DIRECT_MAX_ENTRIES,
    DIRECT,
    METHODS,
    REUSED_DIRECT_MAX_ENTRIES,
    SolverError,
    choose_method,
    require_method,
    superlu,
)
from toolkit.common.fem.factory import Factorization, FactorMaker
from toolkit.common.fem.ordering import ORDERINGS, estimate_factor_entries, fill_reducing_order
from toolkit.common.fem.reuse import ReusePolicy, StoredFactor

__all__ = ["solve", "SolveInfo", "SolverError", "LinearSolver", "SolverOptions", "SolverStatistics",
           "rigid_body_modes", "estimate_factor_entries", "choose_method", "require_method", "superlu",
           "fill_reducing_order",
           "ORDERINGS", "AUTO_DIRECT_MAX_ENTRIES", "REUSED_DIRECT_MAX_ENTRIES", "METHODS", "DIRECT"]


@dataclass(frozen=True)
class SolveInfo:
    """What a solve did: method, iterations (0 for a direct solve), relative residual,
    seconds, and whether it reused an earlier factorization or hierarchy."""

    method: str
    iterations: int
    residual: float
    seconds: float
    reused: bool = False


@dataclass(frozen=True)
class SolverOptions:
    """Settings of a :class:`LinearSolver`.

    Attributes
    ----------
    method : one of :data:`METHODS`; default ``auto``
    factor_entries : expected factor size for ``auto``
        (:func:`~toolkit.common.fem.ordering.estimate_factor_entries`); None: decide by size
    rtol : relative residual of AMG-CG solves, and of the Krylov solves on a reused AMG hierarchy,
        on a float32 factor just made or on a factor of the symmetric part; default 1e-9
    reuse : precondition later systems of the same size with the stored factorization
    reuse_hierarchy : with ``reuse``, also precondition them with a stored AMG hierarchy; False
        builds a hierarchy for every new matrix. A hierarchy costs a few CG iterations to build,
        and one made for another reduction of the same stiffness (a lip pair tied or released, the
        mucosa constrained) preconditions worse than a new one: on the phantom's surfaces meshed
        at 3 mm (tet10) a reused hierarchy needs more CG iterations than a new one, or gives up
        (``benchmarks/static_meshed_speed.py``)
    max_reuse_iterations : Krylov (CG or GMRES) iterations after which a reuse is abandoned for a
        new factorization; default 60
    reuse_rtol : relative residual of the Krylov solves on a reused direct factorization; default
        1e-13, so that reusing changes the answer only at round-off level
    timed_budget : also cap those iterations by what a new factorization costs (its measured time
        over that of one preconditioner application), so that a failed reuse never costs more than
        one extra factorization; False keeps the cap fixed (reproducible choices)
    direct_max_entries : ``auto`` factorizes up to this expected factor size
        (:data:`AUTO_DIRECT_MAX_ENTRIES`; :data:`REUSED_DIRECT_MAX_ENTRIES` where many systems
        share a factorization)
    single_precision : SuperLU or PARDISO factorize in float32 and the factor only preconditions
        (every solve iterates to ``rtol``, later ones to ``reuse_rtol``): on the paper impact face
        with the deformable ball the float32 factorization and back-solve take less time than
        float64's, and a float32 direct solve alone leaves too large a relative residual to serve
        as the answer. Other methods ignore it
    ordering : SuperLU's fill-reducing ordering (:data:`ORDERINGS`); default ``nd``
    factorize_ahead : 0 factorizes only when a reuse fails. ``L > 0`` also factorizes a reused
        system on a worker thread (one at a time) and preconditions with that factor from the
        ``L``-th later solve on, waiting for it there if need be: the factor stays ``L`` to
        ``2L - 1`` systems old, chosen by the count of solves only (the same answers on any
        machine)
    direct : the direct method ``auto`` chooses (:data:`DIRECT`; ``pardiso`` falls back to
        ``superlu`` where MKL is not installed)
    factorize_ahead_above : a solve starts a factorization ahead only when the solve before it
        needed more than this many Krylov iterations, or factorized (0: always); a factor that
        still preconditions in one or two is nearly exact
    symmetric_factor : PARDISO factorizes the symmetric part ``(A + A^T) / 2`` by LDL^T instead of
        ``A`` by LU (half the factorization time and memory); an unsymmetric ``A`` is then solved
        by GMRES, the skew part of its ``local`` term taken exactly by the Woodbury correction.
        Other methods ignore it
    correction_threshold : the Woodbury correction of a reused direct factor leaves dofs whose
        change of the ``local`` term is below this fraction of the largest to the Krylov iterations
        (0: every dof the change touches); default 0.05
    max_left_out : a retired PARDISO factor is refactorized for a new system (no new analysis)
        when the entries it must leave out, all of the ``local`` term, number at most this
        fraction of that term's entries; default 1 (in a paper impact run most factors made ahead
        are then refactorizations, each cheaper than a new factorization beside the solves)
    """

    method: str = "auto"
    factor_entries: int | None = None
    rtol: float = 1e-9
    reuse: bool = True
    reuse_hierarchy: bool = True
    max_reuse_iterations: int = 60
    reuse_rtol: float = 1e-13
    timed_budget: bool = True
    direct_max_entries: int = AUTO_DIRECT_MAX_ENTRIES
    single_precision: bool = False
    ordering: str = "nd"
    factorize_ahead: int = 0
    direct: str = "superlu"
    factorize_ahead_above: int = 0
    symmetric_factor: bool = False
    correction_threshold: float = 0.05
    max_left_out: float = 1.0

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"unknown solver {self.method!r}; expected one of {METHODS}")
        if self.direct not in DIRECT:
            raise ValueError(f"unknown direct solver {self.direct!r}; expected one of {DIRECT}")
        if self.ordering not in ORDERINGS:
            raise ValueError(f"unknown ordering {self.ordering!r}; expected one of {ORDERINGS}")
        if int(self.factorize_ahead) < 0:
            raise ValueError(f"factorize_ahead {self.factorize_ahead} must be >= 0 (solves before a background "
                             "factor is used; 0 for none)")
        if int(self.factorize_ahead_above) < 0:
            raise ValueError(f"factorize_ahead_above {self.factorize_ahead_above} must be >= 0 (Krylov iterations)")
        if not 0 <= self.correction_threshold < 1:
            raise ValueError(f"correction_threshold {self.correction_threshold} must lie in [0, 1) (a fraction of "
                             "the largest change of the local term)")
        for name, kind in (("max_reuse_iterations", int), ("direct_max_entries", int), ("factorize_ahead", int),
                           ("factorize_ahead_above", int), ("single_precision", bool), ("symmetric_factor", bool),
                           ("reuse_hierarchy", bool), ("correction_threshold", float)):
            object.__setattr__(self, name, kind(getattr(self, name)))


@dataclass
class SolverStatistics:
    """Counts of a :class:`LinearSolver` over its solves."""

    factorizations: int = 0  # made in the foreground, when a reuse failed (or the first)
    background_factorizations: int = 0  # made ahead (factorize_ahead) and taken into use
    waited_s: float = 0.0  # seconds the solves waited for those
    reuses: int = 0
    krylov_iterations: int = 0
    correction_columns: int = 0  # back-solves of the Woodbury corrections (solve's ``local``)
    refactorizations: int = 0  # PARDISO factors refactorized without a new analysis


def _statistic(name: str) -> property:
    return property(lambda self: getattr(self.stats, name), doc=f"``stats.{name}``")


class LinearSolver:
    """A sparse solver that reuses its last factorization or AMG hierarchy.

    ``LinearSolver(method, factor_entries, orderings, **settings)``: the fields of
    :class:`SolverOptions` as keywords; :meth:`from_options` takes a :class:`SolverOptions`.
    ``orderings`` (a dict, system size -> nested-dissection permutation) is filled by the
    direct factorizations and read before ordering a system of a size it holds: pass one dict
    to the solvers of systems that share a pattern (the increments of one simulation). :attr:`stats` counts
    factorizations, reuses, Krylov iterations and the wait for the worker thread (also read as
    attributes: ``solver.factorizations``).
    """

    factorizations = _statistic("factorizations")
    background_factorizations = _statistic("background_factorizations")
    waited_s = _statistic("waited_s")
    reuses = _statistic("reuses")
    krylov_iterations = _statistic("krylov_iterations")
    correction_columns = _statistic("correction_columns")
    refactorizations = _statistic("refactorizations")

    def __init__(self, method: str = "auto", factor_entries: int | None = None, orderings: dict | None = None,
                 **settings):
        options = SolverOptions(method, factor_entries, **settings)
        self.options = options
        self.stats = SolverStatistics()
        self._maker = FactorMaker(options, self.stats, orderings)
        self._ahead = FactorizeAhead(self._maker, self.stats)
        self._policy = ReusePolicy(options.max_reuse_iterations, options.timed_budget, options.factorize_ahead,
                                   options.factorize_ahead_above)
        self._stored: StoredFactor | None = None

    def __setattr__(self, name: str, value) -> None:
        if name in SolverOptions.__dataclass_fields__:
            raise AttributeError(f"LinearSolver's {name!r} is set at construction: "
                                 f"LinearSolver(..., {name}={value!r}) or LinearSolver.from_options(...)")
        super().__setattr__(name, value)

    @classmethod
    def from_options(cls, options: SolverOptions) -> LinearSolver:
        """A solver with ``options``."""
        return cls(**{f.name: getattr(options, f.name) for f in fields(options)})

    def solve(self, A: sp.spmatrix, b: np.ndarray, near_nullspace: np.ndarray | None = None,
              x0: np.ndarray | None = None, symmetric: bool = True,
              local: sp.spmatrix | None = None, rtol: float | None = None,
              coarse_space=None) -> tuple[np.ndarray, SolveInfo]:
        """Solve ``A x = b`` (``A`` (m, m) sparse, ``b`` (m,)); returns ``x`` and :class:`SolveInfo`.

        ``A`` is SPD when ``symmetric``. Otherwise it may be unsymmetric with a dominant SPD part
        (a consistent friction tangent): SuperLU and PARDISO factorize ``A`` itself (PARDISO its
        symmetric part with ``symmetric_factor``), CHOLMOD and AMG its symmetric part
        ``(A + A^T) / 2``, which then preconditions GMRES on ``A``; a reused factorization
        preconditions GMRES instead of CG.

        ``near_nullspace`` (m, k): the rigid-body modes for AMG. ``x0`` (m,): initial guess of
        the Krylov iterations.

        ``local`` (m, m) sparse: the part of ``A`` that lives on few dofs and changes much from
        one system to the next (penalty contact). A reused SuperLU or PARDISO factorization then
        takes the change of that part since it was made exactly, by a Woodbury correction on
        its dofs (:mod:`toolkit.common.fem.woodbury`), and GMRES iterates.

        ``rtol``: the relative residual of this solve's Krylov iterations, in place of the
        solver's ``rtol`` and ``reuse_rtol`` (an inexact Newton's forcing term).

        ``coarse_space``: a :class:`~toolkit.common.fem.coarse.CoarseSpace` (a quadratic mesh's
        corner nodes in ``A``'s variables), or a function of no argument that makes it (called only
        when a new AMG hierarchy is built): that hierarchy's first coarsening.
        """
        if not np.isfinite(b).all():
            raise SolverError("right-hand side holds NaN/inf")
        if rtol is not None and not 0 < rtol < 1:
            raise ValueError(f"rtol {rtol} must lie in (0, 1)")
        o, policy, ahead = self.options, self._policy, self._ahead
        fresh_rtol, reuse_rtol = (o.rtol, o.reuse_rtol) if rtol is None else (float(rtol), float(rtol))
        t0 = time.perf_counter()
        if A.shape[0] == 0:
            return np.zeros(0), SolveInfo("none", 0, 0.0, 0.0)
        A = sp.csr_matrix(A)  # the Krylov products; a factorization converts what it needs
        policy.count += 1
        if ahead.pending is not None and policy.due(ahead.pending.started):
            self._take_pending()
        x, iterations, reused = None, 0, False
        stored = self._stored
        if o.reuse and stored is not None and stored.A.shape == A.shape \
                and (o.reuse_hierarchy or stored.kind != "amg" or stored.holds(A)):
            if o.factorize_ahead and ahead.pending is None and policy.stale() \
                    and stored.kind in ("superlu", "pardiso", "cholmod"):
                # started before this solve's Krylov iterations, so that the worker has them too
                ahead.start(A, symmetric, near_nullspace, local, policy.count)
            x, iterations = self._reuse(A, b, x0, symmetric, local, fresh_rtol, reuse_rtol)
            reused = x is not None
        del stored  # a factor replaced below is freed where it was made: no reference held here
        if x is None:
            x, iterations = self._factorize_and_solve(A, b, near_nullspace, x0, symmetric, local, fresh_rtol,
                                                      coarse_space)
        else:
            self.stats.reuses += 1
        bn = np.linalg.norm(b)
        res = float(np.linalg.norm(A @ x - b) / bn) if bn > 0 else 0.0
        # a loose rtol (an inexact Newton's 1e-2) still rejects a solve that did not halve the residual
        limit = max(1e-5, min(1e3 * fresh_rtol, 0.5), 10.0 * reuse_rtol if reused else 0.0)
        kind = self._stored.kind
        if not np.isfinite(x).all() or res > limit:
            raise SolverError(f"{kind} solve did not converge: relative residual {res:.2e} after {iterations} "
                              f"iterations; the system may be singular (under-constrained model)")
        policy.solved(iterations, reused)
        self.stats.krylov_iterations += iterations
        return x, SolveInfo(kind, iterations, res, time.perf_counter() - t0, reused)

    def close(self) -> None:
        """Free the factors made ahead and end the worker thread (call when done with a solver
        that factorizes ahead; a later solve starts afresh)."""
        if not self._ahead.running:
            return
        self._ahead.drop()
        if self._stored is not None and self._stored.background:
            self._install(None, None, True, background=False)
        self._ahead.close()
        self._maker.close()

    def _reuse(self, A, b, x0, symmetric, local, fresh_rtol: float, reuse_rtol: float) -> tuple[np.ndarray | None, int]:
        """Solve on the stored factor: directly when it is of ``A``, else by Krylov iterations
        within the policy's budget; ``x`` None when they do not converge."""
        stored = self._stored
        if stored.holds(A):
            return stored.solve_own(A, b, x0, fresh_rtol, local)
        if self._policy.budget < 2:
            return None, 0
        before = stored.columns
        x, iterations = stored.iterate(A, b, x0, symmetric, local, fresh_rtol if stored.kind == "amg" else reuse_rtol,
                                       self._policy.budget)
        self.stats.correction_columns += stored.columns - before
        return x, iterations

    def _factorize_and_solve(self, A, b, near_nullspace, x0, symmetric, local, rtol,
                             coarse_space=None) -> tuple[np.ndarray, int]:
        """Solve on a new factor of ``A`` (the one being made ahead for it, or a foreground one),
        and set the budget of the reuses that follow."""
        ahead = self._ahead
        t_factor = time.perf_counter()
        if ahead.pending is not None and ahead.pending.A is A:  # being factorized already
            self._take_pending()
        ahead.drop()  # older than this system
        if self._stored is None or self._stored.A is not A:
            if self.options.factorize_ahead:
                ahead.spare_alongside(A, symmetric, near_nullspace)
            self._install(self._maker.make(A, symmetric, near_nullspace, local, coarse_space), A, symmetric,
                          background=False)
            self.stats.factorizations += 1
        t_apply = time.perf_counter()
        x, iterations = self._stored.solve_own(A, b, x0, rtol, local)
        self._policy.factorized(t_apply - t_factor, time.perf_counter() - t_apply, iterations)
        return x, iterations

    def _take_pending(self) -> None:
        """Wait for the factor made ahead and precondition with it from now on."""
        made, pending = self._ahead.take()
        if made is not None:
            self._install(made, pending.A, pending.symmetric, background=True)
            self.stats.background_factorizations += 1

    def _install(self, made: Factorization | None, A, symmetric: bool, background: bool) -> None:
        """Precondition with ``made``, a factorization of ``A``, from now on (None: with nothing).
        The factor it replaces is freed on the worker when it was made there, or kept as the
        spare when it is PARDISO's."""
        old = self._stored
        self._stored = None if made is None else StoredFactor(made, A, symmetric, background,
                                                              self.options.correction_threshold,
                                                              self.options.single_precision)
        if old is None:
            return
        if old.kind == "pardiso":
            self._maker.retire(old.factor)
        elif old.background:
            box = [old]
            del old
            self._ahead.free(box)


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
    """Solve ``A x = b`` for SPD ``A`` once (no reuse; ``auto`` decides by size).

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
    return LinearSolver(method, rtol=rtol, reuse=False).solve(A, b, near_nullspace, x0)
