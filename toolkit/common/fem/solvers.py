"""Sparse solvers for the FE systems of both workflows (the static face and the quasi-static
impact path): symmetric positive definite, or unsymmetric with a dominant SPD part (the
consistent tangent of slipping Coulomb friction).

Options (measured in ``benchmarks/static_solvers.py``; SPEC.md has this machine's figures):

- ``"superlu"``: scipy's direct solver in symmetric mode (diagonal pivots), on METIS's
  nested-dissection ordering of ``A + A^T`` (:func:`superlu`; SuperLU's own minimum degree
  as ``ordering="mmd"``); installs everywhere; fast while the factor stays small (the thin
  phantom shell up to ~10^4 dofs; a bulky 26k-dof tet block: 1.3 s and 560 MiB, against
  6.7 s and 1.0 GiB with minimum degree), hopeless when it does not (the fine phantom with
  minimum degree: > 3 min, > 5 GB).
- ``"pardiso"``: Intel MKL PARDISO (:mod:`toolkit.common.fem.pardiso`; the ``pardiso``
  extra) on the same ordering: on the paper impact face (float32) factorization 1.1 s and
  back-solve 0.021 s against SuperLU's 1.7 s and 0.030 s on this machine. ``auto`` takes it
  where a caller asks for it (``direct="pardiso"``, the implicit impact path) and MKL is
  installed.
- ``"amg"``: pyamg smoothed aggregation (rigid-body near-nullspace) as a
  preconditioner for conjugate gradients.
- ``"cholmod"``: scikit-sparse's CHOLMOD when it is installed (needs the system
  SuiteSparse); otherwise refused with a hint.
- ``"auto"``: by the **expected fill** of the factor, not the number of unknowns:
  ``superlu`` (or the ``direct`` method asked for) when :func:`estimate_factor_entries`
  (the envelope of a reverse Cuthill-McKee ordering of the mesh's node graph, times 9 for
  the 3x3 blocks) is below :data:`AUTO_DIRECT_MAX_ENTRIES`, else ``amg``. A shell stays
  direct up to much larger sizes than a bulky mesh of the same number of dofs.

:class:`LinearSolver` remembers its last factorization or AMG hierarchy. A later
system of the same size (the next lip-contact iteration, the next Newton iteration) is
solved by conjugate gradients preconditioned with it, which converges in a few
iterations when the matrix changed little (a few tied lip pairs, an updated tangent);
when it does not converge within ``max_reuse_iterations`` the solver refactors. An
unsymmetric system (``symmetric=False``) is solved by right-preconditioned GMRES instead.
With ``factorize_ahead`` it also factorizes reused systems in a background thread, so that
the preconditioner stays a few systems old along a Newton path whose matrix keeps changing.
"""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from toolkit.common.fem.woodbury import LocalCorrection

__all__ = ["solve", "SolveInfo", "SolverError", "LinearSolver", "rigid_body_modes", "estimate_factor_entries",
           "choose_method", "superlu", "fill_reducing_order", "ORDERINGS", "AUTO_DIRECT_MAX_ENTRIES",
           "REUSED_DIRECT_MAX_ENTRIES", "METHODS", "DIRECT"]

log = logging.getLogger(__name__)

#: entries of the factor below which ``auto`` factorizes (SuperLU): ~30 M entries ~ 0.5 GB,
#: a few seconds here; the paper phantom is ~4 M, the fine phantom ~2 G, a 26k-dof bulky
#: tet mesh ~40 M (``benchmarks/static_solvers.py``)
AUTO_DIRECT_MAX_ENTRIES = 30_000_000
#: the same limit for a solver that will reuse its factorization over many systems (the
#: implicit impact path's Newton iterations): on the paper face with the deformable ball
#: (54k dofs, estimate 64 M, SuperLU L+U 58 M entries, 1.9 GB, 15 s) one factorization reused
#: as a CG preconditioner ran a 2-step probe in 55 s against 176 s for AMG-CG, whose hierarchy
#: the contact springs spoil (12 set-ups in 14 solves, 8.6 s per solve)
REUSED_DIRECT_MAX_ENTRIES = 150_000_000
METHODS = ("auto", "superlu", "pardiso", "amg", "cholmod")
#: the direct solvers ``auto`` may choose
DIRECT = ("superlu", "pardiso")


