"""One record per cell type: the reference element.

A :class:`ReferenceElement` holds every fact about a cell type that the workflows and
the file formats need: reference node coordinates, shape functions and their
gradients, quadrature rules, corner nodes, edges, outward faces, and the names the
cell has in meshio, VTK and Abaqus. Look one up with :func:`reference_element` or in
:data:`REFERENCE_ELEMENTS`.

Reference cells and node orders (``xi`` are the reference coordinates):

- ``hex8`` (VTK/meshio hexahedron, Abaqus C3D8/C3D8R/C3D8H): [-1, 1]^3, corners
  ``0:(-,-,-) 1:(+,-,-) 2:(+,+,-) 3:(-,+,-) 4:(-,-,+) 5:(+,-,+) 6:(+,+,+) 7:(-,+,+)``.
- ``wedge6`` (meshio ``wedge``, Abaqus C3D6, gmsh prism): unit triangle x [-1, 1],
  ``0:(0,0,-1) 1:(1,0,-1) 2:(0,1,-1) 3:(0,0,1) 4:(1,0,1) 5:(0,1,1)``. The right-hand
  normal of the (0, 1, 2) triangle points INTO the element, towards (3, 4, 5). VTK's
  wedge (id 13) uses the opposite convention: VTK node ``k`` is our node
  ``vtk_order[k]`` with ``vtk_order = [0, 2, 1, 3, 5, 4]`` (meshio applies the same
  permutation when it writes VTU).
- ``tet4`` (C3D4): the unit simplex, ``0:(0,0,0) 1:(1,0,0) 2:(0,1,0) 3:(0,0,1)``.
- ``tet10`` (C3D10): ``tet4`` plus mid-edge nodes 4..9 on edges (0,1) (1,2) (0,2)
  (0,3) (1,3) (2,3) (VTK, meshio and Abaqus agree).
- ``tri3`` (S3/STRI3): the unit triangle; ``quad4`` (S4/S4R): [-1, 1]^2 counter-clockwise.

Positively oriented cells (det dx/dxi > 0) have the faces listed in ``faces`` ordered
counter-clockwise when seen from outside (right-hand normal outward).

Everything here is dimensionless (reference coordinates); arrays are read-only.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from toolkit.common.fem import quadrature as _q

__all__ = ["ReferenceElement", "REFERENCE_ELEMENTS", "reference_element", "TET_EDGES", "WEDGE_VTK_ORDER"]

#: corner pairs of the tetrahedron edges, in the order of the tet10 mid-edge nodes
TET_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
#: VTK wedge node k is our (Abaqus/gmsh/meshio) wedge node WEDGE_VTK_ORDER[k]; the map is its own inverse
WEDGE_VTK_ORDER = np.array([0, 2, 1, 3, 5, 4])


def _ro(a, dtype=float) -> np.ndarray:
    a = np.array(a, dtype=dtype)
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class ReferenceElement:
    """The facts of one cell type.

    Attributes
    ----------
    name : our name (``hex8``, ``wedge6``, ``tet4``, ``tet10``, ``tri3``, ``quad4``)
    n_nodes : nodes per cell
    dim : dimension of the reference cell (3 volume, 2 surface)
    nodes : (n_nodes, dim) reference coordinates
    corners : (k,) local indices of the corner (vertex) nodes
    edges : (m, 2) local corner pairs of the edges
    faces : tuple of (n_faces_of_size, size) arrays — the outward faces by their corner
        nodes, grouped by size (a wedge has one group of 2 triangles and one of 3 quads;
        for surface cells, the edges ordered counter-clockwise)
    corner_frames : (k, dim) — at each corner the ends of its ``dim`` edges, ordered so
        that ``det[x_e1 - x_c, x_e2 - x_c, x_e3 - x_c] > 0`` on a valid (positive) cell
    meshio : meshio cell type name
    vtk_id : VTK cell type id
    vtk_order : (n_nodes,) VTK node k is our node ``vtk_order[k]`` (identity but for wedges)
    abaqus : Abaqus element names read as this type (the first is written)
    degree : polynomial degree of the shape functions
    """

    name: str
    n_nodes: int
    dim: int
    nodes: np.ndarray
    corners: np.ndarray
    edges: np.ndarray
    faces: tuple
    corner_frames: np.ndarray
    meshio: str
    vtk_id: int
    vtk_order: np.ndarray
    abaqus: tuple
    degree: int
    _shape: Callable = field(repr=False)
    _gradient: Callable = field(repr=False)
    _rule: Callable = field(repr=False)

    def _points(self, xi) -> np.ndarray:
        xi = np.atleast_2d(np.asarray(xi, dtype=float))
        if xi.ndim != 2 or xi.shape[1] != self.dim:
            raise ValueError(f"{self.name} reference points have shape {xi.shape}, expected (Q, {self.dim})")
        return xi

    def shape(self, xi) -> np.ndarray:
        """Shape functions ``N_a(xi)``: ``xi (Q, dim)`` -> ``(Q, n_nodes)``."""
        return self._shape(self._points(xi))

    def gradient(self, xi) -> np.ndarray:
        """Shape-function gradients ``dN_a / dxi_k``: ``xi (Q, dim)`` -> ``(Q, n_nodes, dim)``."""
        return self._gradient(self._points(xi))

    def quadrature(self, order: int) -> tuple[np.ndarray, np.ndarray]:
        """Rule exact for polynomials of degree ``order``: points ``(Q, dim)``, weights ``(Q,)``."""
        return self._rule(order)

    @property
    def measure(self) -> float:
        """Volume (area for surface cells) of the reference cell."""
        return float(self.quadrature(1)[1].sum())

    @property
    def hrz_fractions(self) -> np.ndarray:
        """HRZ lumped-mass fractions ``(n_nodes,)`` (sum 1): the diagonal of the consistent
        mass, ``int N_a^2``, scaled to the element mass; exact for affine cells, all positive
        (row-sum lumping gives a ``tet10``'s corners ``-1/20``). ``tet10``: corners ``1/36``,
        mid-edge nodes ``4/27``; ``tet4``: ``1/4``; ``hex8``: ``1/8``."""
        xi, w = self.quadrature(2 * self.degree)
        d = w @ self.shape(xi) ** 2
        return d / d.sum()

    @property
    def faces_flat(self) -> np.ndarray | None:
        """The faces as one array when they all have the same size, else ``None``."""
        return self.faces[0] if len(self.faces) == 1 else None


# ---------------------------------------------------------------- shape functions
_HEX_NODES = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                       [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=float)
_QUAD_NODES = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float)


def _tensor_shape(nodes: np.ndarray) -> tuple[Callable, Callable]:
    """Multilinear Lagrange functions on [-1, 1]^d with corner ``nodes (A, d)``."""
    scale = 0.5 ** nodes.shape[1]

    def shape(xi):
        return scale * np.prod(1.0 + xi[:, None, :] * nodes[None], axis=2)

    def gradient(xi):
        f = 1.0 + xi[:, None, :] * nodes[None]  # (Q, A, d)
        d = nodes.shape[1]
        g = np.empty(f.shape)
        for k in range(d):
            others = [m for m in range(d) if m != k]
            g[..., k] = scale * nodes[None, :, k] * np.prod(f[..., others], axis=2)
        return g

    return shape, gradient


def _simplex_coordinates(xi):
    """Barycentric coordinates ``(Q, dim + 1)`` and their constant gradients ``(dim + 1, dim)``."""
    d = xi.shape[1]
    L = np.column_stack([1.0 - xi.sum(axis=1), xi])
    dL = np.vstack([-np.ones(d), np.eye(d)])
    return L, dL


def _simplex_p1(xi):
    return _simplex_coordinates(xi)[0]


def _simplex_p1_gradient(xi):
    _, dL = _simplex_coordinates(xi)
    return np.broadcast_to(dL, (xi.shape[0],) + dL.shape).copy()


def _tet10(xi):
    L, _ = _simplex_coordinates(xi)
    i, j = TET_EDGES[:, 0], TET_EDGES[:, 1]
    return np.hstack([L * (2.0 * L - 1.0), 4.0 * L[:, i] * L[:, j]])


def _tet10_gradient(xi):
    L, dL = _simplex_coordinates(xi)
    g = np.empty((xi.shape[0], 10, 3))
    g[:, :4, :] = (4.0 * L - 1.0)[:, :, None] * dL[None]
    i, j = TET_EDGES[:, 0], TET_EDGES[:, 1]
    g[:, 4:, :] = 4.0 * (L[:, i, None] * dL[None, j] + L[:, j, None] * dL[None, i])
    return g


def _wedge6(xi):
    L, _ = _simplex_coordinates(xi[:, :2])
    lo, hi = 0.5 * (1.0 - xi[:, 2:3]), 0.5 * (1.0 + xi[:, 2:3])
    return np.hstack([L * lo, L * hi])


def _wedge6_gradient(xi):
    L, dL = _simplex_coordinates(xi[:, :2])  # (Q, 3), (3, 2)
    lo, hi = 0.5 * (1.0 - xi[:, 2]), 0.5 * (1.0 + xi[:, 2])
    g = np.empty((xi.shape[0], 6, 3))
    g[:, :3, :2] = lo[:, None, None] * dL[None]
    g[:, 3:, :2] = hi[:, None, None] * dL[None]
    g[:, :3, 2] = -0.5 * L
    g[:, 3:, 2] = 0.5 * L
    return g


# ----------------------------------------------------------------------- records
def _record(name, nodes, corners, edges, faces, corner_frames, meshio, vtk_id, abaqus, degree, shape, gradient,
            rule, vtk_order=None) -> ReferenceElement:
    nodes = _ro(nodes)
    return ReferenceElement(
        name=name, n_nodes=nodes.shape[0], dim=nodes.shape[1], nodes=nodes,
        corners=_ro(corners, np.int64), edges=_ro(edges, np.int64),
        faces=tuple(_ro(f, np.int64) for f in faces), corner_frames=_ro(corner_frames, np.int64),
        meshio=meshio, vtk_id=vtk_id,
        vtk_order=_ro(np.arange(nodes.shape[0]) if vtk_order is None else vtk_order, np.int64),
        abaqus=tuple(abaqus), degree=degree, _shape=shape, _gradient=gradient, _rule=rule,
    )


_TET_NODES = np.vstack([np.zeros(3), np.eye(3)])
_TET_FACES = ([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]],)
_TET_FRAMES = [[1, 2, 3], [2, 0, 3], [0, 1, 3], [1, 0, 2]]
_TET10_NODES = np.vstack([_TET_NODES, 0.5 * (_TET_NODES[TET_EDGES[:, 0]] + _TET_NODES[TET_EDGES[:, 1]])])
_TRI_NODES = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
_WEDGE_NODES = np.array([[0, 0, -1], [1, 0, -1], [0, 1, -1], [0, 0, 1], [1, 0, 1], [0, 1, 1]], dtype=float)

REFERENCE_ELEMENTS: Mapping[str, ReferenceElement] = MappingProxyType({
    "hex8": _record(
        "hex8", _HEX_NODES, range(8),
        [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]],
        ([[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]],),
        [[1, 3, 4], [2, 0, 5], [3, 1, 6], [0, 2, 7], [7, 5, 0], [4, 6, 1], [5, 7, 2], [6, 4, 3]],
        "hexahedron", 12, ("C3D8", "C3D8R", "C3D8H", "C3D8I", "C3D8IH", "C3D8RH"), 1,
        *_tensor_shape(_HEX_NODES), _q.gauss_hex),
    "wedge6": _record(
        "wedge6", _WEDGE_NODES, range(6),
        [[0, 1], [1, 2], [2, 0], [3, 4], [4, 5], [5, 3], [0, 3], [1, 4], [2, 5]],
        ([[0, 2, 1], [3, 4, 5]], [[0, 1, 4, 3], [1, 2, 5, 4], [2, 0, 3, 5]]),
        [[1, 2, 3], [2, 0, 4], [0, 1, 5], [5, 4, 0], [3, 5, 1], [4, 3, 2]],
        "wedge", 13, ("C3D6",), 1, _wedge6, _wedge6_gradient, _q.wedge_rule, vtk_order=WEDGE_VTK_ORDER),
    "tet4": _record(
        "tet4", _TET_NODES, range(4), TET_EDGES, _TET_FACES, _TET_FRAMES,
        "tetra", 10, ("C3D4", "C3D4H"), 1, _simplex_p1, _simplex_p1_gradient, _q.tet_rule),
    "tet10": _record(
        "tet10", _TET10_NODES, range(4), TET_EDGES, _TET_FACES, _TET_FRAMES,
        "tetra10", 24, ("C3D10", "C3D10H", "C3D10I", "C3D10M", "C3D10MH"), 2, _tet10, _tet10_gradient, _q.tet_rule),
    "tri3": _record(
        "tri3", _TRI_NODES, range(3), [[0, 1], [1, 2], [2, 0]], ([[0, 1], [1, 2], [2, 0]],),
        [[1, 2], [2, 0], [0, 1]], "triangle", 5, ("S3", "S3R", "STRI3", "CPS3", "R3D3"), 1,
        _simplex_p1, _simplex_p1_gradient, _q.triangle_rule),
    "quad4": _record(
        "quad4", _QUAD_NODES, range(4), [[0, 1], [1, 2], [2, 3], [3, 0]], ([[0, 1], [1, 2], [2, 3], [3, 0]],),
        [[1, 3], [2, 0], [3, 1], [0, 2]], "quad", 9, ("S4", "S4R", "CPS4", "CPS4R"), 1,
        *_tensor_shape(_QUAD_NODES), _q.gauss_quad),
})


def reference_element(name: str) -> ReferenceElement:
    """The record of cell type ``name``; a clear KeyError lists the known types."""
    try:
        return REFERENCE_ELEMENTS[name]
    except KeyError:
        raise KeyError(f"unknown cell type {name!r}; expected one of {sorted(REFERENCE_ELEMENTS)}") from None
