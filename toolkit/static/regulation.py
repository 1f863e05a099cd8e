"""Mesh regulation between increments (the lip-sliding paper, section 2.3.2.1).

The lip-sliding paper regulates the face mesh at the start of every increment so that distortion,
which accumulates where differently moving regions meet, does not invert elements. Each
linear increment starts stress-free on the current geometry, so the nodes that no
boundary condition holds may be moved without any stress to transfer.

:func:`regulate` does this locally. Around the elements whose quality (minimum corner
scaled Jacobian) is below a target it moves the *movable* nodes (free nodes that are not
on the skin: the skin is the prediction) to raise every corner Jacobian determinant of
those elements above a target: gradient descent on ``sum max(0, tau - D)^2`` over the
corners (Knupp's untangling objective), with a backtracking line search. Movable nodes on
the mesh boundary (the bone side, a free slit face) move in their tangent plane only, so
the boundary shape is kept. Cells ``hex8``, ``wedge6``, ``tet4`` and ``tet10``: a ``tet10``
is regulated by its corner tetrahedron, and then its movable mid-edge nodes take back the
pre-operative shape of their edge (straight for a mesh with straight edges): deformation
curves the edges, and a curved edge folds a quadratic element whose corners are fine. Where an
element is still folded (a mid-edge node that may not move, on a moving bone beside released
tissue, curves its edge), the same descent runs again on the quadratic map's Jacobian
determinants at the points where its quality is sampled, mid-edge nodes included: only the nodes
of the folded elements and of their neighbours move, and every element they belong to is held
above the target.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from toolkit.common.meshes.mesh import VOLUME_TYPES, Mesh
from toolkit.common.meshes.quality import TET10_SAMPLE_GRADIENTS, scaled_jacobian
from toolkit.common.meshes.topology import tet10_mid_edges, triangulated_boundary

__all__ = ["regulate", "Regulation", "element_quality", "CORNERS"]

#: per linear cell type: (corner, three edge ends) with det[x1 - x0, x2 - x0, x3 - x0] > 0 when valid
CORNERS = {
    "hex8": np.array([[0, 1, 3, 4], [1, 2, 0, 5], [2, 3, 1, 6], [3, 0, 2, 7],
                      [4, 7, 5, 0], [5, 4, 6, 1], [6, 5, 7, 2], [7, 6, 4, 3]]),
    "wedge6": np.array([[0, 1, 2, 3], [1, 2, 0, 4], [2, 0, 1, 5], [3, 5, 4, 0], [4, 3, 5, 1], [5, 4, 3, 2]]),
    "tet4": np.array([[0, 1, 2, 3]]),
    "tet10": np.array([[0, 1, 2, 3]]),  # the corner tetrahedron; mid-edge nodes follow it (see _place_mid_edge_nodes)
}


@dataclass(frozen=True)
class Regulation:
    """What :func:`regulate` did.

    Attributes
    ----------
    points : (n, 3) float, mm — the regulated node positions
    moved : int — nodes that moved
    max_shift : float, mm — largest node move
    min_quality_before, min_quality_after : minimum element scaled Jacobian
    """

    points: np.ndarray
    moved: int
    max_shift: float
    min_quality_before: float
    min_quality_after: float


def element_quality(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """Scaled Jacobian ``(E,)`` of every volume element of ``mesh`` at ``points (n, 3)`` mm."""

    return np.concatenate([scaled_jacobian(ctype, points[conn]) for ctype, conn in mesh.cells.items()
                           if ctype in VOLUME_TYPES])


def _by_block(mesh: Mesh, elements: np.ndarray):
    """``(cell type, connectivity, local ids, offset)`` of every volume block holding some of the
    global ``elements``."""
    offset = 0
    for ctype, conn in mesh.cells.items():
        if ctype not in VOLUME_TYPES:
            continue
        sel = elements[(elements >= offset) & (elements < offset + conn.shape[0])] - offset
        if sel.size:
            yield ctype, conn, sel, offset
        offset += conn.shape[0]


def _corner_tables(mesh: Mesh, elements: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Node ids ``(k, 4)`` (corner, three edge ends) of every corner of the given elements,
    and the element of each corner ``(k,)``."""
    out, owner = [], []
    for ctype, conn, sel, offset in _by_block(mesh, elements):
        if ctype in CORNERS:
            out.append(conn[sel][:, CORNERS[ctype]].reshape(-1, 4))
            owner.append(np.repeat(sel + offset, len(CORNERS[ctype])))
    if not out:
        return np.zeros((0, 4), dtype=np.int64), np.zeros(0, dtype=np.int64)
    return np.concatenate(out), np.concatenate(owner)


