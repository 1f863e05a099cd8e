"""Vectorised assembly of element matrices into one fixed sparse pattern.

An implicit solver assembles the same pattern at every Newton iteration; only the values
change. :class:`SparsePattern` sorts the element dofs into a CSR structure once and keeps,
for every entry of every element matrix, its position in the CSR data, so each assembly is
one scatter-add (compiled, or ``np.bincount``; no COO sort per iteration).
:func:`element_tangent` turns material tangents ``dP/dF`` at the integration points into
element stiffness matrices.

Units follow the caller (mm, N, MPa: stiffness in N/mm).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import scipy.sparse as sp

from toolkit.common.fem.jit import njit, use_jit

__all__ = ["SparsePattern", "element_tangent"]


def element_tangent(grad: np.ndarray, weight: np.ndarray, A: np.ndarray, symmetric: bool = False) -> np.ndarray:
    """Element tangent stiffness ``(E, 3n, 3n)`` N/mm from ``dP/dF``.

    ``K[(a,i),(b,k)] = sum_q w_q dN_a/dX_J A_iJkL dN_b/dX_L``, dofs ordered node by node
    (``3 a + i``); ``symmetric`` returns ``(K + K^T) / 2``.

    Compiled (:mod:`toolkit.common.fem.jit`) when numba is available: one pass per element
    that writes ``K`` in place, where the numpy reference below makes two einsum products and
    a reshaping copy of the ``(E, n, 3, n, 3)`` result (12,000 tet10 elements with 4 points,
    symmetrized: 0.07 s against 0.45 s).

    Parameters
    ----------
    grad : (E, Q, n, 3) 1/mm, shape-function gradients in the reference configuration
    weight : (E, Q) mm^3, integration weights (reference volume per point)
    A : (E, Q, 3, 3, 3, 3) MPa, material tangent ``dP_iJ / dF_kL`` (may be a broadcast view)
    symmetric : symmetrize the result
    """
    E, Q, n, _ = grad.shape
    if use_jit():
        K = np.empty((E, 3 * n, 3 * n))
        _element_tangent_kernel(np.asarray(grad, dtype=np.float64), np.asarray(weight, dtype=np.float64),
                                np.asarray(A, dtype=np.float64), bool(symmetric), K)
        return K
    # (E,Q,a,J) x (E,Q,i,J,k,L) -> (E,Q,a,i,k,L), then x (E,Q,b,L) -> (E,a,i,b,k)
    gA = np.einsum("eqaj,eqijkl->eqaikl", grad * weight[..., None, None], A, optimize=True)
    K = np.einsum("eqaikl,eqbl->eaibk", gA, grad, optimize=True).reshape(E, 3 * n, 3 * n)
    return 0.5 * (K + np.swapaxes(K, 1, 2)) if symmetric else K


@njit
def _element_tangent_kernel(grad, weight, A, symmetric, out):  # pragma: no cover - compiled
    """:func:`element_tangent` into ``out (E, 3n, 3n)``, element by element."""
    E, Q, n, _ = grad.shape
    G = np.empty((n, 3, 3, 3))  # w dN_a/dX_J A_iJkL of one point: (a, i, k, L)
    for e in range(E):
        out[e] = 0.0
        for q in range(Q):
            w = weight[e, q]
            for a in range(n):
                for i in range(3):
                    for k in range(3):
                        for L in range(3):
                            s = 0.0
                            for J in range(3):
                                s += grad[e, q, a, J] * A[e, q, i, J, k, L]
                            G[a, i, k, L] = w * s
            for a in range(n):
                for i in range(3):
                    for b in range(n):
                        for k in range(3):
                            s = 0.0
                            for L in range(3):
                                s += G[a, i, k, L] * grad[e, q, b, L]
                            out[e, 3 * a + i, 3 * b + k] += s
        if symmetric:
            for p in range(3 * n):
                for r in range(p + 1, 3 * n):
                    v = 0.5 * (out[e, p, r] + out[e, r, p])
                    out[e, p, r] = v
                    out[e, r, p] = v


@njit
def _scatter_add(slot, values, out):  # pragma: no cover - compiled
    """``out[slot[i]] += values[i]`` for every ``i``."""
    for i in range(values.size):
        out[slot[i]] += values[i]


def _as_blocks(a) -> list[np.ndarray]:
    """One array, or a sequence of per-block arrays, as a list."""
    return [a] if isinstance(a, np.ndarray) else list(a)


class SparsePattern:
    """The CSR pattern of a stiffness matrix assembled from element blocks, built once per topology.

    Parameters
    ----------
    blocks : (E, n) int array of global node ids, or a sequence of them, one per element block
        (bodies of several element types or meshes may share one pattern)
    n_nodes : nodes of the model (3 dofs each, node-major: dof ``3 * node + component``)

    ``assemble`` sums element matrices (``(E, 3n, 3n)``, one array per block in the same
    order) into CSR with one scatter-add; ``assemble_vector`` does the same for element
    vectors. The pattern is reused for every increment and Newton iteration.
    """

    def __init__(self, blocks: np.ndarray | Sequence[np.ndarray], n_nodes: int):
        self.n_dofs = 3 * int(n_nodes)
        self.block_dofs = []
        keys = []
        for conn in _as_blocks(blocks):
            conn = np.asarray(conn, dtype=np.int64)
            dofs = (3 * conn[:, :, None] + np.arange(3)).reshape(conn.shape[0], -1)  # (E, 3n)
            self.block_dofs.append(dofs)
            keys.append((dofs[:, :, None] * self.n_dofs + dofs[:, None, :]).ravel())
        unique, inverse = np.unique(np.concatenate(keys), return_inverse=True)
        self.rows, self.cols = unique // self.n_dofs, unique % self.n_dofs
        self.indices = self.cols.astype(np.int32)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(self.rows, minlength=self.n_dofs))]).astype(np.int32)
        self.nnz = unique.size
        self._slot = inverse.ravel()
        self._vector_dofs = np.concatenate([d.ravel() for d in self.block_dofs])
        self._diagonal = np.flatnonzero(self.rows == self.cols)
        self._held = None  # (dofs as bytes, entries to zero, diagonal entries to set) of the last constrain

    @property
    def dofs(self) -> np.ndarray:
        """``(E, 3n)`` element dofs of a single-block pattern."""
        if len(self.block_dofs) != 1:
            raise ValueError(f"the pattern has {len(self.block_dofs)} blocks; use block_dofs")
        return self.block_dofs[0]

    def node_graph(self) -> sp.csr_matrix:
        """Node adjacency ``(n_nodes, n_nodes)``: 1 where two nodes share an element."""
        keep = (self.rows % 3 == 0) & (self.cols % 3 == 0)  # one entry per node pair
        n = self.n_dofs // 3
        return sp.csr_matrix((np.ones(int(keep.sum())), (self.rows[keep] // 3, self.cols[keep] // 3)), shape=(n, n))

    def assemble(self, element_matrices: np.ndarray | Sequence[np.ndarray]) -> sp.csr_matrix:
        """The global matrix ``(3 n_nodes, 3 n_nodes)`` from one ``(E, 3n, 3n)`` array per block."""
        blocks = [np.asarray(k, dtype=np.float64).reshape(-1) for k in _as_blocks(element_matrices)]
        if use_jit():  # one pass over each block, no concatenated copy: 0.03 s against 0.13 s for the
            data = np.zeros(self.nnz)  # paper impact face with its ball (10 M entries)
            start = 0
            for values in blocks:
                _scatter_add(self._slot[start:start + values.size], values, data)
                start += values.size
        else:
            data = np.bincount(self._slot, weights=np.concatenate(blocks), minlength=self.nnz)
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n_dofs, self.n_dofs))

    def assemble_vector(self, element_vectors: np.ndarray | Sequence[np.ndarray]) -> np.ndarray:
        """The global vector ``(3 n_nodes,)`` from one ``(E, 3n)`` array per block."""
        data = np.concatenate([np.asarray(f, dtype=np.float64).reshape(-1) for f in _as_blocks(element_vectors)])
        return np.bincount(self._vector_dofs, weights=data, minlength=self.n_dofs)

    def constrain(self, K: sp.csr_matrix, dofs: np.ndarray) -> sp.csr_matrix:
        """``K`` (this pattern) with the rows and columns of ``dofs`` zeroed and a unit diagonal
        there, so that a solve leaves those dofs unchanged (a zero right-hand side on them)."""
        dofs = np.asarray(dofs, dtype=np.int64)
        key = dofs.tobytes()
        if self._held is None or self._held[0] != key:  # a Newton run constrains the same dofs every time
            held = np.zeros(self.n_dofs, dtype=bool)
            held[dofs] = True
            zero = np.flatnonzero(held[self.rows] | held[self.cols])
            self._held = (key, zero, self._diagonal[held[self.rows[self._diagonal]]])
        _, zero, diag = self._held
        data = K.data.copy()
        data[zero] = 0.0
        data[diag] = 1.0
        return sp.csr_matrix((data, self.indices, self.indptr), shape=K.shape)
