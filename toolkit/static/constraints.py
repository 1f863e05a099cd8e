"""Linear displacement constraints, eliminated by a change of variables ``u = T v + u0``.

Three kinds, enough for the lip-sliding paper's boundary conditions:

- **prescribed** nodes (fixed, moving with a bony segment, projected mucosa):
  all three components given;
- **sliding** nodes (mucosa on the bone, symmetry planes): the component along a unit
  normal is given (``n . u = g``: no separation, no penetration), the tangential ones
  free; a node may carry two sliding rows (an edge of two planes), leaving one
  direction free;
- **ties** (master-slave, lip contact): one component of a slave equals that of its
  master plus an offset (``u_s . e = u_m . e + c``, ``e`` the craniocaudal axis), the
  others free.

The reduced stiffness ``T^T K T`` stays symmetric positive definite, and the constraint
forces follow from the full residual ``K u - f``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

__all__ = ["Constraints", "tangent_frames"]


def tangent_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents ``(k, 3)`` orthogonal to unit ``normals (k, 3)`` and to each other."""
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    helper = np.where(np.abs(n[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


def _as(a, shape, dtype=float):
    a = np.asarray(a, dtype=dtype)
    return a.reshape(shape)


@dataclass(frozen=True, eq=False)
class Constraints:
    """Constraints on ``n_nodes`` nodes (see the module docstring). Lengths in mm.

    Attributes
    ----------
    prescribed_nodes : (p,) int; prescribed_values : (p, 3) mm
    sliding_nodes : (s,) int; sliding_normals : (s, 3) unit; sliding_values : (s,) mm
    tie_slaves, tie_masters : (t,) int; tie_offsets : (t,) mm; tie_axis : component (2 = z)
    """

    n_nodes: int
    prescribed_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    prescribed_values: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    sliding_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    sliding_normals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    sliding_values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tie_slaves: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    tie_masters: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    tie_offsets: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tie_axis: int = 2

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731
        set_("prescribed_nodes", _as(self.prescribed_nodes, (-1,), np.int64))
        set_("prescribed_values", _as(self.prescribed_values, (-1, 3)))
        set_("sliding_nodes", _as(self.sliding_nodes, (-1,), np.int64))
        n = _as(self.sliding_normals, (-1, 3))
        set_("sliding_normals", n / np.linalg.norm(n, axis=1, keepdims=True) if n.size else n)
        set_("sliding_values", _as(self.sliding_values, (-1,)))
        set_("tie_slaves", _as(self.tie_slaves, (-1,), np.int64))
        set_("tie_masters", _as(self.tie_masters, (-1,), np.int64))
        set_("tie_offsets", _as(self.tie_offsets, (-1,)))
        for name, nodes, vals in (("prescribed", self.prescribed_nodes, self.prescribed_values),
                                  ("sliding", self.sliding_nodes, self.sliding_values),
                                  ("tie", self.tie_slaves, self.tie_offsets)):
            if len(nodes) != len(vals):
                raise ValueError(f"{name}: {len(nodes)} nodes but {len(vals)} values")
            if not np.isfinite(vals).all():
                raise ValueError(f"{name} constraint values hold NaN/inf")
        if len(self.tie_masters) != len(self.tie_slaves):
            raise ValueError(f"{len(self.tie_slaves)} tie slaves but {len(self.tie_masters)} masters")
        s_uniq, s_count = np.unique(self.sliding_nodes, return_counts=True)
        if (s_count > 2).any():
            raise ValueError(f"nodes {s_uniq[s_count > 2][:5].tolist()} carry more than two sliding rows; "
                             f"prescribe them instead")
        owned = np.concatenate([self.prescribed_nodes, s_uniq, self.tie_slaves])
        uniq, counts = np.unique(owned, return_counts=True)
        if (counts > 1).any():
            dup = uniq[counts > 1]
            raise ValueError(f"{dup.size} nodes carry two constraints (first: {dup[:5].tolist()}); a node can be "
                             f"prescribed, sliding or a tie slave, not several")
        if np.intersect1d(self.tie_slaves, self.tie_masters).size:
            raise ValueError("a tie master is itself a tie slave (chained ties are not supported)")
        if owned.size and (owned.min() < 0 or owned.max() >= self.n_nodes):
            raise ValueError(f"constraint node index out of range 0..{self.n_nodes - 1}")

    def reduction(self, compact: bool = False) -> tuple[sp.csr_matrix, np.ndarray]:
        """``T (3n, m)`` and ``u0 (3n,)`` with every admissible ``u = T v + u0``.

        A tie slave's own column along the tie axis is left in ``T`` empty unless
        ``compact``: then every system of one set of prescribed and sliding nodes has the
        same size whatever pairs are tied, and a solver can reuse its factorization across
        the lip-contact iterations (the empty columns need a unit equation; their value is 0).
        """
        n = self.n_nodes
        kind = np.zeros(n, dtype=np.int8)  # 0 free, 1 prescribed, 2 sliding
        kind[self.prescribed_nodes] = 1
        kind[self.sliding_nodes] = 2
        free = np.flatnonzero(kind == 0)  # free nodes: unit columns
        col = 3 * free.size
        rows, cols, vals = [(3 * free[:, None] + np.arange(3)).ravel()], [np.arange(col)], [np.ones(col)]
        u0 = np.zeros(3 * n)
        one, two = self._sliding_groups()
        if one[0].size:  # one plane: two tangential columns
            nodes, nrm, g = one
            t1, t2 = tangent_frames(nrm)
            for t in (t1, t2):
                rows.append((3 * nodes[:, None] + np.arange(3)).ravel())
                cols.append(np.repeat(col + np.arange(nodes.size), 3))
                vals.append(t.ravel())
                col += nodes.size
            u0.reshape(-1, 3)[nodes] = g[:, None] * nrm
        if two[0].size:  # two planes: the direction along their intersection stays free
            nodes, n1, n2, g1, g2 = two
            t = np.cross(n1, n2)
            t /= np.linalg.norm(t, axis=1, keepdims=True)
            rows.append((3 * nodes[:, None] + np.arange(3)).ravel())
            cols.append(np.repeat(col + np.arange(nodes.size), 3))
            vals.append(t.ravel())
            col += nodes.size
            c12 = np.einsum("ij,ij->i", n1, n2)
            det = 1.0 - c12**2
            a_, b_ = (g1 - c12 * g2) / det, (g2 - c12 * g1) / det
            u0.reshape(-1, 3)[nodes] = a_[:, None] * n1 + b_[:, None] * n2
        T = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * n, col))
        if self.prescribed_nodes.size:
            u0[(3 * self.prescribed_nodes[:, None] + np.arange(3)).ravel()] = self.prescribed_values.ravel()
        if self.tie_slaves.size:
            a = self.tie_axis
            slave_rows = 3 * self.tie_slaves + a
            master_rows = 3 * self.tie_masters + a
            keep = np.ones(3 * n)
            keep[slave_rows] = 0.0
            E = sp.csr_matrix((np.ones(slave_rows.size), (slave_rows, master_rows)), shape=(3 * n, 3 * n))
            T = (sp.diags(keep) @ T + E @ T).tocsc()
            u0[slave_rows] = u0[master_rows] + self.tie_offsets
            if compact:
                used = np.diff(T.indptr) > 0  # drop the slaves' own (now empty) columns
                T = T[:, used].tocsr()
        return T.tocsr(), u0

    def _sliding_groups(self):
        """Sliding rows grouped by node: ``(nodes, normals, values)`` for nodes with one row and
        ``(nodes, n1, n2, g1, g2)`` for nodes with two (independent normals required)."""
        order = np.argsort(self.sliding_nodes, kind="stable")
        nodes, nrm, g = self.sliding_nodes[order], self.sliding_normals[order], self.sliding_values[order]
        uniq, first, count = np.unique(nodes, return_index=True, return_counts=True)
        f1, f2 = first[count == 1], first[count == 2]
        if f2.size:
            c = np.abs(np.einsum("ij,ij->i", nrm[f2], nrm[f2 + 1]))
            if (c > 1 - 1e-9).any():
                raise ValueError(f"node {nodes[f2][c > 1 - 1e-9][0]} has two parallel sliding normals")
        return (nodes[f1], nrm[f1], g[f1]), (nodes[f2], nrm[f2], nrm[f2 + 1], g[f2], g[f2 + 1])

    def forces(self, residual: np.ndarray) -> dict[str, np.ndarray]:
        """Constraint forces (N) from the full residual ``K u - f``, ``(3n,)``.

        Returns ``{"tie": (t,) force on each slave along the tie axis (> 0 pushes the
        slave in +axis, i.e. compression for an upper-lip slave), "sliding": (s,) normal
        force on each sliding node}``.
        """
        r = residual.reshape(-1, 3)
        return {"tie": r[self.tie_slaves, self.tie_axis] if self.tie_slaves.size else np.zeros(0),
                "sliding": np.einsum("ij,ij->i", r[self.sliding_nodes], self.sliding_normals)
                if self.sliding_nodes.size else np.zeros(0)}
