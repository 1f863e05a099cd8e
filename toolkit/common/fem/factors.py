"""Factor backends: SuperLU on METIS nested dissection, MKL PARDISO, CHOLMOD where installed, and
pyamg's smoothed aggregation, each behind :func:`factorize`.

Which one (:func:`choose_method`; the time and memory of each are measured by
``benchmarks/static_solvers.py``, its table in docs/solvers.md):

- ``"superlu"``: scipy's direct solver in symmetric mode (diagonal pivots), on METIS's
  nested-dissection ordering of ``A + A^T`` (:func:`superlu`; SuperLU's own minimum degree
  as ``ordering="mmd"``); installs everywhere; fast while the factor stays small (the thin
  phantom shell; a bulky tet block, in less time and memory than with minimum degree),
  hopeless when it does not (the fine phantom with minimum degree).
- ``"pardiso"``: Intel MKL PARDISO (:mod:`toolkit.common.fem.pardiso`; the ``pardiso``
  extra) on the same ordering: on the paper impact face (float32) it factorizes and
  back-solves faster than SuperLU. ``auto`` takes it where a caller
  asks for it (``direct="pardiso"``, the quasi-static impact path) and MKL is installed.
- ``"amg"``: pyamg smoothed aggregation (rigid-body near-nullspace), a preconditioner for
  conjugate gradients.
- ``"cholmod"``: scikit-sparse's CHOLMOD when it is installed (needs the system
  SuiteSparse); otherwise refused with a hint.
- ``"auto"``: by the **expected fill** of the factor, not the number of unknowns: the direct
  method when :func:`~toolkit.common.fem.ordering.estimate_factor_entries` is below
  :data:`AUTO_DIRECT_MAX_ENTRIES`, else ``amg``. A shell stays direct up to much larger sizes
  than a bulky mesh of the same number of dofs.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from toolkit.common.errors import ToolkitError
from toolkit.common.fem.ordering import ORDERINGS, fill_reducing_order

__all__ = ["Factor", "Refactorizable", "SolverError", "SuperLUFactor", "CholmodFactor", "superlu", "factorize",
           "amg_hierarchy", "choose_method", "METHODS", "DIRECT", "AUTO_DIRECT_MAX_ENTRIES",
           "REUSED_DIRECT_MAX_ENTRIES"]

#: entries of the factor below which ``auto`` factorizes (SuperLU): ~30 M entries ~ 0.5 GB; the
#: paper phantom's factor lies below it, the fine phantom's and a bulky tet mesh's above (their
#: estimates: ``benchmarks/static_solvers.py``)
AUTO_DIRECT_MAX_ENTRIES = 30_000_000
#: the same limit for a solver that reuses its factorization over many systems (the quasi-static
#: impact path's Newton iterations), which the paper face with the deformable ball stays below:
#: there one factorization reused as a CG preconditioner is faster than AMG-CG, whose hierarchy
#: the contact springs spoil (it is set up again at most solves; docs/solvers.md)
REUSED_DIRECT_MAX_ENTRIES = 150_000_000
METHODS = ("auto", "superlu", "pardiso", "amg", "cholmod")
#: the direct solvers ``auto`` may choose
DIRECT = ("superlu", "pardiso")


class SolverError(ToolkitError, RuntimeError):
    """A linear solve failed (singular system, no convergence)."""


@runtime_checkable
class Factor(Protocol):
    """A factorization of a sparse ``A`` (m, m): ``factor(b)`` (or ``factor.solve(b)``) is
    ``A^-1 b`` for ``b`` (m,) or (m, k), in float64 (an approximate inverse when ``single``)."""

    shape: tuple[int, int]
    single: bool

    def __call__(self, b: np.ndarray) -> np.ndarray: ...

    def solve(self, b: np.ndarray) -> np.ndarray: ...


@runtime_checkable
class Refactorizable(Factor, Protocol):
    """A :class:`Factor` that factorizes a new matrix on its analysed pattern
    (:meth:`~toolkit.common.fem.pardiso.PardisoFactor.refactorize`), and frees its memory on
    :meth:`close`."""

    symmetric: bool

    def refactorize(self, A: sp.spmatrix, droppable: sp.spmatrix | None = None,
                    max_left: int | None = None) -> sp.csr_matrix | None: ...

    def close(self) -> None: ...


class SuperLUFactor:
    """SuperLU factorization of an SPD ``A`` (m, m), or one with a dominant SPD part.

    Symmetric mode with diagonal pivots (faster than partial pivoting on the paper impact
    face, same fill). ``ordering``: ``"nd"``, METIS nested dissection
    (:func:`~toolkit.common.fem.ordering.fill_reducing_order`); ``"mmd"``, SuperLU's minimum
    degree on ``A + A^T``; or a permutation ``(m,)`` computed earlier (for a matrix of the same
    pattern, or nearly). On the paper impact face with the deformable ball ``"nd"`` gives fewer
    L+U entries than ``"mmd"``, and a faster factorization (ordering included) and back-solve.
    ``single``: factorize ``A`` in float32, an
    approximate inverse (half the memory traffic of a back-solve); otherwise in ``A``'s dtype.

    Attributes
    ----------
    shape : (m, m)
    single : whether the factor is in float32
    entries : entries of the L and U factors
    """

    def __init__(self, A: sp.spmatrix, ordering: str | np.ndarray = "nd", single: bool = False):
        m = A.shape[0]
        if isinstance(ordering, np.ndarray):
            if ordering.shape != (m,):
                raise ValueError(f"ordering has shape {ordering.shape}; expected a permutation of shape ({m},)")
            perm = ordering
        elif ordering in ORDERINGS:
            perm = fill_reducing_order(A) if ordering == "nd" else None
        else:
            raise ValueError(f"unknown ordering {ordering!r}; expected one of {ORDERINGS} or a permutation")
        if single:
            A = A.astype(np.float32)
        if perm is not None:
            A = sp.csr_matrix(A)[perm][:, perm]
        try:
            self._lu = spla.splu(sp.csc_matrix(A), permc_spec="MMD_AT_PLUS_A" if perm is None else "NATURAL",
                                 diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        except RuntimeError as exc:
            raise SolverError(f"SuperLU failed ({exc}): the system is singular — is the model under-constrained?"
                              ) from exc
        self.shape, self.single = (m, m), bool(single)
        self._perm = perm
        if perm is not None:
            self._inverse = np.empty_like(perm)
            self._inverse[perm] = np.arange(perm.size)

    @property
    def entries(self) -> int:
        return int(self._lu.nnz)

    def __call__(self, b: np.ndarray) -> np.ndarray:
        """``x`` with ``A x = b`` (``b`` (m,) or (m, k))."""
        if self.single:
            return self._solve(np.asarray(b, dtype=np.float32)).astype(np.float64)
        return self._solve(b)

    solve = __call__

    def _solve(self, b):
        if self._perm is None:
            return self._lu.solve(b)
        return self._lu.solve(np.ascontiguousarray(np.asarray(b)[self._perm]))[self._inverse]


def superlu(A: sp.spmatrix, ordering: str | np.ndarray = "nd") -> SuperLUFactor:
    """The :class:`SuperLUFactor` of ``A`` (m, m) in its dtype: callable ``b -> x`` (``b`` (m,)
    or (m, k))."""
    return SuperLUFactor(A, ordering)


#: why ``cholmod`` cannot run, and the remedy
CHOLMOD_MISSING = ("solver 'cholmod' needs scikit-sparse (pip install 'scikit-sparse<0.5' after apt-get install "
                   "libsuitesparse-dev); use solver 'auto', 'amg' or 'superlu'")


class CholmodFactor:
    """scikit-sparse's CHOLMOD Cholesky factor of an SPD ``A`` (m, m)."""

    single = False

    def __init__(self, A: sp.spmatrix):
        try:
            from sksparse.cholmod import cholesky
        except ImportError as exc:
            raise SolverError(CHOLMOD_MISSING) from exc
        self.shape = A.shape
        self._factor = cholesky(sp.csc_matrix(A))

    def __call__(self, b: np.ndarray) -> np.ndarray:
        return self._factor(b)

    solve = __call__


