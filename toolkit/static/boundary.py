"""Boundary types of the face nodes (the PointNet++ and lip-sliding papers) and which bony segment drives them.

Types: ``free=0, moving=1, fixed=2, mucosa_sliding=3, lip_sliding=4``. Moving nodes are
attached to a bony segment and follow its rigid motion; mucosa-sliding nodes slide on
the surface of their segment; lip-sliding nodes are the two faces of the mouth slit.

Types come from the mesh's node sets (:meth:`BoundaryConditions.from_mesh`), or are
transferred by a k-nearest-neighbour vote from labelled points — e.g. a full-resolution
mesh's types onto a down-sampled one, as the PointNet++ paper did (:func:`knn_labels`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from toolkit.common.analysis.surface_distance import closest_points
from toolkit.common.errors import ToolkitError
from toolkit.common.meshes.mesh import VOLUME_TYPES, Mesh
from toolkit.common.meshes.topology import tet10_mid_edges, triangulated_boundary
from toolkit.common.phantoms.phantom import BoneSegment
from toolkit.static.plan import SEGMENTS

__all__ = ["NodeType", "BoundaryConditions", "knn_labels", "BoundaryError", "segments_from_mesh",
           "ATTACHMENT_SETS", "tissue_distance", "tissue_graph", "DEFAULT_RELEASE_WIDTH"]

#: mm, default width of the bands released around the borders between differently driven
#: regions (see :meth:`BoundaryConditions.with_release_bands`)
DEFAULT_RELEASE_WIDTH = 10.0

#: node set rigidly attached to each bony segment in the phantoms (and expected in real meshes)
ATTACHMENT_SETS = {"lefort": "maxilla", "distal": "mandible", "proximal_left": None, "proximal_right": None,
                   "skull": None}


class NodeType(IntEnum):
    FREE = 0
    MOVING = 1
    FIXED = 2
    MUCOSA_SLIDING = 3
    LIP_SLIDING = 4


def _element_side(mesh: Mesh) -> np.ndarray:
    """Mean centroid of the elements around each node, ``(n, 3)`` mm."""
    acc = np.zeros((mesh.n_points, 3))
    count = np.zeros(mesh.n_points)
    for block in mesh.volume_blocks:
        cells = block.cells
        centroids = mesh.points[cells].mean(axis=1)
        np.add.at(acc, cells.ravel(), np.repeat(centroids, cells.shape[1], axis=0))
        count += np.bincount(cells.ravel(), minlength=mesh.n_points)
    count = count[:, None]
    return np.divide(acc, count, out=mesh.points.copy(), where=count > 0)


def _node_pairs(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Every pair of nodes that share a volume element, once: ``(r, c)`` with ``r < c``, sorted."""
    rows, cols = [], []
    for ctype, conn in mesh.cells.items():
        if ctype not in VOLUME_TYPES:
            continue
        a, b = np.triu_indices(conn.shape[1], k=1)
        rows.append(conn[:, a].ravel())
        cols.append(conn[:, b].ravel())
    r, c = np.concatenate(rows), np.concatenate(cols)
    # CSR construction sums the duplicates in compiled code: 4x faster than np.unique on the keys
    g = sp.csr_matrix((np.ones(r.size, dtype=np.int32), (np.minimum(r, c), np.maximum(r, c))),
                      shape=(mesh.n_points,) * 2)
    g.sum_duplicates()
    return np.repeat(np.arange(mesh.n_points), np.diff(g.indptr)), g.indices.astype(np.int64)


def tissue_graph(mesh: Mesh) -> sp.csr_matrix:
    """The node graph :func:`tissue_distance` walks: ``(n, n)`` CSR, upper triangle, each pair of
    nodes that share a volume element weighted by their distance, mm. Build it once to measure
    from several sources."""
    r, c = _node_pairs(mesh)
    w = np.linalg.norm(mesh.points[r] - mesh.points[c], axis=1)
    return sp.csr_matrix((w, (r, c)), shape=(mesh.n_points,) * 2)


