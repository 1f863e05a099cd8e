"""Mesh topology: element faces, edges, boundary extraction, hex-to-tet splitting.

Local node orderings follow VTK/meshio. For ``hex8`` the corners are
``0:(0,0,0) 1:(1,0,0) 2:(1,1,0) 3:(0,1,0) 4:(0,0,1) 5:(1,0,1) 6:(1,1,1) 7:(0,1,1)``;
for ``tet10`` the mid-edge nodes 4..9 sit on edges (0,1) (1,2) (0,2) (0,3) (1,3) (2,3),
which is also Abaqus C3D10's order.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "FACES",
    "TET_EDGES",
    "boundary_faces",
    "boundary_face_blocks",
    "triangulated_boundary",
    "unique_edges",
    "tet10_from_tet4",
    "kuhn_tets",
    "orient_tets",
]

#: outward faces (counter-clockwise seen from outside) of positively oriented cells
FACES = {
    "hex8": np.array(
        [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
    ),
    "tet4": np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]),
}
FACES["tet10"] = FACES["tet4"]
#: outward faces of each volume type grouped by face size (a wedge has both triangles and quads)
FACE_SETS = {"hex8": (FACES["hex8"],), "tet4": (FACES["tet4"],), "tet10": (FACES["tet4"],)}

#: corner pairs of the tetrahedron edges, in the order of the tet10 mid-edge nodes
TET_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])


def boundary_faces(ctype: str, cells: np.ndarray) -> np.ndarray:
    """Faces that belong to exactly one cell.

    Parameters
    ----------
    ctype : ``hex8``, ``tet4`` or ``tet10``
    cells : (n_cells, nodes_per_cell) int

    Returns
    -------
    (n_faces, 4) or (n_faces, 3) int64, outward oriented (corner nodes only for tet10).
    """
    if ctype not in FACES:
        raise ValueError(f"boundary faces of cell type {ctype!r} are not defined; expected one of {sorted(FACES)}")
    local = FACES[ctype]
    faces = cells[:, local].reshape(-1, local.shape[1])
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inverse.ravel()] == 1]


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
        for local in FACE_SETS.get(ctype, ()):
            faces[local.shape[1]].append(conn[:, local].reshape(-1, local.shape[1]))
    out = {}
    for k, name in ((3, "tri3"), (4, "quad4")):
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