def amg_hierarchy(A: sp.spmatrix, near_nullspace: np.ndarray | None = None, coarse_space=None):
    """pyamg's smoothed-aggregation hierarchy of an SPD ``A`` (m, m), ``near_nullspace`` (m, k)
    (the rigid-body modes; None: constants): a preconditioner for conjugate gradients.

    ``coarse_space``: a :class:`~toolkit.common.fem.coarse.CoarseSpace` (a quadratic mesh's corner
    nodes), or a function of no argument that makes it (or returns None: none): the first coarsening is its prolongation
    (Galerkin product), smoothed aggregation coarsens the corner-node system from there, and every
    level smooths by two forward Gauss-Seidel sweeps before the coarse correction and two backward
    after it (a symmetric cycle; on a tet10 face fewer iterations and less time than one
    symmetric sweep each side). The coarsest level is solved by SuperLU, not by pyamg's dense
    pseudo-inverse, whose cost grows with the cube of the coarsest level's size."""
    import pyamg
    from pyamg.multilevel import MultilevelSolver
    from pyamg.relaxation.smoothing import change_smoothers

    A = sp.csr_matrix(A)
    settings = dict(symmetry="symmetric", max_coarse=500, strength=("symmetric", {"theta": 0.0}),
                    coarse_solver="splu")
    if callable(coarse_space):
        coarse_space = coarse_space()
    if coarse_space is None:
        B = near_nullspace if near_nullspace is not None else np.ones((A.shape[0], 1))
        return pyamg.smoothed_aggregation_solver(A, B=B, **settings)
    P = sp.csr_matrix(coarse_space.P)
    R = P.T.tocsr()
    inner = pyamg.smoothed_aggregation_solver((R @ A @ P).tocsr(), B=coarse_space.modes, improve_candidates=None,
                                              **settings)
    first = MultilevelSolver.Level()
    first.A, first.P, first.R = A, P, R
    ml = MultilevelSolver([first, *inner.levels], coarse_solver="splu")
    change_smoothers(ml, presmoother=("gauss_seidel", {"sweep": "forward", "iterations": 2}),
                     postsmoother=("gauss_seidel", {"sweep": "backward", "iterations": 2}))
    return ml