def tissue_distance(mesh: Mesh, sources: np.ndarray, limit: float = np.inf,
                    graph: sp.csr_matrix | None = None) -> np.ndarray:
    """Shortest distance through the tissue from any of ``sources`` to every node, mm.

    Paths run along straight segments between nodes of a common volume element (so
    across element diagonals too, a close upper bound of the straight-line distance inside
    the tissue) and never jump gaps that no element bridges, such as the mouth slit.

    Parameters
    ----------
    mesh : volume mesh (any volume cell types), mm
    sources : (k,) int node indices
    limit : mm; nodes farther than this get ``inf`` (and cost nothing to explore)
    graph : :func:`tissue_graph` of ``mesh``, when already built

    Returns
    -------
    (n_points,) float, mm
    """
    from scipy.sparse.csgraph import dijkstra

    sources = np.unique(np.asarray(sources, dtype=np.int64))
    if not sources.size:
        return np.full(mesh.n_points, np.inf)
    graph = tissue_graph(mesh) if graph is None else graph
    return dijkstra(graph, directed=False, indices=sources, min_only=True, limit=limit)


class BoundaryError(ToolkitError, ValueError):
    """Boundary conditions are inconsistent or leave the problem under-constrained."""


def knn_labels(points: np.ndarray, labelled_points: np.ndarray, labels: np.ndarray, k: int = 5,
               max_distance: float = np.inf, default: int = 0) -> np.ndarray:
    """Majority vote of the ``k`` nearest labelled points (the PointNet++ paper's k-NN assignment).

    Parameters
    ----------
    points : (n, 3) mm — nodes to label
    labelled_points : (m, 3) mm; labels : (m,) int
    k : voters; ties go to the smallest label
    max_distance : mm; nodes farther than this from every labelled point get ``default``

    Returns
    -------
    (n,) int64
    """
    labels = np.asarray(labels, dtype=np.int64)
    k = int(min(k, len(labels)))
    d, idx = cKDTree(labelled_points).query(points, k=k)
    d, idx = d.reshape(len(points), k), idx.reshape(len(points), k)
    votes = labels[idx]
    votes = np.where(d <= max_distance, votes, -1)
    n_labels = labels.max() + 1
    counts = np.stack([(votes == c).sum(axis=1) for c in range(n_labels)], axis=1)
    out = np.argmax(counts, axis=1)
    out[counts.max(axis=1) == 0] = default
    return out


