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

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

from toolkit.common.fem.jit import njit, use_jit

__all__ = ["SparsePattern", "element_tangent", "add_local"]


def element_tangent(grad: np.ndarray, weight: np.ndarray, A: np.ndarray, symmetric: bool = False) -> np.ndarray:
    """Element tangent stiffness ``(E, 3n, 3n)`` N/mm from ``dP/dF``.

    ``K[(a,i),(b,k)] = sum_q w_q dN_a/dX_J A_iJkL dN_b/dX_L``, dofs ordered node by node
    (``3 a + i``); ``symmetric`` returns ``(K + K^T) / 2``.

    Compiled (:mod:`toolkit.common.fem.jit`) when numba is available: one pass per element
    that writes ``K`` in place, where the numpy reference below makes two einsum products and
    a reshaping copy of the ``(E, n, 3, n, 3)`` result.

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


@njit
def _assemble_tangent_kernel(grad, weight, A, symmetric, pair_pos, conn, node_start, row_len, order,
                             data):  # pragma: no cover - compiled
    """:func:`element_tangent` of one block scattered straight into the CSR ``data``: entry
    ``(3 a + i, 3 b + k)`` of element ``e`` goes to ``node_start[na] + i row_len[na] +
    pair_pos[e, a, b] + k`` (``na = conn[e, a]``; every dof row of a node has the same columns,
    each node's three consecutive). ``symmetric``: from the major-symmetrized
    ``(A_iJkL + A_kLiJ) / 2``, whose element matrix is ``(K + K^T) / 2``, computing the node
    blocks ``b >= a`` only and mirroring them. Elements are visited in ``order`` (by their
    lowest node), so that consecutive ones write to nearby rows."""
    E, Q, n, _ = grad.shape
    G = np.empty((n, 3, 3, 3))  # w dN_a/dX_J A_iJkL of one point: (a, i, k, L)
    As = np.empty((3, 3, 3, 3))
    Ke = np.empty((3 * n, 3 * n))
    for e in order:
        Ke[:] = 0.0
        for q in range(Q):
            w = weight[e, q]
            if symmetric:
                for i in range(3):
                    for J in range(3):
                        for k in range(3):
                            for L in range(3):
                                As[i, J, k, L] = 0.5 * (A[e, q, i, J, k, L] + A[e, q, k, L, i, J])
            else:
                As[:] = A[e, q]
            for a in range(n):  # the loads hoisted and the J sum unrolled: faster than plain loops
                g0, g1, g2 = w * grad[e, q, a, 0], w * grad[e, q, a, 1], w * grad[e, q, a, 2]
                for i in range(3):
                    for k in range(3):
                        for L in range(3):
                            G[a, i, k, L] = g0 * As[i, 0, k, L] + g1 * As[i, 1, k, L] + g2 * As[i, 2, k, L]
            for b in range(n):
                h0, h1, h2 = grad[e, q, b, 0], grad[e, q, b, 1], grad[e, q, b, 2]
                for a in range(b + 1 if symmetric else n):
                    for i in range(3):
                        for k in range(3):
                            Ke[3 * a + i, 3 * b + k] += G[a, i, k, 0] * h0 + G[a, i, k, 1] * h1 + G[a, i, k, 2] * h2
        for a in range(n):
            na = conn[e, a]
            for b in range(a if symmetric else 0, n):  # Ke holds the blocks b >= a when symmetric
                nb = conn[e, b]
                for i in range(3):
                    row = node_start[na] + i * row_len[na] + pair_pos[e, a, b]
                    for k in range(3):
                        data[row + k] += Ke[3 * a + i, 3 * b + k]
                if symmetric and b != a:  # the mirrored block (b, a)
                    for k in range(3):
                        row = node_start[nb] + k * row_len[nb] + pair_pos[e, b, a]
                        for i in range(3):
                            data[row + i] += Ke[3 * a + i, 3 * b + k]


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
        n = int(n_nodes)
        self.n_dofs = 3 * n
        self.block_dofs = []
        conns = [np.asarray(conn, dtype=np.int64) for conn in _as_blocks(blocks)]
        # the node graph first (an element's n^2 node pairs, not its 9 n^2 dof pairs): each
        # node's three dof rows hold the same columns, each neighbour's three dofs side by side
        pairs, inverse = np.unique(np.concatenate([(c[:, :, None] * n + c[:, None, :]).ravel() for c in conns]),
                                   return_inverse=True)
        first, second = pairs // n, pairs % n
        degree = np.bincount(first, minlength=n)
        pair_start = np.concatenate([[0], np.cumsum(degree)[:-1]])  # each node's first pair
        row_len = 3 * degree
        node_start = np.concatenate([[0], np.cumsum(3 * row_len)[:-1]])  # data index of each node's first row
        self.nnz = int(9 * pairs.size)
        self.indptr = np.concatenate([[0], np.cumsum(np.repeat(row_len, 3))]).astype(np.int32)
        self.rows = np.repeat(np.arange(self.n_dofs), np.repeat(row_len, 3))
        # column of entry j of row 3 a + i: 3 second[pair_start[a] + j // 3] + j % 3
        offset = np.arange(self.nnz) - self.indptr[:-1].astype(np.int64)[self.rows]
        self.cols = 3 * second[pair_start[self.rows // 3] + offset // 3] + offset % 3
        self.indices = self.cols.astype(np.int32)
        slots, start = [], 0
        for conn in conns:
            E, m = conn.shape
            self.block_dofs.append((3 * conn[:, :, None] + np.arange(3)).reshape(E, -1))  # (E, 3n)
            p = inverse[start:start + E * m * m].reshape(E, m, m)  # the pair of nodes (a, b)
            start += E * m * m
            a = first[p]
            base = node_start[a] + 3 * (p - pair_start[a])  # entry (3a, 3b) in the data
            ik = (np.arange(3)[:, None] * row_len[a][..., None, None] + np.arange(3))  # (E, m, m, 3, 3)
            slots.append((base[..., None, None] + ik).transpose(0, 1, 3, 2, 4).ravel())
        self._slot = np.concatenate(slots)
        self._vector_dofs = np.concatenate([d.ravel() for d in self.block_dofs])
        self._diagonal = np.flatnonzero(self.rows == self.cols)
        self._held = None  # (dofs as bytes, entries to zero, diagonal entries to set) of the last constrain
        self._layout = None  # node blocks' places in the CSR data (assemble_tangent)
        self._node_graph = None

    @property
    def dofs(self) -> np.ndarray:
        """``(E, 3n)`` element dofs of a single-block pattern."""
        if len(self.block_dofs) != 1:
            raise ValueError(f"the pattern has {len(self.block_dofs)} blocks; use block_dofs")
        return self.block_dofs[0]

    def node_graph(self) -> sp.csr_matrix:
        """Node adjacency ``(n_nodes, n_nodes)``: 1 where two nodes share an element (built at the
        first call, then the same matrix: do not modify it)."""
        if self._node_graph is None:
            keep = (self.rows % 3 == 0) & (self.cols % 3 == 0)  # one entry per node pair
            n = self.n_dofs // 3
            self._node_graph = sp.csr_matrix((np.ones(int(keep.sum())), (self.rows[keep] // 3, self.cols[keep] // 3)),
                                             shape=(n, n))
        return self._node_graph

    def assemble(self, element_matrices: np.ndarray | Sequence[np.ndarray]) -> sp.csr_matrix:
        """The global matrix ``(3 n_nodes, 3 n_nodes)`` from one ``(E, 3n, 3n)`` array per block."""
        blocks = [np.asarray(k, dtype=np.float64).reshape(-1) for k in _as_blocks(element_matrices)]
        if use_jit():  # one pass over each block, no concatenated copy
            data = np.zeros(self.nnz)
            start = 0
            for values in blocks:
                _scatter_add(self._slot[start:start + values.size], values, data)
                start += values.size
        else:
            data = np.bincount(self._slot, weights=np.concatenate(blocks), minlength=self.nnz)
        return self._matrix(data)

    def assemble_tangent(self, blocks: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
                         symmetric: bool = False) -> sp.csr_matrix:
        """The global tangent ``(3 n_nodes, 3 n_nodes)`` N/mm from ``(grad, weight, A)`` per
        block (the arguments of :func:`element_tangent`, blocks in the pattern's order):
        ``assemble([element_tangent(*b, symmetric) for b in blocks])``, and equal to it to
        round-off. Compiled, it writes each element's matrix straight into the CSR data
        (no ``(E, 3n, 3n)`` array: 72 MB for the paper impact face) and, ``symmetric``,
        computes only the upper node blocks."""
        blocks = list(blocks)
        if len(blocks) != len(self.block_dofs):
            raise ValueError(f"{len(blocks)} tangent blocks for a pattern of {len(self.block_dofs)} element blocks")
        if not use_jit():
            return self.assemble([element_tangent(g, w, A, symmetric) for g, w, A in blocks])
        node_start, row_len, layout = self._node_layout()
        data = np.zeros(self.nnz)
        for (grad, weight, A), dofs, (pos, conn, order) in zip(blocks, self.block_dofs, layout):
            E, Q, n, _ = grad.shape
            if dofs.shape != (E, 3 * n):
                raise ValueError(f"tangent block of {E} elements x {n} nodes for a pattern block of {dofs.shape[0]} "
                                 f"elements x {dofs.shape[1] // 3} nodes")
            _assemble_tangent_kernel(np.asarray(grad, dtype=np.float64), np.asarray(weight, dtype=np.float64),
                                     np.asarray(A, dtype=np.float64).reshape(E, Q, 3, 3, 3, 3), bool(symmetric),
                                     pos, conn, node_start, row_len, order, data)
        return self._matrix(data)

    def _matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """The pattern's CSR matrix with values ``data``, flagged canonical (its column indices
        are sorted and unique by construction: no O(nnz) check later)."""
        K = sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n_dofs, self.n_dofs))
        K.has_canonical_format = True
        return K

    def _node_layout(self):
        """Where a node pair's 3x3 block sits in the CSR data (built at the first
        :meth:`assemble_tangent`): the first entry of each node's rows ``(n_nodes,)``, the
        length of each of its three rows ``(n_nodes,)``, and per block ``(pair_pos, conn,
        order)``: ``(E, n, n)`` int32 the offset of column node ``b``'s first dof in the rows of
        node ``a``, the ``(E, n)`` nodes, and the elements by their lowest node (a more local
        walk through the data than storage order, whose tet10 mid-edge nodes are numbered far
        from the corners)."""
        if self._layout is None:
            node_start = self.indptr[:-1:3].astype(np.int64)
            row_len = np.diff(self.indptr)[::3].astype(np.int64)
            blocks, start = [], 0
            for dofs in self.block_dofs:
                E, m = dofs.shape
                slot = self._slot[start:start + E * m * m].reshape(E, m, m)[:, ::3, ::3]
                start += E * m * m
                conn = np.ascontiguousarray(dofs[:, ::3] // 3)
                pos = (slot - node_start[conn][:, :, None]).astype(np.int32)
                blocks.append((pos, conn, np.argsort(conn.min(axis=1), kind="stable")))
            self._layout = (node_start, row_len, blocks)
        return self._layout

    def assemble_vector(self, element_vectors: np.ndarray | Sequence[np.ndarray]) -> np.ndarray:
        """The global vector ``(3 n_nodes,)`` from one ``(E, 3n)`` array per block."""
        data = np.concatenate([np.asarray(f, dtype=np.float64).reshape(-1) for f in _as_blocks(element_vectors)])
        return np.bincount(self._vector_dofs, weights=data, minlength=self.n_dofs)

    def constrain(self, K: sp.csr_matrix, dofs: np.ndarray, copy: bool = True) -> sp.csr_matrix:
        """``K`` (this pattern) with the rows and columns of ``dofs`` zeroed and a unit diagonal
        there, so that a solve leaves those dofs unchanged (a zero right-hand side on them);
        ``copy=False`` changes ``K``'s values in place (a matrix just assembled)."""
        dofs = np.asarray(dofs, dtype=np.int64)
        key = dofs.tobytes()
        if self._held is None or self._held[0] != key:  # a Newton run constrains the same dofs every time
            held = np.zeros(self.n_dofs, dtype=bool)
            held[dofs] = True
            zero = np.flatnonzero(held[self.rows] | held[self.cols])
            self._held = (key, zero, self._diagonal[held[self.rows[self._diagonal]]])
        _, zero, diag = self._held
        if not copy:
            K.data[zero] = 0.0
            K.data[diag] = 1.0
            return K
        data = K.data.copy()
        data[zero] = 0.0
        data[diag] = 1.0
        return self._matrix(data)


