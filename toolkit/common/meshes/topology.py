"""Mesh topology: element faces, edges, boundary extraction, hex-to-tet splitting.

Local node orderings and faces come from the reference-element records
(:mod:`toolkit.common.fem.reference`): VTK/meshio for ``hex8``/``tet4``/``tet10``
(``hex8`` corners ``0:(0,0,0) 1:(1,0,0) 2:(1,1,0) 3:(0,1,0) 4:(0,0,1) 5:(1,0,1)
6:(1,1,1) 7:(0,1,1)``; ``tet10`` mid-edge nodes 4..9 on edges (0,1) (1,2) (0,2) (0,3)
(1,3) (2,3), also Abaqus C3D10's order) and Abaqus C3D6/meshio for ``wedge6``.
"""

from __future__ import annotations

from types import MappingProxyType

import numpy as np

from toolkit.common.fem.reference import REFERENCE_ELEMENTS, TET_EDGES

__all__ = [
    "FACES",
    "FACE_SETS",
    "TET_EDGES",
    "boundary_faces",
    "boundary_face_blocks",
    "lumped_boundary_area",
    "triangulated_boundary",
    "unique_edges",
    "rim_edges",
    "tet10_from_tet4",
    "tet10_mid_edges",
    "kuhn_tets",
    "orient_tets",
    "wedges_from_hexes",
]

_VOLUME = {name: ref for name, ref in REFERENCE_ELEMENTS.items() if ref.dim == 3}
#: outward faces of each volume type grouped by face size (a wedge has 2 triangles and 3 quads),
#: counter-clockwise seen from outside for positively oriented cells; corner nodes only
FACE_SETS = MappingProxyType({name: ref.faces for name, ref in _VOLUME.items()})
#: the faces of the volume types whose faces all have one size, as one ``(n_faces, size)`` array
FACES = MappingProxyType({name: ref.faces[0] for name, ref in _VOLUME.items() if len(ref.faces) == 1})
_FACE_TYPES = {3: "tri3", 4: "quad4"}


def boundary_faces(ctype: str, cells: np.ndarray) -> np.ndarray:
    """Faces of one cell block that belong to exactly one cell.

    Parameters
    ----------
    ctype : ``hex8``, ``tet4`` or ``tet10`` (faces of one size; for ``wedge6`` and mixed
        meshes use :func:`boundary_face_blocks`)
    cells : (n_cells, nodes_per_cell) int

    Returns
    -------
    (n_faces, 4) or (n_faces, 3) int64, outward oriented (corner nodes only for tet10).
    """
    if ctype not in FACE_SETS:
        raise ValueError(f"boundary faces of cell type {ctype!r} are not defined; expected one of {sorted(FACE_SETS)}")
    if ctype not in FACES:
        raise ValueError(f"{ctype} cells have faces of several sizes; use boundary_face_blocks({{{ctype!r}: cells}})")
    blocks = boundary_face_blocks({ctype: cells})
    size = FACES[ctype].shape[1]
    return blocks.get(_FACE_TYPES[size], np.zeros((0, size), dtype=np.int64))


def boundary_face_blocks(cells) -> dict[str, np.ndarray]:
    """Boundary faces of all volume blocks of a (possibly mixed) mesh, by face type.

    Parameters
    ----------
    cells : mapping cell type -> (n_cells, nodes_per_cell) int (surface blocks are ignored)

    Returns
    -------
    ``{"tri3": (k, 3), "quad4": (m, 4)}`` int64 (types with no face left out), outward
    oriented; a face shared by two cells of different types is interior.
    """
    faces = {3: [], 4: []}
    for ctype, conn in cells.items():
        conn = np.asarray(conn, dtype=np.int64)
        for local in FACE_SETS.get(ctype, ()):
            faces[local.shape[1]].append(conn[:, local].reshape(-1, local.shape[1]))
    out = {}
    for k, name in _FACE_TYPES.items():
        if not faces[k]:
            continue
        f = np.concatenate(faces[k])
        _, inverse, counts = np.unique(np.sort(f, axis=1), axis=0, return_inverse=True, return_counts=True)
        f = f[counts[inverse.ravel()] == 1]
        if f.size:
            out[name] = f
    return out


def triangulated_boundary(cells) -> np.ndarray:
    """Outward boundary triangles ``(k, 3)`` of all volume blocks (quads split in two)."""
    blocks = boundary_face_blocks(cells)
    tris = [blocks["tri3"]] if "tri3" in blocks else []
    if "quad4" in blocks:
        q = blocks["quad4"]
        tris += [q[:, [0, 1, 2]], q[:, [0, 2, 3]]]
    return np.concatenate(tris) if tris else np.zeros((0, 3), dtype=np.int64)


def lumped_boundary_area(points: np.ndarray, cells) -> np.ndarray:
    """Boundary area held by each node ``(n,)`` mm^2 (points in mm): every boundary face of the
    volume blocks ``cells`` gives an equal share of its area to each of its corners (a third of a
    triangle, a quarter of a quadrilateral); interior and mid-edge nodes hold none."""
    out = np.zeros(points.shape[0])
    for kind, faces in boundary_face_blocks(cells).items():
        k = 3 if kind == "tri3" else 4
        x = points[faces[:, :k]]
        area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
        if k == 4:
            area += 0.5 * np.linalg.norm(np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]), axis=1)
        out += np.bincount(faces[:, :k].ravel(), weights=np.repeat(area / k, k), minlength=points.shape[0])
    return out