def factorize(A: sp.spmatrix, method: str, single: bool = False, ordering: str | np.ndarray = "nd",
              symmetric_part: bool = False) -> Factor:
    """The :class:`Factor` of ``A`` (m, m) by the direct ``method`` (``superlu``, ``pardiso`` or
    ``cholmod``). ``single``: SuperLU or PARDISO in float32, an approximate inverse;
    ``ordering``: see :class:`SuperLUFactor` (PARDISO takes a permutation, or runs METIS
    itself); ``symmetric_part``: PARDISO's LDL^T of ``(A + A^T) / 2``."""
    if method == "pardiso":
        from toolkit.common.fem.pardiso import PardisoError, PardisoFactor

        try:
            return PardisoFactor(A, ordering if isinstance(ordering, np.ndarray) else None, single,
                                 symmetric=symmetric_part)
        except PardisoError as exc:
            raise SolverError(str(exc)) from exc
    if method == "superlu":
        return SuperLUFactor(A, ordering, single)
    if method == "cholmod":
        return CholmodFactor(A)
    raise ValueError(f"unknown direct method {method!r}; expected 'superlu', 'pardiso' or 'cholmod'")


def require_method(method: str) -> None:
    """Raise ``ValueError`` when ``method`` is not a solver (:data:`METHODS`) or needs a package
    that is not installed (``cholmod``: scikit-sparse; ``pardiso``: the ``mkl`` wheel), so that an
    option is refused before any computation instead of failing at the first solve."""
    if method not in METHODS:
        raise ValueError(f"unknown solver {method!r}; expected one of {METHODS}")
    if method == "cholmod":
        try:
            import sksparse.cholmod  # noqa: F401
        except ImportError:
            raise ValueError(CHOLMOD_MISSING) from None
    if method == "pardiso":
        from toolkit.common.fem import pardiso

        if not pardiso.available():
            raise ValueError("solver 'pardiso' needs MKL (pip install mkl); use solver 'auto', 'amg' or 'superlu'")


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
