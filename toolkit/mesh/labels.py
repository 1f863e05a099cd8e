"""Node sets of a meshed face from its bone surfaces, by the rules of :mod:`toolkit.mesh.rules`.

Each boundary face of the tissue mesh is classified once, then its nodes take its label:

1. **bone side**: the face lies within ``contact_mm`` of a bone surface, parallel to it within
   ``facing_deg``, and the bone lies on its outer side (or at most ``touch_mm`` behind it):
   ``bone``, and the segment of the nearest such bone. Every test reads the tissue's own
   outward normal and the bone's closest point; the bone's triangle winding, which exported
   segmentations leave inconsistent, decides nothing;
2. **truncation cuts** (``fixed``): among the others, faces turned toward a cut direction and
   within ``margin_mm`` of the mesh's extreme along it;
3. **skin**: the rest (the mouth slit's faces, when cut, are labelled by
   :mod:`toolkit.mesh.mouth` and taken out first).

Bone-side nodes are then split per segment by its :class:`~toolkit.mesh.rules.SegmentRule`:
carried (``maxilla`` for ``lefort``, ``mandible`` for ``distal``; ``fixed`` for a segment
ruled ``fixed``) or sliding (``mucosa_<segment>``, all of them in ``mucosa_sliding``). Sets
are disjoint where the simulation needs them so (``fixed`` first, then carried, sliding and
lip nodes), as :meth:`~toolkit.static.boundary.BoundaryConditions.from_mesh` requires.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from toolkit.common.analysis.surface_distance import barycentric, closest_points
from toolkit.common.meshes.mesh import Mesh
from toolkit.common.meshes.topology import boundary_faces, rim_edges
from toolkit.mesh.rules import SEGMENTS, LabelRules

__all__ = ["FaceLabels", "label_nodes", "CARRIED_SETS"]

#: node set carried by each segment (segments without one cannot use ``attach`` other than
#: ``none`` or ``fixed``: the static workflow has no attachment set for them)
CARRIED_SETS = {"lefort": "maxilla", "distal": "mandible"}
#: mm, distances to two bones closer than this are a tie
_TIE_MM = 1e-6


@dataclass(frozen=True)
class FaceLabels:
    """Node sets (name -> sorted int64 ids) and what decided them."""

    node_sets: dict[str, np.ndarray]
    face_label: np.ndarray  # (f,) str per boundary face: 'bone:<segment>', 'fixed', 'skin', 'slit'
    offsets: dict[str, np.ndarray]  # segment -> distances (mm) of its bone-side nodes to its bone


def _face_normals(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = points[faces]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    return x.mean(axis=1), n / np.linalg.norm(n, axis=1, keepdims=True)


def _faces_bone(centre: np.ndarray, normal: np.ndarray, cp, rules: LabelRules) -> np.ndarray:
    """Whether tissue boundary faces (centres and outward unit normals ``(f, 3)``) lie on a bone
    whose closest points are ``cp``: within ``contact_mm`` of it, parallel to it within
    ``facing_deg`` (either winding: exported bone surfaces mix both), and with the bone on their
    outer side, or behind it by at most ``touch_mm`` (a face on the bone, or sunk into it by
    the segmentation's staircase). The skin, with the bone behind it, and the truncation cuts,
    across the bone's surface, are not."""
    parallel = np.abs(np.einsum("ij,ij->i", normal, cp.normal)) >= np.cos(np.radians(rules.facing_deg))
    ahead = np.einsum("ij,ij->i", cp.point - centre, normal) >= -rules.touch_mm
    return parallel & ahead & (cp.distance <= rules.contact_mm)


def label_nodes(points: np.ndarray, tets: np.ndarray, bones: Mapping[str, Mesh], rules: LabelRules,
                exclude_faces: np.ndarray | None = None) -> FaceLabels:
    """Boundary node sets of a tet mesh of the tissue.

    Parameters
    ----------
    points : (n, 3) mm
    tets : (t, 4) positively oriented corners
    bones : segment name -> ``tri3`` surface (mm), in any winding, open or closed, in one
        piece or several
    rules : the labelling rules
    exclude_faces : (k, 3) boundary faces already labelled (the mouth slit); their nodes
        are kept out of every set made here
    """
    faces = boundary_faces("tet4", tets)
    centre, normal = _face_normals(points, faces)
    f = faces.shape[0]
    label = np.full(f, "skin", dtype=object)
    slit = np.zeros(f, dtype=bool)
    if exclude_faces is not None and len(exclude_faces):
        key = {tuple(k) for k in np.sort(exclude_faces, axis=1).tolist()}
        slit = np.array([tuple(k) in key for k in np.sort(faces, axis=1).tolist()], dtype=bool)
        label[slit] = "slit"
    # 1. bone side: the nearest bone within contact that the face lies along and does not turn
    #    its back on (measured from the tissue: the bone's winding decides nothing)
    names = [s for s in SEGMENTS if s in bones]
    best = np.full(f, np.inf)
    seg_of = np.full(f, -1)
    for k, name in enumerate(names):
        cp = closest_points(centre, bones[name].points, bones[name].cells["tri3"])
        ok = _faces_bone(centre, normal, cp, rules) & (cp.distance < best) & ~slit
        best[ok], seg_of[ok] = cp.distance[ok], k
    on_bone = seg_of >= 0
    label[on_bone] = np.array([f"bone:{names[k]}" for k in seg_of[on_bone]], dtype=object)
    # 2. truncation cuts, among the faces not on a bone
    cut = np.zeros(f, dtype=bool)
    cos_cut = np.cos(np.radians(rules.cuts.max_angle_deg))
    for d in rules.cuts.directions:
        d = np.asarray(d, dtype=float) / np.linalg.norm(d)
        extreme = float((points @ d).max())
        cut |= (normal @ d >= cos_cut) & (centre @ d >= extreme - rules.cuts.margin_mm)
    # measured to the tissue lying on a moving bone (as the Le Fort I border is): where the bone
    # itself lies, a few mm off the tissue, does not move the held cut
    moving = [k for k, s in enumerate(names) if _moves(s, rules)]
    on_moving = faces[np.isin(seg_of, moving)]
    idx = np.flatnonzero(cut)
    if on_moving.size and idx.size:
        near = cKDTree(points[np.unique(on_moving)]).query(centre[idx])[0]
        cut[idx[near < rules.cuts.clear_of_moving_mm]] = False
    cut &= ~on_bone & ~slit
    label[cut] = "fixed"

    n = points.shape[0]

    def nodes_of(mask):
        return np.unique(faces[mask])

    slit_nodes = nodes_of(slit)
    taken = np.zeros(n, dtype=bool)
    taken[slit_nodes] = True
    sets: dict[str, np.ndarray] = {}
    fixed = np.setdiff1d(nodes_of(cut), slit_nodes)
    bone_nodes = np.setdiff1d(nodes_of(on_bone), slit_nodes)
    # a bone-side node takes the segment of the bone it lies over (its closest point inside the
    # bone, not on its rim), the nearest of those; a node over none (in a saw cut) the nearest bone
    node_dist = np.full((n, len(names)), np.inf)
    over = np.zeros((n, len(names)), dtype=bool)
    for k, name in enumerate(names):
        cp = closest_points(points[bone_nodes], bones[name].points, bones[name].cells["tri3"])
        node_dist[bone_nodes, k] = cp.distance
        over[bone_nodes, k] = ~_on_rim(bones[name], cp)
    node_dist = np.where(over | ~over.any(axis=1, keepdims=True), node_dist, np.inf)
    # ties (a node on the osteotomy line, on two bones' rims) go to the first segment in SEGMENTS
    # order, whatever the triangulation's rounding
    node_seg = np.argmax(node_dist <= node_dist.min(axis=1, keepdims=True) + _TIE_MM, axis=1)
    fixed_mask = np.zeros(n, dtype=bool)
    fixed_mask[fixed] = True
    offsets = {}
    for k, name in enumerate(names):
        mine = bone_nodes[node_seg[bone_nodes] == k]
        mine = mine[~fixed_mask[mine]]
        offsets[name] = node_dist[mine, k]
        rule = rules.segments[name]
        carried = _carried(points, mine, bones[name], rule)
        others = [o for o in names if o != name and _moves(o, rules)]
        if rule.border_mm > 0 and others and carried.any():
            # measured to the tissue the other segments hold: their border is the osteotomy line
            # as the tissue sees it, wherever a saw cut or an export left the bones' rims
            theirs = bone_nodes[np.isin(node_seg[bone_nodes], [names.index(o) for o in others])]
            near = cKDTree(points[theirs]).query(points[mine])[0] if theirs.size else np.full(mine.size, np.inf)
            carried &= near >= rule.border_mm
        if rule.attach == "fixed":
            fixed_mask[mine[carried]] = True
        elif carried.any():
            sets[CARRIED_SETS[name]] = mine[carried]
        sets[f"mucosa_{name}"] = mine[~carried]
    sets["fixed"] = np.flatnonzero(fixed_mask)
    sliding = [sets[f"mucosa_{s}"] for s in names if f"mucosa_{s}" in sets]
    sets["mucosa_sliding"] = np.unique(np.concatenate(sliding)) if sliding else np.zeros(0, np.int64)
    sets["bone"] = bone_nodes
    skin = nodes_of(label == "skin")
    sets["skin"] = skin[~np.isin(skin, bone_nodes) & ~taken[skin]]
    return FaceLabels({k: np.asarray(v, dtype=np.int64) for k, v in sets.items()}, label, offsets)


def _on_rim(bone: Mesh, cp, tol: float = 1e-6) -> np.ndarray:
    """Whether closest points ``cp`` on ``bone`` lie on its rim (an edge of one triangle only,
    within ``tol`` of the triangle's size in barycentric terms): points beyond the bone's edge."""

    tris = bone.cells["tri3"][cp.triangle]
    rim = rim_edges(bone.cells["tri3"])
    if not rim.size:
        return np.zeros(tris.shape[0], dtype=bool)
    m = int(bone.points.shape[0])
    keys = np.sort(rim, axis=1) @ np.array([m, 1])
    bary = barycentric(cp.point, bone.points[tris])
    out = np.zeros(tris.shape[0], dtype=bool)
    for corner, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):  # the edge opposite each corner
        edge = np.sort(tris[:, [i, j]], axis=1) @ np.array([m, 1])
        out |= (bary[:, corner] <= tol) & np.isin(edge, keys)
    return out