@dataclass(frozen=True, eq=False)
class BoundaryConditions:
    """Node types and segment ownership of a face mesh.

    Attributes
    ----------
    types : (n,) int8 — :class:`NodeType` per node
    segment : (n,) int8 — index into ``segment_names`` for moving and mucosa nodes, else -1
    segment_names : tuple of str
    upper_lip, lower_lip : (k,) int64 — lip-sliding nodes on the upper and lower slit faces
    released : (r,) int64 — nodes freed by :meth:`with_release_bands`, :meth:`with_freed` or
        :meth:`with_mid_edges_of_corners` (empty otherwise)
    """

    types: np.ndarray
    segment: np.ndarray
    segment_names: tuple[str, ...]
    upper_lip: np.ndarray
    lower_lip: np.ndarray
    released: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __post_init__(self):
        types = np.asarray(self.types, dtype=np.int8)
        if types.min(initial=0) < 0 or types.max(initial=0) > 4:
            raise BoundaryError(f"node types must be 0..4 ({[t.name for t in NodeType]}), got {np.unique(types)}")
        object.__setattr__(self, "types", types)
        object.__setattr__(self, "segment", np.asarray(self.segment, dtype=np.int8))
        object.__setattr__(self, "released", np.asarray(self.released, dtype=np.int64).reshape(-1))
        needs = np.isin(types, (NodeType.MOVING, NodeType.MUCOSA_SLIDING)) & (self.segment < 0)
        if needs.any():
            raise BoundaryError(f"{needs.sum()} moving/mucosa nodes have no bony segment (first: "
                                f"{np.flatnonzero(needs)[:5].tolist()})")
        constrained = np.isin(types, (NodeType.MOVING, NodeType.FIXED)).sum()
        if constrained < 3:
            raise BoundaryError(f"only {constrained} fixed/moving nodes: the face would float freely (rigid-body "
                                f"modes); expected at least 3 non-collinear fixed or moving nodes")

    @property
    def n_nodes(self) -> int:
        return self.types.size

    def nodes(self, kind: NodeType) -> np.ndarray:
        return np.flatnonzero(self.types == kind)

    def segment_nodes(self, kind: NodeType, name: str) -> np.ndarray:
        k = self.segment_names.index(name)
        return np.flatnonzero((self.types == kind) & (self.segment == k))

    def one_hot(self) -> np.ndarray:
        """The PointNet++ paper's explicit boundary encoding ``(n, 3)``: free, moving, fixed (sliding count as free)."""
        out = np.zeros((self.n_nodes, 3))
        out[np.arange(self.n_nodes), 0] = 1.0
        for col, kind in ((1, NodeType.MOVING), (2, NodeType.FIXED)):
            ids = self.nodes(kind)
            out[ids] = 0.0
            out[ids, col] = 1.0
        return out

    def with_sliding(self, sliding: str) -> BoundaryConditions:
        """Copy for a sliding model: ``"mucosa+lip"`` (the lip-sliding paper), ``"mucosa"`` (lips free)
        or ``"none"`` (mucosa nodes attached to their segment, lips free: the lip-sliding paper's method 1)."""
        if sliding not in ("none", "mucosa", "mucosa+lip"):
            raise ValueError(f"sliding must be 'none', 'mucosa' or 'mucosa+lip', got {sliding!r}")
        types = self.types.copy()
        if sliding == "none":
            types[types == NodeType.MUCOSA_SLIDING] = NodeType.MOVING
        if sliding != "mucosa+lip":
            types[types == NodeType.LIP_SLIDING] = NodeType.FREE
        lips = sliding == "mucosa+lip"
        empty = np.zeros(0, np.int64)
        return BoundaryConditions(types, self.segment, self.segment_names,
                                  self.upper_lip if lips else empty, self.lower_lip if lips else empty,
                                  self.released)

    def drivers(self) -> np.ndarray:
        """What moves each node, ``(n,)`` int: -1 nothing (free, lip), 0 fixed (the skull),
        ``1 + s`` bony segment ``s`` (attached or sliding on it)."""

        d = np.full(self.n_nodes, -1, dtype=np.int64)
        d[self.types == NodeType.FIXED] = 0
        on_bone = np.isin(self.types, (NodeType.MOVING, NodeType.MUCOSA_SLIDING))
        d[on_bone] = 1 + self.segment[on_bone]
        # a segment no plan moves (the skull) is as immobile as the fixed nodes
        immobile = [1 + k for k, name in enumerate(self.segment_names) if name not in SEGMENTS]
        d[np.isin(d, immobile)] = 0
        return d

    def with_release_bands(self, mesh: Mesh, width: float = DEFAULT_RELEASE_WIDTH,
                           candidates: np.ndarray | None = None) -> BoundaryConditions:
        """Copy in which the tissue along every border between differently driven regions is
        bound to neither side.

        Where two bony segments, or a segment and the fixed skull, drive neighbouring nodes
        (along an osteotomy line, at the occlusal level between the jaws, where the ramus
        mucosa meets the fixed posterior border), the boundary displacement jumps. Surgically
        the periosteum there is stripped (degloving) and the cheek mucosa between the jaws
        belongs to neither, so a node is released (made free) when a node with another
        driver lies within ``width / 2`` of it through the tissue (:func:`tissue_distance`):
        a band about ``width`` wide, whatever the mesh size, centred on each border. Without
        it the jump sits across one element and inverts it as the mesh is refined. Where the
        mesh is coarser than the band (no node that close), the border still gets one
        element: of two neighbours with different drivers, the one of the weaker driver is
        freed (the immobile skull first, then the proximal segments, the distal mandible,
        and the Le Fort I segment last), so a jump never sits across a single element.

        Parameters
        ----------
        mesh : the face mesh these conditions belong to, mm
        width : mm, band width (0 releases nothing)
        candidates : (k,) int — nodes that may be released; default the ``bone`` node set
            when the mesh has one (the bone-side surface), else every constrained node

        Returns
        -------
        BoundaryConditions with the released nodes free and listed in ``released``
        """
        width = float(width)
        if not np.isfinite(width) or width < 0:
            raise ValueError(f"release width = {width!r} mm; expected a finite number >= 0")
        if mesh.n_points != self.n_nodes:
            raise ValueError(f"mesh has {mesh.n_points} nodes but the boundary conditions {self.n_nodes}")
        if width == 0:
            return self
        drivers = self.drivers()
        allowed = np.zeros(self.n_nodes, dtype=bool)
        if candidates is None:
            candidates = mesh.node_sets["bone"] if "bone" in mesh.node_sets else np.flatnonzero(drivers >= 0)
        allowed[np.asarray(candidates, dtype=np.int64)] = True
        release = np.zeros(self.n_nodes, dtype=bool)
        graph = tissue_graph(mesh)
        for d in np.unique(drivers[drivers >= 0]):
            near = tissue_distance(mesh, np.flatnonzero(drivers == d), limit=0.5 * width, graph=graph) < 0.5 * width
            release |= near & (drivers >= 0) & (drivers != d) & allowed
        # neighbours still driven differently (a mesh coarser than the band): free the weaker one
        r = np.repeat(np.arange(self.n_nodes), np.diff(graph.indptr))
        c = graph.indices
        dr, dc = np.where(release, -1, drivers)[r], np.where(release, -1, drivers)[c]
        clash = (dr >= 0) & (dc >= 0) & (dr != dc)
        if clash.any():
            rank = self._driver_strength()
            r, c, dr, dc = r[clash], c[clash], dr[clash], dc[clash]
            weaker = np.where(rank[dr] < rank[dc], r, c)
            stronger = np.where(rank[dr] < rank[dc], c, r)
            weaker = np.where(allowed[weaker], weaker, stronger)
            release[weaker[allowed[weaker]]] = True
        if not release.any():
            return self
        types = self.types.copy()
        segment = self.segment.copy()
        types[release] = NodeType.FREE
        segment[release] = -1
        ids = np.union1d(self.released, np.flatnonzero(release))
        return BoundaryConditions(types, segment, self.segment_names, self.upper_lip, self.lower_lip, ids)

    def with_freed(self, nodes: np.ndarray) -> BoundaryConditions:
        """Copy in which ``nodes`` ((k,) int; fixed, moving or mucosa nodes, not lip pairs) are
        free and listed in ``released``."""
        nodes = np.asarray(nodes, dtype=np.int64).reshape(-1)
        if nodes.size and (nodes.min() < 0 or nodes.max() >= self.n_nodes):
            raise ValueError(f"nodes to free must lie in [0, {self.n_nodes}), got {nodes.min()}..{nodes.max()}")
        if not nodes.size:
            return self
        types, segment = self.types.copy(), self.segment.copy()
        types[nodes] = NodeType.FREE
        segment[nodes] = -1
        return BoundaryConditions(types, segment, self.segment_names, self.upper_lip, self.lower_lip,
                                  np.union1d(self.released, nodes))

    def with_mid_edges_of_corners(self, mesh: Mesh) -> BoundaryConditions:
        """Copy in which every ``tet10`` mid-edge node that is fixed, moving or sliding is freed
        unless both corners of its edge have its type and segment.

        A boundary condition on a quadratic edge is the corners' condition interpolated along it.
        Node sets and release bands decide node by node, so a mid-edge node can stay attached to
        its bone while a corner of its edge is free (at the edge of a release band or of an
        attachment set): the bone then drags the middle of the edge along while the free corner
        lags, the edge bends and the element's Jacobian turns negative at a corner, whatever
        the step size. Freeing such a node lets the solve shape the edge as it shapes every free
        edge. Lip pairs are left as they are. Meshes without ``tet10`` cells are returned as
        they are."""
        if "tet10" not in mesh.cells or mesh.n_points != self.n_nodes:
            return self
        mid, a, b = tet10_mid_edges(mesh.cells["tet10"])
        t, s = self.types, self.segment
        bound = np.isin(t[mid], (NodeType.FIXED, NodeType.MOVING, NodeType.MUCOSA_SLIDING))
        same = (t[a] == t[mid]) & (t[b] == t[mid]) & (s[a] == s[mid]) & (s[b] == s[mid])
        loose = mid[bound & ~same]
        return self.with_freed(loose) if loose.size else self

    def _driver_strength(self) -> np.ndarray:
        """Rank of each driver (index = driver) when one of two neighbours must be freed:
        the immobile bone lowest, then proximal segments, distal mandible, Le Fort I."""
        order = {"proximal_left": 1, "proximal_right": 1, "distal": 2, "lefort": 3}
        return np.array([0] + [order.get(name, 0) for name in self.segment_names])

    @classmethod
    def from_mesh(cls, mesh: Mesh, segments: Mapping, *, lip_threshold: float = 0.2) -> BoundaryConditions:
        """Types from the node sets ``fixed``, the segments' attachment sets,
        ``mucosa_sliding`` and ``lip_sliding``.

        Parameters
        ----------
        mesh : the face (hex or tet) with those node sets; sets must be disjoint
        segments : name -> :class:`~toolkit.common.phantoms.phantom.BoneSegment`; a mucosa node slides
            on the segment whose ``sliding_set`` holds it, or (without such sets) on the
            segment surface nearest to it
        lip_threshold : mm; without ``upper_lip_face``/``lower_lip_face`` sets, lip nodes are
            paired by proximity below this distance (the lip-sliding paper's collision threshold), the
            node whose elements lie higher being the upper lip
        """
        n = mesh.n_points
        types = np.zeros(n, dtype=np.int8)
        segment = np.full(n, -1, dtype=np.int8)
        names = tuple(segments)
        owner: dict[int, str] = {}

        def claim(ids, kind, label):
            ids = np.asarray(ids, dtype=np.int64)
            clash = ids[types[ids] != NodeType.FREE]
            if clash.size:
                raise BoundaryError(f"node sets {owner.get(int(clash[0]), '?')!r} and {label!r} share {clash.size} "
                                    f"nodes (first: {clash[:5].tolist()}); a node can have one boundary type")
            types[ids] = kind
            owner.update(dict.fromkeys(ids.tolist(), label))

        claim(mesh.node_set("fixed"), NodeType.FIXED, "fixed")
        for k, seg in enumerate(segments.values()):
            if seg.node_set is not None and seg.node_set in mesh.node_sets:
                ids = mesh.node_sets[seg.node_set]
                claim(ids, NodeType.MOVING, seg.node_set)
                segment[ids] = k
        if "mucosa_sliding" in mesh.node_sets:
            muc = mesh.node_sets["mucosa_sliding"]
            claim(muc, NodeType.MUCOSA_SLIDING, "mucosa_sliding")
            sliding_sets = [getattr(s, "sliding_set", None) for s in segments.values()]
            if muc.size and all(n in mesh.node_sets for n in sliding_sets if n) and any(sliding_sets):
                for k, name in enumerate(sliding_sets):
                    if name:
                        segment[mesh.node_sets[name]] = k
                unassigned = muc[segment[muc] < 0]
                if unassigned.size:
                    raise BoundaryError(f"{unassigned.size} mucosa nodes are in no segment's sliding set (first: "
                                        f"{unassigned[:5].tolist()})")
            elif muc.size:
                # nudge each node towards its elements so that coincident nodes (the two faces of
                # the mouth slit on the occlusal plane) go to the segment on their own side
                probe = mesh.points[muc] + 0.25 * (_element_side(mesh)[muc] - mesh.points[muc])
                dist = np.stack([closest_points(probe, s.surface.points, s.surface.cells["tri3"]).distance
                                 for s in segments.values()], axis=1)
                segment[muc] = np.argmin(dist, axis=1)
        upper = lower = np.zeros(0, np.int64)
        if "lip_sliding" in mesh.node_sets:
            lip = mesh.node_sets["lip_sliding"]
            claim(lip, NodeType.LIP_SLIDING, "lip_sliding")
            if "upper_lip_face" in mesh.node_sets and "lower_lip_face" in mesh.node_sets:
                upper = np.intersect1d(lip, mesh.node_sets["upper_lip_face"])
                lower = np.intersect1d(lip, mesh.node_sets["lower_lip_face"])
            else:
                pts = mesh.points[lip]
                pairs = cKDTree(pts).query_pairs(lip_threshold, output_type="ndarray")
                a, b = lip[pairs[:, 0]], lip[pairs[:, 1]]
                # coincident nodes of a closed mouth tie in z: the side of their elements decides
                side = _element_side(mesh)
                up_first = side[a, 2] >= side[b, 2]
                upper, lower = np.where(up_first, a, b), np.where(up_first, b, a)
        return cls(types, segment, names, np.asarray(upper, np.int64), np.asarray(lower, np.int64))


