"""Intel MKL PARDISO, the sparse direct solver of the ``pardiso`` method, through ctypes.

MKL comes from the ``mkl`` wheel (the ``pardiso`` extra: ``pip install
"facial-biomech-toolkit[pardiso]"``); without it :func:`available` is False and ``auto``
keeps SuperLU. On the paper impact face's tangent with the deformable ball (unsymmetric with
slipping friction, the METIS nested-dissection ordering of
:func:`~toolkit.common.fem.ordering.fill_reducing_order`), PARDISO in float32 factorizes and
back-solves faster than SuperLU on the same ordering. PARDISO's own METIS ordering gives about
the same fill there.

The library runs on MKL's sequential threading layer (chosen at the first factorization, only
for MKL, which nothing else here loads: numpy and scipy use OpenBLAS), so it starts no OpenMP
runtime beside torch's and numba's. ctypes releases the GIL around every call, so a
factorization on a worker thread runs beside the main thread's solves.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import glob
import os
import sys
import threading

import numpy as np
import scipy.sparse as sp

from toolkit.common.errors import ToolkitError
from toolkit.common.fem.jit import njit, use_jit

__all__ = ["available", "PardisoFactor", "PardisoError", "symmetric_upper"]

#: PARDISO's error codes (``error`` of ``pardiso``), from MKL's reference
_ERRORS = {-1: "input inconsistent", -2: "not enough memory", -3: "reordering problem",
           -4: "zero pivot (numerical factorization or iterative refinement failed)",
           -5: "unclassified internal error", -6: "reordering failed", -7: "diagonal matrix is singular",
           -8: "32-bit integer overflow", -9: "not enough memory for out-of-core", -10: "out-of-core files",
           -11: "out-of-core read/write error", -12: "pardiso_64 called from a 32-bit library"}
_REAL_UNSYMMETRIC = 11  # mtype: structurally symmetric or not, any sign; diagonal pivoting with perturbation
_SYMMETRIC_INDEFINITE = -2  # mtype: real symmetric, any sign; LDL^T, 1x1 diagonal pivots (iparm[20] = 0)
_SEQUENTIAL = 1  # MKL_THREADING_SEQUENTIAL
_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_searched = False


class PardisoError(ToolkitError, RuntimeError):
    """PARDISO refused or failed a phase (the message names its error code)."""


def _candidates() -> list[str]:
    """Where the ``mkl`` wheel (or a system MKL) puts the single dynamic library ``mkl_rt``."""
    names = [os.environ.get("TOOLKIT_MKL_RT", "")]
    for prefix in dict.fromkeys((sys.prefix, sys.base_prefix)):
        names += sorted(glob.glob(os.path.join(prefix, "lib", "libmkl_rt.so*")))
        names += sorted(glob.glob(os.path.join(prefix, "lib", "libmkl_rt*.dylib")))
        names += sorted(glob.glob(os.path.join(prefix, "Library", "bin", "mkl_rt*.dll")))
    names.append(ctypes.util.find_library("mkl_rt") or "")
    return [n for n in names if n]


def _library() -> ctypes.CDLL | None:
    """MKL's ``mkl_rt`` on the sequential threading layer, or None when it is not installed."""
    global _lib, _searched
    with _lock:
        if not _searched:
            _searched = True
            for name in _candidates():
                try:
                    lib = ctypes.CDLL(name)
                    lib.pardiso  # noqa: B018 - the symbol this module needs
                except (OSError, AttributeError):
                    continue
                lib.MKL_Set_Threading_Layer.restype = ctypes.c_int
                lib.MKL_Set_Threading_Layer(ctypes.c_int(_SEQUENTIAL))  # no effect once MKL has run
                lib.pardiso.restype = None
                _lib = lib
                break
        return _lib


def available() -> bool:
    """Whether MKL PARDISO can be loaded (the ``mkl`` wheel is installed)."""
    return _library() is not None


def _pointer(array: np.ndarray) -> ctypes.c_void_p:
    return array.ctypes.data_as(ctypes.c_void_p)