def _element_adjacency(mesh: Mesh) -> sp.csr_matrix:
    """Node-element incidence ``(n, E)`` of the volume blocks."""
    rows, cols, offset = [], [], 0
    for ctype, conn in mesh.cells.items():
        if ctype not in VOLUME_TYPES:
            continue
        rows.append(conn.ravel())
        cols.append(np.repeat(offset + np.arange(conn.shape[0]), conn.shape[1]))
        offset += conn.shape[0]
    r, c = np.concatenate(rows), np.concatenate(cols)
    return sp.csr_matrix((np.ones(r.size), (r, c)), shape=(mesh.n_points, offset))


def _boundary_normals(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """Area-weighted outward normals ``(n, 3)`` at boundary nodes (zero inside)."""

    tris = triangulated_boundary(mesh.cells)
    x = points[tris]
    nrm = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    out = np.zeros((points.shape[0], 3))
    for k in range(3):
        np.add.at(out, tris[:, k], nrm)
    length = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, length, out=np.zeros_like(out), where=length > 0)


#: a corner tetrahedron's frame as weights on (corner, three edge ends): rows ``x_k - x_0``
_EDGE_WEIGHTS = np.array([[-1.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 1.0]])


def _objective(x: np.ndarray, frames: list, gradient: bool = True):
    """``sum max(0, tau - D)^2`` over the frames and its gradient ``(n, 3)``.

    ``frames`` holds groups ``(nodes (k, p), weights (3, p), tau (k,))``: each of the ``k``
    frames has rows ``sum_a weights[j, a] * x[nodes[:, a]]`` and determinant ``D``."""
    value, grad = 0.0, np.zeros_like(x) if gradient else None
    for nodes, weights, tau in frames:
        rows = np.einsum("jp,kpd->kjd", weights, x[nodes])
        r0, r1, r2 = rows[:, 0], rows[:, 1], rows[:, 2]
        D = np.einsum("ij,ij->i", np.cross(r0, r1), r2)
        short = np.maximum(0.0, tau - D)
        value += float(np.sum(short**2))
        if gradient:
            dD = np.stack([np.cross(r1, r2), np.cross(r2, r0), np.cross(r0, r1)], axis=1)  # d D / d row_j
            np.add.at(grad, nodes, (-2.0 * short)[:, None, None] * np.einsum("jp,kjd->kpd", weights, dD))
    return value, grad


def _tet10_frames(mesh: Mesh, elements: np.ndarray, x: np.ndarray, target: np.ndarray) -> list:
    """The quadratic map's Jacobian of the given ``tet10`` elements at the samples where their
    quality is measured (:data:`~toolkit.common.meshes.quality.TET10_SAMPLE_GRADIENTS`), as frames of
    :func:`_objective`; each aims at ``target`` times the product of its corner tetrahedron's
    edge lengths at node 0 (the scale of stage one's corner frames)."""

    frames = []
    for ctype, conn, sel, offset in _by_block(mesh, elements):
        if ctype != "tet10":
            continue
        nodes = conn[sel]
        scale = np.prod(np.linalg.norm(x[nodes[:, 1:4]] - x[nodes[:, :1]], axis=2), axis=1)
        tau = target[sel + offset] * np.maximum(scale, 1e-27)
        frames += [(nodes, weights, tau) for weights in TET10_SAMPLE_GRADIENTS]
    return frames


def _descend(x: np.ndarray, frames: list, active: np.ndarray, normals: np.ndarray, length: float,
             iterations: int) -> np.ndarray:
    """Gradient descent of :func:`_objective` over the ``active`` nodes of ``x (n, 3)``, those
    with a boundary normal moving in their tangent plane, each step capped at a tenth of the
    local edge ``length`` mm, with a backtracking line search."""
    on_boundary = active & (np.linalg.norm(normals, axis=1) > 0)
    tau_max = max(float(max(np.abs(t).max() for _, _, t in frames)), 1e-30)
    value, grad = _objective(x, frames)
    step = length**2 / tau_max
    for _ in range(iterations):
        if value == 0.0:
            break
        d = -grad
        d[~active] = 0.0
        d[on_boundary] -= np.einsum("ij,ij->i", d[on_boundary], normals[on_boundary])[:, None] * normals[on_boundary]
        # cap the move at a tenth of the local edge length so a step cannot fold neighbours
        dmax = float(np.abs(d).max())
        if dmax == 0.0:
            break
        alpha = min(step, 0.1 * length / dmax)
        for _ in range(30):
            trial = x + alpha * d
            v_trial, _ = _objective(trial, frames, gradient=False)
            if v_trial < value:
                break
            alpha *= 0.5
        else:
            break
        x = trial
        value, grad = _objective(x, frames)
        step = 2.0 * alpha
    return x