class SolverError(RuntimeError):
    """A linear solve failed (singular system, no convergence)."""


@dataclass(frozen=True)
class SolveInfo:
    """What a solve did: method, iterations (0 for a direct solve), relative residual,
    seconds, and whether it reused an earlier factorization or hierarchy."""

    method: str
    iterations: int
    residual: float
    seconds: float
    reused: bool = False


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


def estimate_factor_entries(node_graph: sp.spmatrix, block: int = 3) -> int:
    """Expected entries of the Cholesky factor of a ``block``-dof-per-node stiffness.

    The envelope (profile) of the node graph after a reverse Cuthill-McKee ordering,
    times ``block**2``: an upper bound of the fill of a profile factorization and, on mesh
    graphs, within a small factor of a minimum-degree one. Thin shells (a face) have a
    narrow envelope; bulky 3D meshes a wide one.

    Parameters
    ----------
    node_graph : (n, n) sparse, nonzero where two nodes share an element
    block : dofs per node
    """
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    g = sp.csr_matrix(node_graph)
    n = g.shape[0]
    if n == 0:
        return 0
    perm = reverse_cuthill_mckee(g, symmetric_mode=True)
    rank = np.empty(n, dtype=np.int64)
    rank[perm] = np.arange(n)
    rows = np.repeat(np.arange(n), np.diff(g.indptr))
    first = rank.copy()  # per node: smallest rank among itself and its neighbours
    np.minimum.at(first, rows, rank[g.indices])
    return int((np.sum(rank - first) + n) * block * block)


def choose_method(method: str, n_dofs: int, factor_entries: int | None,
                  direct_max_entries: int = AUTO_DIRECT_MAX_ENTRIES, direct: str = "superlu") -> str:
    """The concrete solver for ``method`` (``auto`` decides by ``factor_entries`` against
    ``direct_max_entries``, or by size when it is unknown: direct below 40k dofs; ``direct``
    is its direct method, ``pardiso`` only where MKL is installed, else ``superlu``)."""
    if method not in METHODS:
        raise ValueError(f"unknown solver {method!r}; expected one of {METHODS}")
    if direct not in DIRECT:
        raise ValueError(f"unknown direct solver {direct!r}; expected one of {DIRECT}")
    if method != "auto":
        return method
    if direct == "pardiso":
        from toolkit.common.fem import pardiso

        direct = "pardiso" if pardiso.available() else "superlu"
    if factor_entries is None:
        return direct if n_dofs <= 40_000 else "amg"
    return direct if factor_entries <= direct_max_entries else "amg"


def _factorize(A: sp.spmatrix, method: str, near_nullspace, rtol: float, single: bool = False,
               ordering: str | np.ndarray = "nd", symmetric_part: bool = False):
    """A callable ``b -> x`` for ``A`` (exact for direct methods, one AMG-CG solve otherwise;
    ``single``: SuperLU or PARDISO in float32, an approximate inverse; ``ordering``: see
    :func:`superlu`; PARDISO takes a permutation or runs METIS itself; ``symmetric_part``:
    PARDISO's LDL^T of ``(A + A^T) / 2``)."""
    if method == "pardiso":
        from toolkit.common.fem.pardiso import PardisoError, PardisoFactor

        try:
            return PardisoFactor(A, ordering if isinstance(ordering, np.ndarray) else None, single,
                                 symmetric=symmetric_part)
        except PardisoError as exc:
            raise SolverError(str(exc)) from exc
    if method == "superlu":
        if single:
            lu32 = superlu(A.astype(np.float32), ordering)
            return lambda b: lu32(np.asarray(b, dtype=np.float32)).astype(np.float64)
        return superlu(A, ordering)
    if method == "cholmod":
        try:
            from sksparse.cholmod import cholesky
        except ImportError as exc:
            raise SolverError("solver 'cholmod' needs scikit-sparse (pip install 'scikit-sparse<0.5' after "
                              "apt-get install libsuitesparse-dev); use 'amg' or 'superlu'") from exc
        return cholesky(sp.csc_matrix(A))
    import pyamg

    B = near_nullspace if near_nullspace is not None else np.ones((A.shape[0], 1))
    return pyamg.smoothed_aggregation_solver(sp.csr_matrix(A), B=B, symmetry="symmetric", max_coarse=500,
                                             strength=("symmetric", {"theta": 0.0}))


ORDERINGS = ("nd", "mmd")