def segments_from_mesh(mesh: Mesh, pivots: Mapping[str, np.ndarray]) -> dict:
    """Bony segments rebuilt from a face mesh's own bone-side surface.

    For a mesh without separate bone surfaces (e.g. a phantom read back from Abaqus, or a
    patient mesh with the phantom's node-set names), the bone side is the boundary faces
    whose nodes all lie on bone (any attachment set ``maxilla``/``mandible``, any sliding
    set ``mucosa_<segment>``, or the set ``bone`` when present), and a segment's surface
    is the bone-side faces touching its own attachment or sliding nodes. Segments with
    no such faces are left out.

    Parameters
    ----------
    mesh : the face mesh, mm
    pivots : segment name -> (3,) pivot, mm (e.g. the plan's)

    Returns
    -------
    dict name -> BoneSegment
    """

    tris = triangulated_boundary(mesh.cells)[:, [0, 2, 1]]  # normals into the tissue: out of the bone
    own = {}
    on_bone = np.zeros(mesh.n_points, dtype=bool)
    if "bone" in mesh.node_sets:
        on_bone[mesh.node_sets["bone"]] = True
    for name, attached in ATTACHMENT_SETS.items():
        own[name] = np.zeros(mesh.n_points, dtype=bool)
        for set_name in (attached, f"mucosa_{name}"):
            if set_name and set_name in mesh.node_sets:
                own[name][mesh.node_sets[set_name]] = True
        on_bone |= own[name]
    tris = tris[on_bone[tris].all(axis=1)]
    out = {}
    for name, attached in ATTACHMENT_SETS.items():
        sliding = f"mucosa_{name}"
        keep = tris[own[name][tris].any(axis=1)]
        if not keep.size:
            continue
        used = np.unique(keep)
        renumber = np.full(mesh.n_points, -1)
        renumber[used] = np.arange(used.size)
        surface = Mesh(mesh.points[used], {"tri3": renumber[keep]})
        out[name] = BoneSegment(name, surface, np.asarray(pivots.get(name, surface.points.mean(axis=0)), float),
                                attached if attached in mesh.node_sets else None,
                                sliding if sliding in mesh.node_sets else None)
    if not out:
        raise BoundaryError(f"no bone surface found: the mesh has none of the sets {sorted(ATTACHMENT_SETS.values())} "
                            f"or mucosa_<segment>; it has {sorted(mesh.node_sets)}")
    return out