def _place_mid_edge_nodes(mesh: Mesh, x: np.ndarray, elements: np.ndarray, movable: np.ndarray) -> np.ndarray:
    """``x`` with the movable mid-edge nodes of the given ``tet10`` elements at their offset
    from their edge's midpoint in ``mesh.points`` (the pre-operative mesh): a straight edge is
    made straight again, a curved one gets its own curvature back."""

    X, out = mesh.points, x.copy()
    for ctype, conn, sel, _ in _by_block(mesh, elements):
        if ctype != "tet10":
            continue
        mid, a, b = tet10_mid_edges(conn[sel])
        placed = 0.5 * (x[a] + x[b]) + X[mid] - 0.5 * (X[a] + X[b])
        out[mid] = np.where(movable[mid][:, None], placed, x[mid])
    return out


def regulate(mesh: Mesh, points: np.ndarray, movable: np.ndarray, target: float | np.ndarray = 0.2,
             rings: int = 2, iterations: int = 200) -> Regulation:
    """Raise the elements below ``target`` quality by moving ``movable`` nodes.

    Parameters
    ----------
    mesh : topology, mm (its points, the pre-operative mesh, give only the shape of ``tet10`` edges)
    points : (n, 3) float, mm — the configuration to regulate
    movable : (n,) bool — nodes that may move (free, not on the skin)
    target : scaled Jacobian the bad elements are raised towards: one number, or one per
        volume element ``(E,)`` (e.g. capped by each element's quality before deformation, so
        that a poor element of a real mesh is kept from inverting, not remeshed)
    rings : element rings around the bad elements whose nodes may move with them
    iterations : gradient steps at most

    Returns
    -------
    Regulation (the input points when nothing is below ``target`` or nothing improved)
    """
    x0 = np.array(points, dtype=float)
    q = element_quality(mesh, x0)
    before = float(q.min())
    target = np.broadcast_to(np.asarray(target, dtype=float), q.shape)
    if np.all(q >= target):
        return Regulation(x0, 0, 0.0, before, before)
    inc = _element_adjacency(mesh)
    nodes = np.asarray(inc[:, q < target].sum(axis=1)).ravel() > 0
    for _ in range(rings):
        elems = np.asarray(inc[nodes].sum(axis=0)).ravel() > 0
        nodes = np.asarray(inc[:, elems].sum(axis=1)).ravel() > 0
    movable = np.asarray(movable, dtype=bool)
    active = nodes & movable
    elems = np.flatnonzero(np.asarray(inc[active].sum(axis=0)).ravel() > 0)
    corners, owner = _corner_tables(mesh, elems)
    if not active.any() or not corners.size:
        return Regulation(x0, 0, 0.0, before, before)
    # target determinant per corner: ``target`` times the product of its edge lengths, with
    # the lengths of the element as it is (a scale-free goal)
    lengths = np.stack([np.linalg.norm(x0[corners[:, k]] - x0[corners[:, 0]], axis=1) for k in (1, 2, 3)], axis=1)
    tau = target[owner] * np.prod(np.maximum(lengths, 1e-9), axis=1)
    normals = _boundary_normals(mesh, x0)
    length = float(np.median(lengths))
    x = _descend(x0.copy(), [(corners, _EDGE_WEIGHTS, tau)], active, normals, length, iterations)
    if "tet10" in mesh.cells:
        x = _place_mid_edge_nodes(mesh, x, elems, active)
    after = element_quality(mesh, x)
    if "tet10" in mesh.cells:
        # an element whose corners are good may still fold along an edge whose mid-edge node
        # cannot move (on a bone, on the skin) or was put back on a neighbour's straight edge:
        # then the quadratic map's own Jacobian is what the nodes are moved for
        folded = elems[after[elems] <= 0.0]
        if folded.size:
            # only the nodes of the folded elements and of their neighbours move, guarded by
            # every element they belong to: the rest of the regulated region keeps stage one's answer
            near = np.asarray(inc[:, folded].sum(axis=1)).ravel() > 0
            near = np.asarray(inc[:, np.asarray(inc[near].sum(axis=0)).ravel() > 0].sum(axis=1)).ravel() > 0
            near &= active
            guard = np.flatnonzero(np.asarray(inc[near].sum(axis=0)).ravel() > 0)
            frames = _tet10_frames(mesh, guard, x, target)
            if frames:  # (a folded element of another cell type has no quadratic map)
                x = _descend(x, frames, near, normals, length, iterations)
                after = element_quality(mesh, x)
    if after.min() <= before:  # no better than the start: leave the mesh as it was
        return Regulation(x0, 0, 0.0, before, before)
    shift = np.linalg.norm(x - x0, axis=1)
    return Regulation(x, int((shift > 0).sum()), float(shift.max()), before, float(after.min()))