def fill_reducing_order(A: sp.spmatrix) -> np.ndarray:
    """METIS nested dissection of ``A + A^T``'s graph: a permutation ``(m,)`` of the unknowns.

    An ``A`` of ``3 k`` unknowns is taken as ``k`` nodes of 3 dofs (node-major, as every
    pattern of :mod:`toolkit.common.fem.assembly` is): the ordering of the node graph, each
    node's dofs kept together, which is half the cost of ordering the dof graph for the same
    fill. (Another layout still gets a valid, only poorer, ordering.)
    """
    try:
        import pymetis
    except ImportError as exc:  # a declared dependency; a hand-made environment may lack it
        raise ImportError("the nested-dissection ordering needs pymetis (pip install pymetis); "
                          "ordering='mmd' uses SuperLU's minimum degree instead") from exc

    m = A.shape[0]
    block = 3 if m % 3 == 0 else 1
    n = m // block
    rows = sp.csr_matrix(A)[::block]  # each node's first dof row: its couplings to all nodes' dofs
    r = np.repeat(np.arange(n), np.diff(rows.indptr))
    graph = sp.csr_matrix((np.ones(r.size), (r, rows.indices // block)), shape=(n, n))
    graph = graph + graph.T  # the pattern of A + A^T
    graph.setdiag(0)
    graph.eliminate_zeros()
    perm, _ = pymetis.nested_dissection(pymetis.CSRAdjacency(graph.indptr, graph.indices))
    perm = np.asarray(perm, dtype=np.int64)
    return (block * perm[:, None] + np.arange(block)).ravel()


def superlu(A: sp.spmatrix, ordering: str | np.ndarray = "nd"):
    """SuperLU factorization of an SPD ``A`` (m, m), or one with a dominant SPD part, as a
    callable ``b -> x`` (``b`` (m,) or (m, k); the dtype of ``A``).

    Symmetric mode with diagonal pivots (4x faster than partial pivoting on the paper impact
    face, same fill). ``ordering``: ``"nd"``, METIS nested dissection
    (:func:`fill_reducing_order`); ``"mmd"``, SuperLU's minimum degree on ``A + A^T``; or a
    permutation ``(m,)`` computed earlier (for a matrix of the same pattern, or nearly). Paper
    impact face with the deformable ball (54k dofs, float32): L+U 39 M entries against 58 M,
    factorization 1.3 s against 2.9 s (ordering included), back-solve 0.029 s against 0.036 s.
    """
    if isinstance(ordering, np.ndarray):
        if ordering.shape != (A.shape[0],):
            raise ValueError(f"ordering has shape {ordering.shape}; expected a permutation of shape ({A.shape[0]},)")
        perm = ordering
    elif ordering in ORDERINGS:
        perm = fill_reducing_order(A) if ordering == "nd" else None
    else:
        raise ValueError(f"unknown ordering {ordering!r}; expected one of {ORDERINGS} or a permutation")
    if perm is not None:
        A = sp.csr_matrix(A)[perm][:, perm]
    try:
        lu = spla.splu(sp.csc_matrix(A), permc_spec="MMD_AT_PLUS_A" if perm is None else "NATURAL",
                       diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError as exc:
        raise SolverError(f"SuperLU failed ({exc}): the system is singular — is the model under-constrained?"
                          ) from exc
    if perm is None:
        return lu.solve
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(perm.size)
    return lambda b: lu.solve(np.ascontiguousarray(np.asarray(b)[perm]))[inverse]


class LinearSolver:
    """A sparse solver that reuses its last factorization or AMG hierarchy.

    Parameters
    ----------
    method : one of :data:`METHODS`
    factor_entries : expected factor size for ``auto`` (see :func:`estimate_factor_entries`)
    rtol : relative residual of AMG-CG solves (and of the Krylov solves on a reused AMG
        hierarchy, on a float32 factor just made, or on a factor of the symmetric part)
    reuse_rtol : relative residual of the Krylov solves on a reused direct factorization
        (tight by default, so that reusing changes the answer only at round-off level)
    reuse : precondition later systems of the same size with the stored factorization
    max_reuse_iterations : Krylov (CG or GMRES) iterations after which a reuse is abandoned
        for a new factorization
    timed_budget : also cap those iterations by what a new factorization costs (its measured
        time over that of one preconditioner application), so that a failed reuse never costs
        more than one extra factorization; False keeps the cap fixed (reproducible choices)
    direct_max_entries : ``auto`` factorizes up to this expected factor size
        (:data:`AUTO_DIRECT_MAX_ENTRIES`; :data:`REUSED_DIRECT_MAX_ENTRIES` where many
        systems will share a factorization)
    direct : the direct method ``auto`` chooses (:data:`DIRECT`; ``pardiso`` falls back to
        ``superlu`` where MKL is not installed)
    single_precision : factorize with SuperLU or PARDISO in float32 and use the factor only as a
        preconditioner (every solve then iterates to ``rtol``, later ones to ``reuse_rtol``):
        half the memory traffic of a back-solve. Paper impact face with the deformable ball
        (54k dofs, measured with the minimum-degree ordering): factorization 3.1 s against 5.6 s,
        back-solve 0.035 s against 0.056 s; a float32 direct solve alone leaves a relative
        residual of 3e-3 there. Other methods
        ignore it.
    ordering : SuperLU's fill-reducing ordering (:data:`ORDERINGS`; see :func:`superlu`)
    factorize_ahead : 0 factorizes only when a reuse fails. ``L > 0`` also factorizes a
        reused system in a background thread (one at a time; SuperLU, PARDISO and CHOLMOD release
        the GIL, so on a second core) and preconditions with that factor from the ``L``-th later
        solve on, waiting for it there if need be. The factor then stays ``L`` to ``2L - 1``
        systems old instead of going stale over a whole Newton path, and the choice of factor
        depends on the count of solves only, never on timing (the same answers on any machine).
    factorize_ahead_above : a solve starts a factorization ahead only when the solve before it
        needed more than this many Krylov iterations, or factorized (0: always): a factor that still
        preconditions in one or two is nearly exact, and another would buy nothing. The choice
        depends on iteration counts only, so it stays reproducible.
    correction_threshold : the Woodbury correction of a reused direct factor for the change of
        the ``local`` term (:meth:`solve`) leaves dofs whose change is below this fraction of the
        largest to the Krylov iterations (:class:`~toolkit.common.fem.woodbury.LocalCorrection`'s
        ``threshold``; 0: every dof the change touches)
    symmetric_factor : PARDISO factorizes the symmetric part ``(A + A^T) / 2`` of every system by
        LDL^T (:class:`~toolkit.common.fem.pardiso.PardisoFactor`'s ``symmetric``) instead of ``A``
        by LU: half the factorization time and memory. An unsymmetric ``A`` is then solved by
        GMRES, and the skew part of its ``local`` term (slipping friction's) is taken exactly by
        the Woodbury correction, so a factor preconditions as the LU of ``A`` does where the skew
        part is local. Other methods ignore it.
    """

    #: a retired PARDISO factor is refactorized for a new matrix (no new symbolic analysis) when
    #: the entries it must leave out, all of the local term, number at most this fraction of
    #: that term's entries. Paper impact run (before systems without a local term were
    #: refactorized too): 35 of 38 background factorizations refactorized (0.85 s against 1.2 s
    #: each beside the solves), 2,006 Woodbury columns against 996; with 0.2, 19 refactorized
    max_left_out = 1.0

    def __init__(self, method: str = "auto", factor_entries: int | None = None, rtol: float = 1e-9,
                 reuse: bool = True, max_reuse_iterations: int = 60, reuse_rtol: float = 1e-13,
                 timed_budget: bool = True, direct_max_entries: int = AUTO_DIRECT_MAX_ENTRIES,
                 single_precision: bool = False, ordering: str = "nd", factorize_ahead: int = 0,
                 direct: str = "superlu", factorize_ahead_above: int = 0, symmetric_factor: bool = False,
                 correction_threshold: float = 0.05):
        if method not in METHODS:
            raise ValueError(f"unknown solver {method!r}; expected one of {METHODS}")
        if direct not in DIRECT:
            raise ValueError(f"unknown direct solver {direct!r}; expected one of {DIRECT}")
        self.direct = direct
        if ordering not in ORDERINGS:
            raise ValueError(f"unknown ordering {ordering!r}; expected one of {ORDERINGS}")
        if int(factorize_ahead) < 0:
            raise ValueError(f"factorize_ahead {factorize_ahead} must be >= 0 (solves before a background factor "
                             "is used; 0 for none)")
        if int(factorize_ahead_above) < 0:
            raise ValueError(f"factorize_ahead_above {factorize_ahead_above} must be >= 0 (Krylov iterations)")
        self.ordering, self.factorize_ahead = ordering, int(factorize_ahead)
        self.factorize_ahead_above = int(factorize_ahead_above)
        self.symmetric_factor = bool(symmetric_factor)
        if not 0 <= correction_threshold < 1:
            raise ValueError(f"correction_threshold {correction_threshold} must lie in [0, 1) (a fraction of the "
                             "largest change of the local term)")
        self.correction_threshold = float(correction_threshold)
        self._last_iterations = None  # the Krylov iterations of the last solve (None: it factorized)
        self._perm = None  # the nested-dissection ordering of this size's systems
        self._worker = None  # the thread pool of one that factorizes ahead
        self._background = False  # whether the factor in use was made on the worker
        self._pending = None  # a background factorization: (future, solve count at its start, matrix, symmetric)
        self._count = 0
        self.method, self.factor_entries, self.rtol, self.reuse_rtol = method, factor_entries, rtol, reuse_rtol
        self.reuse, self.max_reuse_iterations, self.timed_budget = reuse, int(max_reuse_iterations), timed_budget
        self.direct_max_entries = int(direct_max_entries)
        self.single_precision = bool(single_precision)
        self._A = None
        self._factor = None
        self._kind = None
        self._exact = self._symmetric = True
        self._budget = 0
        self.factorizations = 0  # made in the foreground, when a reuse failed (or the first)
        self.background_factorizations = 0  # made ahead (``factorize_ahead``) and taken into use
        self.waited_s = 0.0  # seconds the solves waited for those
        self.reuses = 0
        self.krylov_iterations = 0  # over all solves
        self.correction_columns = 0  # back-solves of the Woodbury corrections (solve's ``local``)
        self.refactorizations = 0  # PARDISO factors refactorized without a new analysis
        self._local = None
        self._correction = None
        self._spare = None  # a retired PARDISO factor (_new_factor)
        self._lock = threading.Lock()

    def solve(self, A: sp.spmatrix, b: np.ndarray, near_nullspace: np.ndarray | None = None,
              x0: np.ndarray | None = None, symmetric: bool = True,
              local: sp.spmatrix | None = None, rtol: float | None = None) -> tuple[np.ndarray, SolveInfo]:
        """Solve ``A x = b`` (``A`` (m, m) sparse, ``b`` (m,)); returns ``x`` and :class:`SolveInfo`.

        ``A`` is SPD when ``symmetric``. Otherwise it may be unsymmetric with a dominant SPD part
        (a consistent friction tangent): SuperLU and PARDISO factorize ``A`` itself, CHOLMOD and AMG its
        symmetric part ``(A + A^T) / 2``, which then preconditions GMRES on ``A``; a reused
        factorization preconditions GMRES instead of CG.

        ``local`` (m, m) sparse: the part of ``A`` that lives on few dofs and changes much from
        one system to the next (penalty contact). A reused SuperLU or PARDISO factorization then
        takes the change of that part since it was made exactly, by a Woodbury correction on
        its dofs (:mod:`toolkit.common.fem.woodbury`), and GMRES iterates.

        ``rtol``: the relative residual of this solve's Krylov iterations, in place of the
        solver's ``rtol`` and ``reuse_rtol`` (an inexact Newton's forcing term).
        """
        if not np.isfinite(b).all():
            raise SolverError("right-hand side holds NaN/inf")
        if rtol is not None and not 0 < rtol < 1:
            raise ValueError(f"rtol {rtol} must lie in (0, 1)")
        fresh_rtol, reuse_rtol = (self.rtol, self.reuse_rtol) if rtol is None else (float(rtol), float(rtol))
        t0 = time.perf_counter()
        m = A.shape[0]
        if m == 0:
            return np.zeros(0), SolveInfo("none", 0, 0.0, 0.0)
        A = sp.csr_matrix(A)  # the Krylov products; a factorization converts what it needs
        self._count += 1
        if self._pending is not None and self._count - self._pending[1] >= self.factorize_ahead:
            self._take_pending()
        x, iterations, reused = None, 0, False
        if self.reuse and self._A is not None and self._A.shape == A.shape:
            stale = self._last_iterations is None or self._last_iterations > self.factorize_ahead_above
            if self.factorize_ahead and self._pending is None and stale \
                    and self._kind in ("superlu", "pardiso", "cholmod"):
                # started before this solve's Krylov iterations, so that the worker has them too
                self._start_pending(A, symmetric, near_nullspace, local)
            x, iterations = self._reuse(A, b, x0, symmetric, local, fresh_rtol, reuse_rtol)
            reused = x is not None
        if x is None:
            t_factor = time.perf_counter()
            if self._pending is not None and self._pending[2] is A:  # being factorized already
                self._take_pending()
            self._drop_pending()  # older than this system
            if self._A is not A:
                self._spare_ahead(A, symmetric, near_nullspace)
                self._install(self._new_factor(A, symmetric, near_nullspace, local), A, symmetric,
                              background=False)
                self.factorizations += 1
            t_apply = time.perf_counter()
            x, iterations = self._apply(A, b, x0, fresh_rtol, local)
            t_end = time.perf_counter()
            per_application = (t_end - t_apply) / max(iterations, 1)
            # a reuse may spend what a new factorization costs, in preconditioned Krylov iterations
            cost = (t_apply - t_factor) + (t_end - t_apply)
            self._budget = int(min(self.max_reuse_iterations, cost / max(per_application, 1e-9))) \
                if self.timed_budget else self.max_reuse_iterations
        else:
            self.reuses += 1
        bn = np.linalg.norm(b)
        res = float(np.linalg.norm(A @ x - b) / bn) if bn > 0 else 0.0
        # a loose rtol (an inexact Newton's 1e-2) still rejects a solve that did not halve the residual
        limit = max(1e-5, min(1e3 * fresh_rtol, 0.5), 10.0 * reuse_rtol if reused else 0.0)
        if not np.isfinite(x).all() or res > limit:
            raise SolverError(f"{self._kind} solve did not converge: relative residual {res:.2e} after {iterations} "
                              f"iterations; the system may be singular (under-constrained model)")
        self._last_iterations = iterations if reused else None
        self.krylov_iterations += iterations
        return x, SolveInfo(self._kind, iterations, res, time.perf_counter() - t0, reused)

    def close(self) -> None:
        """Free the factors made ahead and end the worker thread (call when done with a solver
        that factorizes ahead; a later solve starts afresh)."""
        if self._worker is None:
            return
        self._drop_pending()
        if self._background:
            self._install((None, None, True, None), None, True, background=False)
        self._worker.shutdown(wait=True)
        self._worker = None
        with self._lock:
            spare, self._spare = self._spare, None
        if spare is not None:
            spare.close()

    def _new_factor(self, A, symmetric: bool, near_nullspace, local=None):
        """``(factor, kind, exact, local_in_factor)`` for ``A``: of ``A`` itself, or of its
        symmetric part (AMG, CHOLMOD on an unsymmetric ``A``; PARDISO with
        :attr:`symmetric_factor`, whose ``local_in_factor`` is then the symmetric part of
        ``local``); exact unless float32 or of the symmetric part of an unsymmetric ``A``. With
        PARDISO a retired factor is refactorized on its own analysed pattern when that holds
        all of ``A``, or all but some entries of the ``local`` term (see :meth:`solve`; at
        most :attr:`max_left_out` of its entries): those are left out and ``local_in_factor``
        is the rest, so that the Woodbury correction takes them. (Paper impact run: the
        systems before contact, which have no local term, were factorized afresh before, 4
        analyses of ~0.5 s each where the worker was behind.)"""
        kind = choose_method(self.method, A.shape[0], self.factor_entries, self.direct_max_entries, self.direct)
        single = self.single_precision and kind in DIRECT
        halves = kind == "pardiso" and self.symmetric_factor  # LDL^T of the symmetric part
        own = symmetric or (kind in DIRECT and not halves)  # a factor of A itself
        if halves and local is not None:
            local = 0.5 * (local + local.T)
        if kind == "pardiso":
            with self._lock:
                spare, self._spare = self._spare, None
            if spare is not None:
                if spare.single == single and spare.symmetric == halves and spare.shape == A.shape:
                    # without a local term nothing may be left out: A must fit the analysed pattern
                    left = spare.refactorize(A, local, 0 if local is None else int(self.max_left_out * local.nnz))
                    if left is not None:
                        with self._lock:  # the worker and a foreground factorization may count at once
                            self.refactorizations += 1
                        return spare, kind, own and not single and left.nnz == 0, local - left if left.nnz else local
                spare.close()
        ordering = self._nd_ordering(A) if kind in DIRECT and self.ordering == "nd" else self.ordering
        factor = _factorize(A if own or halves else 0.5 * (A + A.T), kind, near_nullspace, self.rtol, single, ordering,
                            symmetric_part=halves)
        return factor, kind, own and not single, local

    def _install(self, made: tuple, A, symmetric: bool, background: bool) -> None:
        """Precondition with ``made`` = ``(factor, kind, exact, local)`` of ``A`` from now on. A factor
        made on the worker thread is freed on it: scipy's SuperLU objects freed on another
        thread than the one that made them keep their memory (scipy issue #15921; a paper impact
        run grew to 13.4 GB)."""
        old, old_kind = self._factor, self._kind
        box = [old] if self._background and old_kind != "pardiso" else None  # the old factor's last reference
        self._factor, self._kind, self._exact, self._local = made  # _local: solve's ``local`` in the factor
        self._A, self._symmetric, self._background = A, symmetric, background
        self._correction = None
        if box is not None:
            self._worker.submit(box.clear)
        elif old_kind == "pardiso":
            self._retire(old)

    def _retire(self, factor) -> None:
        """Keep a PARDISO factor no solve uses any more, for :meth:`_new_factor` to refactorize
        (one at most; another is freed)."""
        with self._lock:
            keep = self._spare is None
            if keep:
                self._spare = factor
        if not keep:
            factor.close()

    def _drop_pending(self) -> None:
        """Forget the background factorization, freeing it on the worker once it is done."""
        if self._pending is not None:
            box = [self._pending[0]]  # the future holds the factor
            self._pending = None
            self._worker.submit(box.clear)

    def _nd_ordering(self, A) -> np.ndarray:
        """The nested-dissection ordering of ``A``'s size, computed for the first system: the
        first system's ordering serves all of its size, as they share the mesh's pattern.
        Contact couplings added later cost little fill (paper impact face: 41.7 M entries
        against 39.7 M), ordering each system 0.2 s, most of it holding the GIL."""
        if self._perm is None or self._perm.size != A.shape[0]:
            self._perm = fill_reducing_order(A)
        return self._perm

    def _spare_ahead(self, A, symmetric: bool, near_nullspace) -> None:
        """At the first factorization of a solver that factorizes ahead with PARDISO: the worker,
        idle until then, factorizes the same system beside the foreground and keeps it as the
        spare that the first factor made ahead refactorizes (paper impact face: 0.75 s instead
        of 1.25 s with the analysis, where the worker is furthest behind the solves). Either
        factor is the same, whichever thread finishes first."""
        kind = choose_method(self.method, A.shape[0], self.factor_entries, self.direct_max_entries, self.direct)
        if not (self.factorize_ahead and kind == "pardiso" and self._worker is None):
            return
        if self.ordering == "nd":
            self._nd_ordering(A)  # before the worker starts: one ordering for both

        def spare() -> None:
            self._retire(self._new_factor(A, symmetric, near_nullspace)[0])

        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="toolkit-factorize-ahead")
        self._worker.submit(spare)

    def _start_pending(self, A, symmetric: bool, near_nullspace, local=None) -> None:
        """Factorize ``A`` on the worker thread (:attr:`factorize_ahead`)."""
        if self._worker is None:
            self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="toolkit-factorize-ahead")
        future = self._worker.submit(self._new_factor, A, symmetric, near_nullspace, local)
        self._pending = (future, self._count, A, symmetric)

    def _take_pending(self) -> None:
        """Wait for the background factorization and precondition with it from now on (a failed
        one is dropped: the next failed reuse factorizes in the foreground and reports)."""
        future, _, A, symmetric = self._pending
        t0 = time.perf_counter()
        error = future.exception()  # waits
        self.waited_s += time.perf_counter() - t0
        if error is None:
            self._install(future.result(), A, symmetric, background=True)
            self.background_factorizations += 1
        else:
            log.warning("background factorization failed (%s); keeping the previous factor", error)
        self._drop_pending()  # the future's reference, freed on the worker too

    def _preconditioner(self, shape) -> spla.LinearOperator:
        """The stored factorization or hierarchy as an approximate inverse."""
        if self._kind == "amg":
            return self._factor.aspreconditioner(cycle="V")
        return spla.LinearOperator(shape, matvec=self._factor, dtype=float)

    def _apply(self, A, b, x0, rtol: float, local=None) -> tuple[np.ndarray, int]:
        """Solve with the fresh factorization of ``A`` (or of its symmetric part, or in float32)."""
        if self._kind == "amg" and self._symmetric:
            residuals = []
            x = self._factor.solve(b, x0=x0, tol=rtol, accel="cg", maxiter=500, residuals=residuals)
            return x, len(residuals) - 1
        if self._exact:
            return self._factor(b), 0
        x, count = self._iterate(A, b, x0, self._symmetric, local, rtol, 500)
        return (x, count) if x is not None else (np.full_like(b, np.nan), count)

    def _reuse(self, A, b, x0, symmetric, local, fresh_rtol: float,
               reuse_rtol: float) -> tuple[np.ndarray | None, int]:
        """A Krylov solve of ``A`` preconditioned by the stored factorization (CG when both are
        symmetric, GMRES otherwise), corrected for the change of ``local`` (see :meth:`solve`);
        None if it does not converge within the budget."""
        same = (A.nnz == self._A.nnz and np.array_equal(A.indptr, self._A.indptr)
                and np.array_equal(A.indices, self._A.indices) and np.array_equal(A.data, self._A.data))
        if same:
            return self._apply(A, b, x0, fresh_rtol, local)
        if self._budget < 2:
            return None, 0
        rtol = fresh_rtol if self._kind == "amg" else reuse_rtol
        return self._iterate(A, b, x0, symmetric, local, rtol, self._budget)

    def _iterate(self, A, b, x0, symmetric, local, rtol: float, maxiter: int) -> tuple[np.ndarray | None, int]:
        """Krylov iterations on ``A`` preconditioned by the stored factor or hierarchy: for a
        direct factor, corrected exactly for the difference between ``local`` and the local
        term it holds (GMRES), else CG when ``A`` and the factor are symmetric, GMRES otherwise;
        ``x`` None when they do not converge in ``maxiter``."""
        if self._kind in DIRECT and (local is not None or self._local is not None):
            if self._correction is None:
                self._correction = LocalCorrection(self._factor, A.shape[0], self._local,
                                                   threshold=self.correction_threshold,
                                                   dtype=np.float32 if self.single_precision else np.float64)
            before = self._correction.columns
            # with no x0, GMRES's first application is to b: solved with the new columns
            corrected, first = self._correction.preconditioner_and_solve(local, b if x0 is None else None)
            self.correction_columns += self._correction.columns - before
            if corrected is not None:
                M = spla.LinearOperator(A.shape, matvec=corrected, dtype=float)
                return _gmres(A, b, x0, M, rtol, maxiter, first=first)
        return _krylov(A, b, x0, self._preconditioner(A.shape), rtol, maxiter,
                       symmetric=symmetric and self._symmetric)


def _krylov(A, b, x0, M, rtol: float, maxiter: int, symmetric: bool) -> tuple[np.ndarray | None, int]:
    """Preconditioned CG (``symmetric``) or :func:`_gmres` to the relative residual ``rtol``
    in at most ``maxiter`` iterations; ``(x, iterations)``, ``x`` None when it did not converge."""
    if not symmetric:
        return _gmres(A, b, x0, M, rtol, maxiter)
    count = [0]

    def callback(_):
        count[0] += 1

    x, info = spla.cg(A, b, x0=x0, rtol=rtol, maxiter=maxiter, M=M, callback=callback)
    return (x, count[0]) if info == 0 else (None, count[0])


def _gmres(A, b, x0, M, rtol: float, maxiter: int, first: np.ndarray | None = None) -> tuple[np.ndarray | None, int]:
    """Right-preconditioned GMRES without restarts: ``x = x0 + M^-1 V y`` minimizes the true
    residual ``|b - A x|`` over the Krylov space, so it stops when that residual is below
    ``rtol |b|``. (scipy's ``gmres`` preconditions on the left and judges the preconditioned
    residual, which a stale factorization makes a poor proxy: with one restart cycle it
    failed 61 of 93 reuses on the coarse impact face that converged in 3 iterations when
    they did.) ``first``: ``M^-1 b`` when already known (``x0`` must then be None). Returns
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
