"""The geometric coarse space of a quadratic mesh: its corner nodes' linear field (p-multigrid).

Smoothed aggregation (pyamg) converges slowly on quadratic tetrahedra: on a tet10 ``toolkit
mesh`` face (nu = 0.47) conjugate gradients need many more iterations than on the phantom's
trilinear hexahedra, and more as the mesh is refined. The coarse space that suits
them is the linear element on their corner nodes: a mid-edge node takes the mean of its edge's
two corners, which reproduces every linear field, the rigid-body modes among them. With this
interpolation as the first coarsening and smoothed aggregation on the corner-node system from
there, CG needs fewer iterations and less time per solve (``benchmarks/static_solvers.py``, rows
``meshed-5mm`` and ``meshed-3mm``).

:func:`corner_interpolation` builds the interpolation once per mesh; :func:`reduced_coarse_space`
carries it into the reduced variables of a set of constraints (``u = T v + u0``) for
:func:`~toolkit.common.fem.factors.amg_hierarchy`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from toolkit.common.fem.reference import TET_EDGES
from toolkit.common.fem.solvers import rigid_body_modes

__all__ = ["CornerInterpolation", "CoarseSpace", "corner_interpolation", "reduced_coarse_space"]

#: a reduced coarse column is kept when its norm is at least this (a corner whose own dofs are all
#: prescribed keeps only the halves its mid-edge neighbours give it, and drops out when all are)
MIN_COLUMN_NORM = 0.25


@dataclass(frozen=True, eq=False)
class CornerInterpolation:
    """The interpolation of a quadratic mesh's displacement from its corner nodes.

    Attributes
    ----------
    P : (3 n, 3 c) sparse, dof-major per node like the stiffness: corner ``j``'s dofs are
        ``3 j .. 3 j + 2`` of the coarse space
    corners : (c,) int, the mesh nodes that are corners, in coarse order
    """

    P: sp.csr_matrix
    corners: np.ndarray


@dataclass(frozen=True, eq=False)
class CoarseSpace:
    """A coarse space in a system's own variables.

    Attributes
    ----------
    P : (m, k) sparse, the prolongation from the coarse space to the ``m`` unknowns
    modes : (k, r) the near-nullspace (rigid-body modes) of the coarse system
    """

    P: sp.csr_matrix
    modes: np.ndarray


def corner_interpolation(blocks: dict[str, np.ndarray], n_nodes: int) -> CornerInterpolation | None:
    """The corner-node interpolation of a mesh whose volume blocks ``blocks`` (cell type ->
    (E, nodes) int) hold ``tet10`` cells, or None when none do (a linear mesh is its own coarse
    space). Nodes of other blocks (a hexahedral part) count as corners."""
    if "tet10" not in blocks or not len(blocks["tet10"]):
        return None
    cells = np.asarray(blocks["tet10"], dtype=np.int64)
    mid, first = np.unique(cells[:, 4:].ravel(), return_index=True)
    ends = (cells[:, TET_EDGES[:, 0]].ravel()[first], cells[:, TET_EDGES[:, 1]].ravel()[first])
    is_mid = np.zeros(n_nodes, dtype=bool)
    is_mid[mid] = True
    corners = np.flatnonzero(~is_mid)
    index = np.full(n_nodes, -1, dtype=np.int64)
    index[corners] = np.arange(corners.size)
    rows = np.concatenate([corners, mid, mid])
    cols = np.concatenate([index[corners], index[ends[0]], index[ends[1]]])
    vals = np.concatenate([np.ones(corners.size), np.full(2 * mid.size, 0.5)])
    nodal = sp.csr_matrix((vals, (rows, cols)), shape=(n_nodes, corners.size))
    return CornerInterpolation(sp.kron(nodal, sp.identity(3), format="csr"), corners)


def reduced_coarse_space(interp: CornerInterpolation, T: sp.spmatrix, points: np.ndarray) -> CoarseSpace:
    """``interp`` in the reduced variables ``v`` of ``u = T v + u0`` (``T`` (3 n, m)): the
    coarse displacement's interpolation projected onto ``T``'s columns (each scaled by its squared
    norm, so that a tie's merged column takes the value, not twice it), without the coarse
    columns nearly all of whose support is prescribed. ``points`` (n, 3) mm: the mesh's nodes,
    for the coarse rigid-body modes."""

    T = sp.csr_matrix(T)
    scale = np.asarray(T.multiply(T).sum(axis=0)).ravel()
    P = (sp.diags(1.0 / np.maximum(scale, 1e-300)) @ (T.T @ interp.P)).tocsc()
    keep = np.sqrt(np.asarray(P.multiply(P).sum(axis=0)).ravel()) >= MIN_COLUMN_NORM
    return CoarseSpace(P[:, keep].tocsr(), rigid_body_modes(points[interp.corners])[keep])
