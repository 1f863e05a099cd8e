"""The lip muscle's fibre direction on a mesh that does not carry one.

The phantom's orbicularis oris fibres run superior-inferior along the face's surface
(``fibre_direction``, built with the grid). A meshed or hand-made face gets the same rule stated
without a grid: each element's fibre is the superior axis (+z) projected onto the tangent plane of
the nearest skin face. Over the coarse phantom's lip muscle this rule stays close to the
phantom's own fibres (``tests/common/test_fibres.py`` bounds the angle between them, at the
median and at worst).
"""

from __future__ import annotations

import numpy as np

from toolkit.common.meshes.mesh import Mesh
from toolkit.common.meshes.topology import triangulated_boundary

__all__ = ["superior_fibres", "with_lip_fibres"]

_SUPERIOR = np.array([0.0, 0.0, 1.0])


def superior_fibres(mesh: Mesh, skin: np.ndarray) -> np.ndarray:
    """Unit fibre directions ``(n_cells, 3)``: +z projected onto the tangent plane of the skin
    face nearest each cell's centroid (cells of every block, in global order).

    skin : node ids of the skin; its boundary faces are those with every corner in it.
    Where the skin is horizontal (the projection vanishes) the fibre is +z. Without a skin
    face every fibre is +z.
    """
    from scipy.spatial import cKDTree


    centroids = np.concatenate([mesh.points[b.cells].mean(axis=1) for b in mesh.blocks])
    member = np.zeros(mesh.n_points, dtype=bool)
    member[skin] = True
    faces = triangulated_boundary(mesh.cells)
    faces = faces[member[faces].all(axis=1)]
    fibre = np.tile(_SUPERIOR, (centroids.shape[0], 1))
    if faces.size == 0:
        return fibre
    x = mesh.points[faces]
    normal = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    n = normal[cKDTree(x.mean(axis=1)).query(centroids)[1]]
    tangent = _SUPERIOR - (n @ _SUPERIOR)[:, None] * n
    length = np.linalg.norm(tangent, axis=1)
    ok = length > 1e-6
    fibre[ok] = tangent[ok] / length[ok, None]
    return fibre


def with_lip_fibres(mesh: Mesh) -> Mesh:
    """``mesh`` with the cell field ``fibre_direction`` by :func:`superior_fibres` when it has an
    element set ``lip_muscle``, a node set ``skin`` and no such field; otherwise ``mesh`` itself."""
    if "lip_muscle" not in mesh.element_sets or "fibre_direction" in mesh.cell_data or "skin" not in mesh.node_sets:
        return mesh
    return mesh.with_cell_data(fibre_direction=superior_fibres(mesh, mesh.node_sets["skin"]))
