"""Fill-reducing orderings and the expected size of a factor, from the sparsity pattern alone."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from toolkit.common.runtime import deferred_interrupt

__all__ = ["ORDERINGS", "fill_reducing_order", "estimate_factor_entries"]

#: orderings of a SuperLU factorization: METIS nested dissection, or SuperLU's minimum degree
ORDERINGS = ("nd", "mmd")


def fill_reducing_order(A: sp.spmatrix) -> np.ndarray:
    """METIS nested dissection of ``A + A^T``'s graph: a permutation ``(m,)`` of the unknowns.

    An ``A`` of ``3 k`` unknowns is taken as ``k`` nodes of 3 dofs (node-major, as every
    pattern of :mod:`toolkit.common.fem.assembly` is): the ordering of the node graph, each
    node's dofs kept together, which costs less than ordering the dof graph for the same
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
    # pymetis (pybind11) aborts the process when a Ctrl-C reaches Python inside its call
    with deferred_interrupt():
        perm, _ = pymetis.nested_dissection(pymetis.CSRAdjacency(graph.indptr, graph.indices))
    perm = np.asarray(perm, dtype=np.int64)
    return (block * perm[:, None] + np.arange(block)).ravel()


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