def add_local(K: sp.csr_matrix, C: sp.csr_matrix) -> sp.csr_matrix:
    """``K + C`` as CSR with sorted indices, for an assembled ``K`` and a term ``C`` on few rows
    (penalty contact): the runs of rows ``C`` leaves alone are copied whole, the others merged.
    ``K`` must be CSR with sorted, unique indices (as :class:`SparsePattern` makes them); ``C``
    is brought to that form. scipy's ``K + C`` merges every row."""
    if K.shape != C.shape:
        raise ValueError(f"shapes differ: {K.shape} and {C.shape}")
    if not sp.isspmatrix_csr(K) or not K.has_canonical_format:
        raise ValueError("add_local needs K as CSR with sorted, unique indices (call K.sum_duplicates())")
    C = sp.csr_matrix(C)
    if not C.has_canonical_format:
        C = C.copy()
        C.sum_duplicates()
    if not use_jit():
        return (K + C).tocsr()
    rows = np.flatnonzero(np.diff(C.indptr))  # the rows C touches
    new = np.zeros(K.shape[0] + 1, dtype=np.int64)  # per row: C's columns not in K's row
    new[rows + 1] = _new_columns(K.indptr, K.indices, C.indptr, C.indices, rows)
    indptr = K.indptr + np.cumsum(new)
    indices = np.empty(indptr[-1], dtype=K.indices.dtype)
    data = np.empty(indptr[-1], dtype=np.result_type(K.dtype, C.dtype))
    _merge_rows(K.indptr, K.indices, K.data, C.indptr, C.indices, C.data, rows, indptr, indices, data)
    out = sp.csr_matrix((data, indices, indptr.astype(K.indptr.dtype, copy=False)), shape=K.shape)
    out.has_sorted_indices = True
    return out