def unique_edges(cells: np.ndarray, local_edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges of a cell block.

    Returns
    -------
    edges : (n_edges, 2) int64, sorted pairs in lexicographic order
    cell_edges : (n_cells, n_local_edges) int64, index into ``edges``
    """
    pairs = np.sort(cells[:, local_edges], axis=2).reshape(-1, 2)
    edges, inverse = np.unique(pairs, axis=0, return_inverse=True)
    return edges, inverse.reshape(cells.shape[0], local_edges.shape[0])


def rim_edges(triangles) -> np.ndarray:
    """Edges ``(e, 2)`` (sorted node pairs) of a triangle surface that belong to one triangle
    only: the rim of an open surface (empty for a closed one)."""
    t = np.asarray(triangles, dtype=np.int64)
    edges, tri_edges = unique_edges(t, REFERENCE_ELEMENTS["tri3"].edges)
    return edges[np.bincount(tri_edges.ravel(), minlength=edges.shape[0]) == 1]


def tet10_mid_edges(cells10: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mid-edge nodes of tet10 cells ``(t, 10)``, each once ``(k,)`` in increasing order,
    and the two corner nodes of the edge each lies on ``(k,)``, ``(k,)``."""
    cells10 = np.asarray(cells10, dtype=np.int64)
    mid, first = np.unique(cells10[:, 4:].ravel(), return_index=True)
    return mid, cells10[:, TET_EDGES[:, 0]].ravel()[first], cells10[:, TET_EDGES[:, 1]].ravel()[first]


def tet10_from_tet4(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Straight-sided quadratic tetrahedra from linear ones.

    Mid-edge nodes are appended after the corner nodes, numbered by the
    lexicographic order of their sorted corner pairs.

    Parameters
    ----------
    points : (n_points, 3) float, mm
    tets : (n_tets, 4) int

    Returns
    -------
    points10 : (n_points + n_edges, 3) float
    tets10 : (n_tets, 10) int64
    """
    edges, cell_edges = unique_edges(tets, TET_EDGES)
    mid = 0.5 * (points[edges[:, 0]] + points[edges[:, 1]])
    points10 = np.vstack([points, mid])
    tets10 = np.hstack([tets, points.shape[0] + cell_edges]).astype(np.int64)
    return points10, tets10


def orient_tets(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Swap corners 1 and 2 of tetrahedra with negative signed volume."""
    tets = np.array(tets, dtype=np.int64, copy=True)
    x = points[tets[:, :4]]
    vol = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0])
    neg = vol < 0
    tets[neg, 1], tets[neg, 2] = tets[neg, 2], tets[neg, 1].copy()
    return tets


def kuhn_tets(corners: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Split hexahedra into 6 tetrahedra each along the (0,0,0)-(1,1,1) diagonal.

    Neighbouring cells whose local axes agree on the shared face split that face
    along the same diagonal, so a structured grid gives a conforming tet mesh.

    Parameters
    ----------
    corners : (n_cells, 2, 2, 2) int
        Node of each cell at local corner ``[i, j, k]``.
    points : (n_points, 3) float
        Used only to orient every tetrahedron positively.

    Returns
    -------
    (6 * n_cells, 4) int64
    """
    c = corners.reshape(-1, 8)  # index i*4 + j*2 + k
    bit = {0: 4, 1: 2, 2: 1}
    tets = []
    for a, b in ((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)):
        p1 = bit[a]
        p2 = bit[a] + bit[b]
        tets.append(np.stack([c[:, 0], c[:, p1], c[:, p2], c[:, 7]], axis=1))
    return orient_tets(points, np.concatenate(tets, axis=0))


def wedges_from_hexes(corners: np.ndarray, points: np.ndarray | None = None) -> np.ndarray:
    """Split hexahedra into 2 wedges each, prism axis along the third local direction.

    The cut runs through the local corners ``(0,0,*)`` and ``(1,1,*)``: the triangles at
    ``k = 0`` and ``k = 1`` are the ones :func:`kuhn_tets` puts on those faces, so wedges
    stacked on Kuhn tetrahedra (or on each other) conform, and the quad faces are the
    hexahedra's own side faces, so wedges beside hexahedra conform.

    Parameters
    ----------
    corners : (n_cells, 2, 2, 2) int
        Node of each cell at local corner ``[i, j, k]``.
    points : (n_points, 3) float, optional
        When given, wedges with a negative Jacobian (a left-handed local frame) are
        flipped to a positive orientation.

    Returns
    -------
    (2 * n_cells, 6) int64 in the ``wedge6`` (Abaqus C3D6) node order: the first
    wedge of every cell, then the second.
    """
    c = np.asarray(corners, dtype=np.int64).reshape(-1, 2, 2, 2)
    bottoms = ([(0, 0), (1, 0), (1, 1)], [(0, 0), (1, 1), (0, 1)])
    wedges = [np.stack([c[:, i, j, k] for k in (0, 1) for i, j in tri], axis=1) for tri in bottoms]
    wedges = np.concatenate(wedges, axis=0)
    if points is not None:
        x = np.asarray(points, dtype=float)[wedges]
        e1, e2, e3 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
        flip = np.einsum("ij,ij->i", np.cross(e1, e2), e3) < 0
        wedges[flip] = wedges[flip][:, [0, 2, 1, 3, 5, 4]]
    return wedges
