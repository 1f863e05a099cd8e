"""Triangle surfaces as segmentation and planning systems export them: :func:`read_surface`
reads one (STL, OBJ, PLY, VTK, VTU or OFF, in any length unit; quads and polygons triangulated,
the duplicated vertices of STL files merged), :func:`consistent_orientation` winds a surface's
triangles alike piece by piece, and :func:`orient_surface` turns it so that its normals point
towards given points (into the soft tissue, as the phantoms' bones are): segmentation tools
write either orientation, and STL files often mix both.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.sparse as sp

from toolkit.common.meshes.io import UNIT_SCALES, check_units
from toolkit.common.meshes.mesh import Mesh, MeshError

__all__ = ["read_surface", "orient_surface", "consistent_orientation", "SURFACE_FORMATS"]

#: suffixes :func:`read_surface` reads (through meshio)
SURFACE_FORMATS = (".stl", ".obj", ".ply", ".vtk", ".vtu", ".off")


def _triangles(m) -> np.ndarray:
    """All triangles of a meshio mesh ``(t, 3)``: quads and polygons split as fans."""
    tris = []
    for block in m.cells:
        c = np.asarray(block.data, dtype=np.int64)
        if block.type == "triangle":
            tris.append(c)
        elif block.type in ("quad", "polygon") or block.type.startswith("polygon"):
            tris += [c[:, [0, k, k + 1]] for k in range(1, c.shape[1] - 1)]
    if not tris:
        types = sorted({b.type for b in m.cells})
        raise MeshError(f"the file holds no surface cells (cell types {types}); expected triangles, quads or polygons")
    return np.concatenate(tris)


def read_surface(path, units: str = "mm", merge_tolerance: float = 1e-6) -> Mesh:
    """Read a bone surface as a ``tri3`` :class:`~toolkit.common.meshes.mesh.Mesh` in mm.

    Parameters
    ----------
    path : file with one of :data:`SURFACE_FORMATS`
    units : length unit of the file (``mm``, ``cm``, ``m``, ``um``), converted to mm
    merge_tolerance : vertices closer than this fraction of the surface's extent are one
        vertex (STL stores every triangle's corners separately)

    Returns
    -------
    Mesh with one ``tri3`` block, points ``(n, 3)`` mm; degenerate triangles dropped.
    Not oriented: see :func:`orient_surface`.
    """

    path = Path(path)
    if path.suffix.lower() not in SURFACE_FORMATS:
        raise ValueError(f"unknown surface format {path.suffix!r} of {str(path)!r}; expected one of {SURFACE_FORMATS}")
    if units not in UNIT_SCALES:
        raise ValueError(f"units = {units!r}; expected one of {sorted(UNIT_SCALES)}")
    if not path.exists():
        raise FileNotFoundError(f"bone surface {str(path)!r} does not exist")
    if path.is_dir() or path.stat().st_size == 0:
        raise MeshError(f"bone surface {path.name} is {'a folder' if path.is_dir() else 'empty (0 bytes)'}; "
                        f"expected a triangulated surface ({path.suffix.lower()[1:].upper()})")
    # meshio's own ``read`` prints and exits the process on a file it cannot parse; its
    # per-format readers raise
    from meshio._helpers import reader_map

    fmt = path.suffix.lower()[1:]
    try:
        with np.errstate(over="ignore"):  # meshio's binary-STL size probe overflows on ASCII files
            m = reader_map[fmt](str(path))
        pts = np.asarray(m.points, dtype=float).reshape(len(m.points), -1)[:, :3] * UNIT_SCALES[units]
    except (Exception, SystemExit) as exc:
        raise MeshError(f"bone surface {path.name} could not be read as {fmt.upper()} "
                        f"({type(exc).__name__}: {exc}); expected a triangulated surface in mm") from None
    if len(pts) == 0:
        raise MeshError(f"bone surface {path.name} holds no points; expected a triangulated surface")
    tris = _triangles(m)
    # merge coincident vertices on a grid of the tolerance
    tol = merge_tolerance * max(float(np.ptp(pts, axis=0).max()), 1e-12)
    _, first, inverse = np.unique(np.round(pts / tol).astype(np.int64), axis=0, return_index=True,
                                  return_inverse=True)
    tris = inverse.ravel()[tris]
    keep = (tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])
    used, tris = np.unique(tris[keep], return_inverse=True)
    surface = Mesh(pts[first][used], {"tri3": tris.reshape(-1, 3)})
    check_units(surface, f"bone surface {path.name}")
    return surface


def _edge_relations(tris: np.ndarray):
    """Pairs of triangles sharing an edge, and whether they traverse it the same way."""
    t = tris.shape[0]
    directed = np.stack([tris, np.roll(tris, -1, axis=1)], axis=2).reshape(-1, 2)  # (3t, 2)
    owner = np.repeat(np.arange(t), 3)
    key = np.sort(directed, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, directed, owner = key[order], directed[order], owner[order]
    same_edge = np.all(key[1:] == key[:-1], axis=1)
    i = np.flatnonzero(same_edge)
    a, b = owner[i], owner[i + 1]
    same_direction = directed[i, 0] == directed[i + 1, 0]
    return a, b, same_direction


def consistent_orientation(triangles, name: str = "surface") -> tuple[np.ndarray, np.ndarray]:
    """Triangles ``(t, 3)`` oriented consistently within each connected piece, and each one's piece id.

    Orientation is propagated across shared edges (two neighbours must traverse their common
    edge in opposite directions) with a connected-components pass on the graph of triangle
    orientations; each piece keeps the orientation of its lowest-numbered triangle. Raises
    :class:`MeshError` naming ``name`` if a piece is not orientable (a Moebius strip).
    """
    from scipy.sparse.csgraph import connected_components

    tris = np.array(triangles, dtype=np.int64)
    t = tris.shape[0]
    a, b, same = _edge_relations(tris)
    # node i: triangle i as it is; node t + i: triangle i flipped
    rows = np.concatenate([a, a + t])
    cols = np.concatenate([np.where(same, b + t, b), np.where(same, b, b + t)])
    graph = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(2 * t, 2 * t))
    _, label = connected_components(graph, directed=False)
    if np.any(label[:t] == label[t:]):
        bad = np.flatnonzero(label[:t] == label[t:])
        raise MeshError(f"{name} is not orientable ({bad.size} triangles, first {bad[:5].tolist()}); "
                        "expected a surface with two sides")
    piece = np.minimum(label[:t], label[t:])
    flip = label[:t] != piece
    tris[flip] = tris[flip][:, [0, 2, 1]]
    return tris, piece


def orient_surface(surface: Mesh, toward: np.ndarray) -> Mesh:
    """The surface with every connected piece consistently oriented, normals towards ``toward``.

    Each piece is oriented by :func:`consistent_orientation`, then flipped so that its
    area-weighted normals point towards the nearest of the ``toward`` points (e.g. the face mesh's element
    centroids: the soft tissue; points on the surface itself decide nothing).

    Parameters
    ----------
    surface : Mesh with a ``tri3`` block, mm
    toward : (k, 3) float, mm

    Raises
    ------
    MeshError if a piece is not orientable (a Moebius strip)
    """
    from scipy.spatial import cKDTree

    tris, piece_of = consistent_orientation(surface.cells["tri3"], "bone surface")
    x = surface.points[tris]
    normal = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])  # area-weighted
    centroid = x.mean(axis=1)
    toward = np.asarray(toward, dtype=float).reshape(-1, 3)
    _, nearest = cKDTree(toward).query(centroid)
    score = np.einsum("ij,ij->i", normal, toward[nearest] - centroid)
    pieces, piece_index = np.unique(piece_of, return_inverse=True)
    wrong = np.bincount(piece_index, weights=score, minlength=pieces.size) < 0
    flip = wrong[piece_index]
    tris[flip] = tris[flip][:, [0, 2, 1]]
    return Mesh(surface.points, {"tri3": tris})
