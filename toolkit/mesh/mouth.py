"""The mouth slit: cut a tet mesh of a closed-mouth face between the two commissures.

A segmentation of a closed mouth joins the lips. The slit is the surface through the
commissures ``c1``, ``c2`` and the anterior direction ``y`` (the plane through the line of
the commissures, turned to contain ``y``), between the commissures and in front of the
line that joins them (down to ``behind_mm`` behind it). Tetrahedra are split by the side of
that plane their centroid lies on; the faces between an upper and a lower one inside the slit region are the slit. Its
nodes are duplicated (the upper tetrahedra keep the original node, the lower ones take the
copy) except along the slit's front inside the tissue (the commissures and the back of the
slit), where the lips stay joined. The copies start where their originals are: the lips
touch and slide on each other (``lip_sliding``, ``upper_lip_face``, ``lower_lip_face``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.common.errors import ToolkitError
from toolkit.common.fem.reference import REFERENCE_ELEMENTS
from toolkit.common.meshes.topology import boundary_faces, rim_edges, unique_edges

__all__ = ["MouthError", "MouthSlit", "cut_mouth"]

_TET_FACES = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])


class MouthError(ToolkitError, ValueError):
    """Commissure points that do not define a slit in the mesh."""


@dataclass(frozen=True)
class MouthSlit:
    """A mesh with its mouth cut.

    points : (n + d, 3) mm, the ``d`` copies appended
    tets : (t, 4) the lower lip's tetrahedra renumbered to the copies
    upper : (d,) original nodes of the slit (upper lip face)
    lower : (d,) their copies (lower lip face), ``lower[i]`` coincides with ``upper[i]``
    faces : (k, 3) the slit's faces on the upper side (node ids of the cut mesh)
    normal : (3,) unit normal of the slit plane, pointing up
    """

    points: np.ndarray
    tets: np.ndarray
    upper: np.ndarray
    lower: np.ndarray
    faces: np.ndarray
    lower_faces: np.ndarray
    normal: np.ndarray
    width_mm: float


def _frame(c1: np.ndarray, c2: np.ndarray):
    e = c2 - c1
    width = float(np.linalg.norm(e))
    e = e / width
    n = np.cross(e, [0.0, 1.0, 0.0])
    if np.linalg.norm(n) < 0.5:
        raise MouthError(f"the commissures {c1.round(1).tolist()} and {c2.round(1).tolist()} mm lie along the "
                         "anterior axis; expected them side by side (left and right corners of the mouth, x apart)")
    n /= np.linalg.norm(n)
    if n[2] < 0:
        n = -n
    return e, n, width


def cut_mouth(points: np.ndarray, tets: np.ndarray, commissures, behind_mm: float = 15.0) -> MouthSlit:
    """Cut the slit between two commissure points (see the module).

    Parameters
    ----------
    points : (n, 3) mm
    tets : (t, 4) positively oriented
    commissures : two points (2, 3) mm, the corners of the mouth on the skin
    behind_mm : the slit reaches this far behind the line of the commissures (through the
        lips' thickness, which is behind the commissures at the sides of the mouth)

    Raises
    ------
    MouthError if the points are not two distinct points beside each other, or no face of
    the mesh lies on the slit between them
    """
    c = np.asarray(commissures, dtype=float)
    if c.shape != (2, 3) or not np.isfinite(c).all():
        raise MouthError(f"commissures = {c.tolist()}; expected two points [x, y, z] mm")
    if np.linalg.norm(c[1] - c[0]) < 5.0:
        raise MouthError(f"the commissures are {np.linalg.norm(c[1] - c[0]):.1f} mm apart; expected the two corners "
                         "of the mouth, 30-70 mm apart")
    e, n, width = _frame(c[0], c[1])
    centroid = points[tets].mean(axis=1)
    above = (centroid - c[0]) @ n > 0
    # the faces between an upper and a lower tetrahedron
    faces = tets[:, _TET_FACES].reshape(-1, 3)
    owner = np.repeat(np.arange(tets.shape[0]), 4)
    key = np.sort(faces, axis=1)
    order = np.lexsort(key.T[::-1])
    key, faces, owner = key[order], faces[order], owner[order]
    pair = np.flatnonzero(np.all(key[1:] == key[:-1], axis=1))
    a, b = owner[pair], owner[pair + 1]
    between = above[a] != above[b]
    pair, a, b = pair[between], a[between], b[between]
    up_face = np.where(above[a][:, None], faces[pair], faces[pair + 1])  # as the upper tet sees it
    fc = points[up_face].mean(axis=1)
    t = (fc - c[0]) @ e / width
    behind = c[0, 1] + t * (c[1, 1] - c[0, 1]) - fc[:, 1]  # mm behind the commissure line
    inside = (t > 0) & (t < 1) & (behind < behind_mm)
    slit = up_face[inside]
    if not slit.size:
        raise MouthError(f"no face of the mesh lies on the mouth slit between {c[0].round(1).tolist()} and "
                         f"{c[1].round(1).tolist()} mm; expected the commissures on the skin at the corners "
                         "of the mouth (in the mesh's axes and units)")
    # the slit front inside the tissue: slit edges used by one slit face that are not on the tissue surface
    rim = rim_edges(slit)
    outer_edges = unique_edges(boundary_faces("tet4", tets), REFERENCE_ELEMENTS["tri3"].edges)[0]
    on_surface = _rows_in(rim, outer_edges)
    front = np.unique(rim[~on_surface])
    nodes = np.setdiff1d(np.unique(slit), front)
    if not nodes.size:
        raise MouthError("the mouth slit between the commissures is a single row of faces with no node to open; "
                         "expected a finer mesh (smaller size) or commissures farther apart")
    copy = np.full(points.shape[0], -1, dtype=np.int64)
    copy[nodes] = points.shape[0] + np.arange(nodes.size)
    lower_tets = ~above
    new_tets = tets.copy()
    sub = new_tets[lower_tets]
    dup = copy[sub] >= 0
    sub[dup] = copy[sub[dup]]
    new_tets[lower_tets] = sub
    new_points = np.vstack([points, points[nodes]])
    lower_faces = np.where(copy[slit] >= 0, copy[slit], slit)[:, [0, 2, 1]]
    return MouthSlit(new_points, new_tets, nodes, copy[nodes], slit, lower_faces, n, width)


def _rows_in(rows: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Whether each row of ``rows`` (k, 2) is a row of ``table`` (m, 2) (both int)."""
    base = int(max(rows.max(initial=0), table.max(initial=0))) + 1
    return np.isin(rows[:, 0] * base + rows[:, 1], table[:, 0] * base + table[:, 1])