def arch_centre(bone: Mesh) -> np.ndarray:
    """Centre ``(2,)`` mm (x, y) of the circle fitted, seen from above, to a bone surface: for
    a jaw segment, the centre of its dental arch (least squares on ``x^2 + y^2 = 2 a x + 2 b y + c``
    at the triangles' centroids, weighted by their areas, so that the fit is the surface's and
    not its triangulation's)."""
    x3 = bone.points[bone.cells["tri3"]]
    c = x3.mean(axis=1)
    w = np.sqrt(0.5 * np.linalg.norm(np.cross(x3[:, 1] - x3[:, 0], x3[:, 2] - x3[:, 0]), axis=1))
    x, y = c[:, 0], c[:, 1]
    a = np.column_stack([2 * x, 2 * y, np.ones_like(x)]) * w[:, None]
    cx, cy, _ = np.linalg.lstsq(a, (x**2 + y**2) * w, rcond=None)[0]
    return np.array([cx, cy])


def _moves(segment: str, rules: LabelRules) -> bool:
    """Whether a segment can move in a plan (the skull and segments ruled ``fixed`` do not)."""
    return segment != "skull" and rules.segments[segment].attach != "fixed"


def _carried(points: np.ndarray, nodes: np.ndarray, bone: Mesh, rule) -> np.ndarray:
    """Which of a segment's bone-side ``nodes`` it carries (bool per node)."""
    if rule.attach in ("all", "fixed"):
        return np.ones(nodes.size, dtype=bool)
    if rule.attach == "none" or not nodes.size:
        return np.zeros(nodes.size, dtype=bool)
    x = points[nodes]
    if rule.attach == "anterior":
        c = arch_centre(bone)
        angle = np.degrees(np.arctan2(np.abs(x[:, 0] - c[0]), x[:, 1] - c[1]))
        return angle <= rule.anterior_deg
    z = x[:, 2]
    return z <= z.min() + rule.inferior_fraction * (z.max() - z.min())