class PardisoFactor:
    """The LU factorization of a sparse ``A`` (m, m) by PARDISO, callable as ``b -> x``.

    Diagonal pivoting (tiny pivots perturbed to ``1e-13 |A|``, then two steps of iterative
    refinement), as SuperLU's symmetric mode: meant for SPD matrices and ones with a dominant
    SPD part (a friction tangent). A singular matrix is not refused but leaves a large
    residual, which :class:`~toolkit.common.fem.solvers.LinearSolver` checks. Satisfies
    :class:`~toolkit.common.fem.factors.Refactorizable`.

    Parameters
    ----------
    A : (m, m) sparse matrix
    ordering : (m,) the fill-reducing permutation (new position ``k`` holds unknown
        ``ordering[k]``, as :func:`~toolkit.common.fem.ordering.fill_reducing_order` returns);
        None lets PARDISO run METIS itself (the same fill on the paper impact face)
    single : factorize in float32: an approximate inverse for a Krylov preconditioner, not a
        solver on its own, in less time than float64
    symmetric : factorize the symmetric part ``S = (A + A^T) / 2`` by LDL^T (PARDISO's real
        symmetric indefinite type, 1x1 diagonal pivots with the same perturbation), and solve
        ``S x = b``: ``A`` itself when it is symmetric. About half the work and the entries of
        LU (the paper impact tangent's: docs/solvers.md); a back-solve reads L twice and so
        takes about as long as LU's. For an unsymmetric ``A`` the
        factor is a preconditioner, whose skew part a caller corrects for
        (:mod:`toolkit.common.fem.woodbury` where that part is local, as friction's is).

    Attributes
    ----------
    shape : (m, m)
    single : whether the factor is in float32
    symmetric : whether the factor is of the symmetric part (LDL^T)
    entries : entries of the L and U factors
    perturbed : pivots PARDISO perturbed (nonzero only for a nearly singular matrix)
    """

    def __init__(self, A: sp.spmatrix, ordering: np.ndarray | None = None, single: bool = False,
                 symmetric: bool = False):
        lib = _library()
        if lib is None:
            raise PardisoError("MKL PARDISO is not installed: pip install 'facial-biomech-toolkit[pardiso]' "
                               "(the mkl wheel), or set TOOLKIT_MKL_RT to the path of libmkl_rt")
        A = _sorted_csr(A)
        m = A.shape[0]
        if A.shape != (m, m) or m == 0:
            raise ValueError(f"PARDISO needs a nonempty square matrix; got shape {A.shape}")
        self.symmetric = bool(symmetric)
        self._mtype = _SYMMETRIC_INDEFINITE if self.symmetric else _REAL_UNSYMMETRIC
        if self.symmetric:
            A = symmetric_upper(A)
        if ordering is not None and np.shape(ordering) != (m,):
            raise ValueError(f"ordering has shape {np.shape(ordering)}; expected a permutation of shape ({m},)")
        self._lib, self._m = lib, m
        self.shape, self.single = (m, m), bool(single)
        self._dtype = np.float32 if single else np.float64
        # PARDISO keeps pointers to the matrix (iterative refinement): the arrays live with the
        # factor, copies of the caller's (refactorize overwrites the values in place)
        self._data = np.array(A.data, dtype=self._dtype)
        self._indptr = np.array(A.indptr, dtype=np.int32)
        self._indices = np.array(A.indices, dtype=np.int32)
        self._handle = np.zeros(64, dtype=np.int64)  # PARDISO's internal memory pointers
        self._iparm = np.zeros(64, dtype=np.int32)
        p = self._iparm
        p[0] = 1  # these settings, not the defaults
        p[1] = 2  # METIS, when no ordering is given
        p[4] = 0 if ordering is None else 1  # the user's permutation
        p[9] = 13  # pivot perturbation 1e-13
        p[10] = p[12] = 0  # no scaling or weighted matching: the diagonal dominates
        p[17] = -1  # report the factor's entries
        p[20] = 0  # LDL^T (symmetric): 1x1 diagonal pivots, as LU's
        p[27] = 1 if single else 0
        p[34] = 1  # zero-based indices
        self._perm = (np.zeros(m, dtype=np.int32) if ordering is None
                      else np.ascontiguousarray(ordering, dtype=np.int32))
        self._live = False
        try:
            self._call(12)  # analysis and numerical factorization
        except PardisoError:
            self.close()
            raise
        self.entries = int(p[17])
        self.perturbed = int(p[13])

    def refactorize(self, A: sp.spmatrix, droppable: sp.spmatrix | None = None,
                    max_left: int | None = None) -> sp.csr_matrix | None:
        """Factorize ``A`` in place of the matrix this factor holds, on its analysed pattern:
        PARDISO's numerical phase only (no symbolic analysis). Entries of ``A`` outside that
        pattern are left out of the factor when they are entries of ``droppable`` (a term the
        caller corrects for) and at most ``max_left`` of them (default: any number); otherwise
        nothing changes and None is returned.
        Returns the entries left out ``(m, m)`` CSR (empty when none): the factor is of ``A``
        minus them (of ``(A + A^T) / 2`` minus them for a :attr:`symmetric` factor, whose
        left-out entries come in both triangles). Never call it on a factor another thread
        may be solving with."""
        if not self._live:
            raise PardisoError("this PARDISO factor was closed; factorize the matrix again")
        A = _sorted_csr(A)
        if A.shape != (self._m, self._m):
            raise ValueError(f"matrix of shape {A.shape}; this factor is of shape {(self._m, self._m)}")
        if self.symmetric:
            A = symmetric_upper(A)
            droppable = None if droppable is None else symmetric_upper(droppable)
        data = np.zeros(self._indices.size, dtype=self._dtype)
        outside = np.zeros(A.nnz, dtype=np.bool_)
        if use_jit():
            _project(self._indptr, self._indices, A.indptr, A.indices, A.data, data, outside)
        else:
            _project_numpy(self._indptr, self._indices, A, data, outside)
        at = np.flatnonzero(outside)
        at = at[A.data[at] != 0]  # a stored zero left out changes nothing (copies: A's arrays stay A's)
        rows = np.searchsorted(A.indptr, at, side="right") - 1
        left = sp.csr_matrix((A.data[at], (rows, A.indices[at])), shape=A.shape)
        if left.nnz:
            if droppable is None or (max_left is not None and left.nnz > max_left):
                return None
            keys = _keys(left)
            if not np.isin(keys, _keys(_sorted_csr(droppable))).all():
                return None
        self._data[:] = data
        self._call(22)
        self.perturbed = int(self._iparm[13])
        if self.symmetric and left.nnz:  # both triangles of the symmetric entries left out
            left = (left + sp.triu(left, k=1, format="csr").T).tocsr()
        return left

    def __call__(self, b: np.ndarray) -> np.ndarray:
        """``x`` with ``A x = b`` (``b`` (m,) or (m, k)); float64."""
        if not self._live:
            raise PardisoError("this PARDISO factor was closed; factorize the matrix again")
        b = np.asarray(b)
        if b.shape[0] != self._m:
            raise ValueError(f"right-hand side has {b.shape[0]} rows; expected {self._m}")
        rhs = np.asfortranarray(b.reshape(self._m, -1), dtype=self._dtype)
        x = np.zeros_like(rhs)
        self._call(33, rhs, x)
        return x.astype(np.float64).reshape(b.shape)

    solve = __call__

    def close(self) -> None:
        """Free PARDISO's memory (also done when the factor is garbage collected)."""
        if self._live:
            self._live = False
            self._call(-1)

    def __del__(self):
        try:
            self.close()
        except Exception:  # noqa: BLE001 - never raise from a finalizer
            pass

    def _call(self, phase: int, b: np.ndarray | None = None, x: np.ndarray | None = None) -> None:
        nrhs = 1 if b is None else b.shape[1]
        b = np.zeros(1, self._dtype) if b is None else b
        x = np.zeros(1, self._dtype) if x is None else x
        error = ctypes.c_int(0)
        self._lib.pardiso(_pointer(self._handle), ctypes.byref(ctypes.c_int(1)), ctypes.byref(ctypes.c_int(1)),
                          ctypes.byref(ctypes.c_int(self._mtype)), ctypes.byref(ctypes.c_int(phase)),
                          ctypes.byref(ctypes.c_int(self._m)), _pointer(self._data), _pointer(self._indptr),
                          _pointer(self._indices), _pointer(self._perm), ctypes.byref(ctypes.c_int(nrhs)),
                          _pointer(self._iparm), ctypes.byref(ctypes.c_int(0)), _pointer(b), _pointer(x),
                          ctypes.byref(error))
        if phase == 12:
            self._live = True  # PARDISO holds memory from the analysis on, even if it then fails
        if error.value != 0:
            raise PardisoError(f"PARDISO phase {phase} failed: error {error.value} "
                               f"({_ERRORS.get(error.value, 'unknown')})")