@njit
def _new_columns(k_ptr, k_idx, c_ptr, c_idx, rows):  # pragma: no cover - compiled
    """For each of ``rows``: how many of ``C``'s columns ``K``'s row lacks."""
    out = np.zeros(rows.size, dtype=np.int64)
    for i in range(rows.size):
        r = rows[i]
        a, a_end = k_ptr[r], k_ptr[r + 1]
        for b in range(c_ptr[r], c_ptr[r + 1]):
            while a < a_end and k_idx[a] < c_idx[b]:
                a += 1
            if a >= a_end or k_idx[a] != c_idx[b]:
                out[i] += 1
    return out


@njit
def _merge_rows(k_ptr, k_idx, k_val, c_ptr, c_idx, c_val, rows, indptr, indices, data):  # pragma: no cover
    """Fill the sum: the runs of rows between ``rows`` as blocks, ``rows`` merged."""
    n = k_ptr.size - 1
    done = 0  # rows before this are written
    for i in range(rows.size + 1):
        r = rows[i] if i < rows.size else n
        a, a_end, p = k_ptr[done], k_ptr[r], indptr[done]  # the run of untouched rows
        indices[p:p + a_end - a] = k_idx[a:a_end]
        data[p:p + a_end - a] = k_val[a:a_end]
        if r == n:
            break
        a, a_end, b, b_end, p = k_ptr[r], k_ptr[r + 1], c_ptr[r], c_ptr[r + 1], indptr[r]
        while a < a_end or b < b_end:
            if b >= b_end or (a < a_end and k_idx[a] < c_idx[b]):
                indices[p], data[p] = k_idx[a], k_val[a]
                a += 1
            elif a >= a_end or c_idx[b] < k_idx[a]:
                indices[p], data[p] = c_idx[b], c_val[b]
                b += 1
            else:
                indices[p], data[p] = k_idx[a], k_val[a] + c_val[b]
                a += 1
                b += 1
            p += 1
        done = r + 1