def _sorted_csr(A: sp.spmatrix) -> sp.csr_matrix:
    """``A`` as CSR with sorted indices, sharing the caller's arrays when it already is one
    (never sorted in place: another thread may be using them)."""
    A = sp.csr_matrix(A)
    return A if A.has_sorted_indices else A.sorted_indices()


def symmetric_upper(A: sp.spmatrix) -> sp.csr_matrix:
    """The upper triangle (diagonal included) of ``(A + A^T) / 2`` as sorted CSR (``A`` (m, m)),
    with ``A``'s pattern (no entry dropped for being zero, so that a factor's analysed pattern
    stays that of the matrices it refactorizes).

    Compiled for a structurally symmetric ``A`` (every FE tangent, contact couplings included):
    much faster than scipy's sparse arithmetic, which a worker thread would spend holding the
    GIL. Any other pattern takes
    that arithmetic."""
    A = _sorted_csr(A)
    if use_jit():
        m = A.shape[0]
        start = np.empty(m, dtype=np.int64)
        indptr = np.zeros(m + 1, dtype=np.int64)
        _upper_starts(A.indptr, A.indices, start, indptr)
        indices = np.empty(indptr[-1], dtype=A.indices.dtype)
        data = np.empty(indptr[-1], dtype=A.data.dtype)
        if _upper_fill(A.indptr, A.indices, A.data, start, indptr, indices, data):
            return sp.csr_matrix((data, indices, indptr), shape=A.shape)
    upper = sp.triu(0.5 * (A + A.T), format="csr")
    upper.sort_indices()
    return upper


@njit
def _upper_starts(indptr, indices, start, u_indptr):  # pragma: no cover - compiled
    """Per row of the sorted CSR ``(indptr, indices)``: the position of its first entry on or
    above the diagonal (``start``), and the row pointer of its upper triangle (``u_indptr``)."""
    for r in range(indptr.size - 1):
        q = indptr[r]
        while q < indptr[r + 1] and indices[q] < r:
            q += 1
        start[r] = q
        u_indptr[r + 1] = u_indptr[r] + indptr[r + 1] - q


@njit
def _upper_fill(indptr, indices, data, start, u_indptr, u_indices, u_data):  # pragma: no cover - compiled
    """The upper triangle of ``(A + A^T) / 2`` into ``(u_indptr, u_indices, u_data)``; False when
    an entry below the diagonal has no transposed partner (not structurally symmetric). One
    pass: the lower entries ``(r, c)`` of a column ``c``, met in increasing ``r``, find their
    partners ``(c, r)`` in increasing order along row ``c``."""
    m = indptr.size - 1
    nxt = start.copy()
    for r in range(m):
        k = u_indptr[r]
        for q in range(start[r], indptr[r + 1]):
            u_indices[k] = indices[q]
            u_data[k] = data[q] if indices[q] == r else 0.5 * data[q]
            k += 1
    for r in range(m):
        for q in range(indptr[r], start[r]):
            c = indices[q]
            p, end = nxt[c], indptr[c + 1]
            while p < end and indices[p] < r:
                p += 1
            if p == end or indices[p] != r:
                return False
            u_data[u_indptr[c] + p - start[c]] += 0.5 * data[q]
            nxt[c] = p + 1
    return True


def _keys(A: sp.csr_matrix) -> np.ndarray:
    """``row * m + column`` of every stored entry (int64)."""
    m = A.shape[1]
    return np.repeat(np.arange(A.shape[0], dtype=np.int64), np.diff(A.indptr)) * m + A.indices


@njit
def _project(indptr, indices, a_indptr, a_indices, a_data, out, outside):  # pragma: no cover - compiled
    """``out[k] = a`` for every entry ``a`` of the sorted CSR ``A`` found at position ``k`` of
    the sorted pattern ``(indptr, indices)``; ``outside[q]`` marks the entries not found."""
    for r in range(indptr.size - 1):
        p, end = indptr[r], indptr[r + 1]
        for q in range(a_indptr[r], a_indptr[r + 1]):
            c = a_indices[q]
            while p < end and indices[p] < c:
                p += 1
            if p < end and indices[p] == c:
                out[p] = a_data[q]
            else:
                outside[q] = True


def _project_numpy(indptr, indices, A, out, outside) -> None:
    """:func:`_project` without numba."""
    m = A.shape[1]
    keys = np.repeat(np.arange(indptr.size - 1, dtype=np.int64), np.diff(indptr)) * m + indices
    a_keys = _keys(A)
    at = np.minimum(np.searchsorted(keys, a_keys), keys.size - 1)
    found = keys[at] == a_keys
    out[at[found]] = A.data[found]
    outside[:] = ~found
