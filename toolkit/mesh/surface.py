"""A closed, outward-oriented tissue surface from a segmentation export.

Segmentation tools (3D Slicer, ITK-SNAP) export the soft tissue as triangles that often
carry small defects. :func:`closed_surface` repairs those that have one safe answer and
refuses the others, naming the defect and where it is:

- coincident vertices (STL stores every triangle's corners separately): merged;
- degenerate triangles (two equal corners or no area): dropped;
- duplicated triangles: one kept; a pair of coincident triangles of opposite orientation
  (an internal membrane, e.g. two lips that touch in the segmentation) is dropped whole;
- small floating pieces (under ``min_piece_fraction`` of the triangles): dropped;
- inconsistent orientation: every piece oriented consistently, normals outward
  (positive enclosed volume);
- holes of up to ``max_hole_edges`` boundary edges: closed by a fan around the hole's centroid.

Refused (:class:`SurfaceError`): an edge shared by more than two triangles (non-manifold),
a non-orientable piece, a hole larger than ``max_hole_edges``, nothing left. Small
self-intersections are left to the mesher (fTetWild meshes through them; see
:mod:`toolkit.mesh.backends`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from toolkit.common.meshes.mesh import VOLUME_TYPES, Mesh, MeshError
from toolkit.common.meshes.surfaces import consistent_orientation, read_surface
from toolkit.common.meshes.topology import triangulated_boundary

__all__ = ["SurfaceError", "SurfaceRepair", "closed_surface", "read_tissue_surface", "tissue_surface_of"]


class SurfaceError(MeshError):
    """A surface defect that has no safe automatic repair."""


@dataclass(frozen=True)
class SurfaceRepair:
    """What :func:`closed_surface` changed (counts)."""

    merged_vertices: int = 0
    degenerate_triangles: int = 0
    duplicate_triangles: int = 0
    internal_triangles: int = 0
    dropped_pieces: int = 0
    dropped_piece_triangles: int = 0
    flipped_triangles: int = 0
    filled_holes: int = 0
    filled_hole_edges: int = 0

    def to_dict(self) -> dict:
        return asdict(self)

    @property
    def changed(self) -> bool:
        return any(v for v in asdict(self).values())


def _where(points: np.ndarray) -> str:
    return "(" + ", ".join(f"{v:.1f}" for v in np.asarray(points, dtype=float).reshape(-1, 3).mean(axis=0)) + ") mm"


def _coincident(points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """One representative per group of points closer than ``tolerance`` x the extent (on a grid
    of that step): (index of each group's first point, group of every point)."""
    tol = tolerance * max(float(np.ptp(points, axis=0).max()), 1e-12)
    _, first, inverse = np.unique(np.round(points / tol).astype(np.int64), axis=0, return_index=True,
                                  return_inverse=True)
    return first, inverse.ravel()


def _merge(points: np.ndarray, tris: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray, int]:
    first, inverse = _coincident(points, tolerance)
    return points[first], inverse[tris], points.shape[0] - first.size


def _without_degenerate(points: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, int]:
    x = points[tris]
    area2 = np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
    scale = max(float(np.ptp(points, axis=0).max()), 1e-12)
    keep = ((tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])
            & (area2 > 1e-14 * scale**2))
    return tris[keep], int((~keep).sum())


def _parity(tris: np.ndarray) -> np.ndarray:
    """+1 where ``tris`` is an even permutation of its sorted corners, -1 where odd."""
    order = np.argsort(tris, axis=1)
    inversions = ((order[:, 0] > order[:, 1]).astype(int) + (order[:, 0] > order[:, 2]) + (order[:, 1] > order[:, 2]))
    return np.where(inversions % 2 == 0, 1, -1)


def _without_duplicates(tris: np.ndarray) -> tuple[np.ndarray, int, int]:
    """Drop repeated triangles (keep one) and coincident opposite pairs (drop both)."""
    key = np.sort(tris, axis=1)
    _, first, inverse, counts = np.unique(key, axis=0, return_index=True, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    parity = _parity(tris)
    net = np.bincount(inverse, weights=parity, minlength=first.size)  # +k, -k or mixed
    keep_group = (counts == 1) | (np.abs(net) == counts)  # all copies alike
    # groups with both orientations: an internal membrane when they cancel, else keep the majority
    mixed = ~keep_group
    keep_group |= mixed & (net != 0)
    keep = np.zeros(tris.shape[0], dtype=bool)
    keep[first[keep_group]] = True
    out = tris[keep].copy()
    # a mixed group kept for its majority takes the majority's orientation
    flip = (np.sign(net[inverse[keep]]) != parity[keep]) & mixed[inverse[keep]]
    out[flip] = out[flip][:, [0, 2, 1]]
    internal = int(counts[mixed & (net == 0)].sum())
    duplicate = int(tris.shape[0] - keep.sum() - internal)
    return out, duplicate, internal


def _edges(tris: np.ndarray):
    """Directed edges ``(3t, 2)``, their owner triangle, undirected edge ids and use counts."""
    directed = np.stack([tris, np.roll(tris, -1, axis=1)], axis=2).reshape(-1, 2)
    owner = np.repeat(np.arange(tris.shape[0]), 3)
    key = np.sort(directed, axis=1)
    edges, eid, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return directed, owner, edges, eid.ravel(), counts


def _check_manifold(points: np.ndarray, tris: np.ndarray, name: str) -> None:
    _, _, edges, _, counts = _edges(tris)
    bad = np.flatnonzero(counts > 2)
    if bad.size:
        raise SurfaceError(
            f"{name}: {bad.size} edges are shared by more than two triangles (non-manifold), first near "
            f"{_where(points[edges[bad[0]]])}; expected each edge in at most two triangles. Repair it in the "
            "segmentation tool (3D Slicer: Surface Toolbox, 'Clean' then 'Fill holes'; or export the "
            "segment again as a closed surface)")


def _pieces(tris: np.ndarray) -> np.ndarray:
    """Connected piece of each triangle (sharing an edge)."""
    _, owner, _, eid, _ = _edges(tris)
    t = tris.shape[0]
    g = sp.coo_matrix((np.ones(eid.size), (owner, eid)), shape=(t, eid.max() + 1)).tocsr()
    _, label = connected_components(g @ g.T, directed=False)
    return label


def _drop_small_pieces(tris: np.ndarray, fraction: float) -> tuple[np.ndarray, int, int]:
    label = _pieces(tris)
    sizes = np.bincount(label)
    small = sizes < fraction * tris.shape[0]
    keep = ~small[label]
    return tris[keep], int(small.sum()), int((~keep).sum())


def _orient(points: np.ndarray, tris: np.ndarray, name: str) -> tuple[np.ndarray, int]:
    """Consistent orientation per piece, outward (positive signed volume); and how many
    triangles turned."""

    try:
        out, piece = consistent_orientation(tris, name)
    except MeshError as exc:
        raise SurfaceError(f"{exc}; expected a surface with an inside and an outside") from None
    x = points[out]
    vol = np.einsum("ij,ij->i", x[:, 0], np.cross(x[:, 1], x[:, 2])) / 6.0
    pieces, idx = np.unique(piece, return_inverse=True)
    inward = (np.bincount(idx, weights=vol, minlength=pieces.size) < 0)[idx]
    out[inward] = out[inward][:, [0, 2, 1]]
    return out, int(np.any(out != tris, axis=1).sum())


def _boundary_loops(tris: np.ndarray) -> list[np.ndarray]:
    """Closed loops of directed boundary edges, each in the direction its triangle traverses it."""
    directed, _, _, eid, counts = _edges(tris)
    rim = directed[counts[eid] == 1]
    if not rim.size:
        return []
    nxt: dict[int, list[int]] = {}  # a vertex where two holes touch has two successors
    for a, b in rim.tolist():
        nxt.setdefault(a, []).append(b)
    loops = []
    for start in rim[:, 0].tolist():
        if not nxt[start]:
            continue
        loop, v = [start], start
        while True:  # each directed rim edge once; a pinch vertex may appear twice in a loop
            w = nxt[v].pop()
            if w == start:
                break
            loop.append(w)
            v = w
        loops.extend(_simple_loops(loop))
    return loops


def _simple_loops(loop: list[int]) -> list[np.ndarray]:
    """Split a closed walk that passes a vertex twice (holes touching at a pinch) into simple loops."""
    out, stack, where = [], [], {}
    for v in loop:
        if v in where:  # close the sub-loop since the first visit
            i = where[v]
            sub = stack[i:]
            out.append(np.array(sub, dtype=np.int64))
            for w in sub[1:]:
                del where[w]
            del stack[i + 1:]
        else:
            where[v] = len(stack)
            stack.append(v)
    out.append(np.array(stack, dtype=np.int64))
    return [lp for lp in out if lp.size >= 3]


def _fill_holes(points: np.ndarray, tris: np.ndarray, max_edges: int, name: str):
    """Close each boundary loop of up to ``max_edges`` edges with a fan around its centroid."""
    loops = _boundary_loops(tris)
    big = [lp for lp in loops if lp.size > max_edges]
    if big:
        lp = max(big, key=len)
        length = float(np.linalg.norm(points[lp] - points[np.roll(lp, -1)], axis=1).sum())
        raise SurfaceError(
            f"{name} is open: a hole bounded by {lp.size} edges ({length:.0f} mm around) near {_where(points[lp])}"
            f"{f' and {len(big) - 1} more' if len(big) > 1 else ''}; expected a closed surface (holes of up to "
            f"max_hole_edges = {max_edges} edges are closed automatically). Close it in the segmentation tool, "
            f"or raise max_hole_edges (command line: --max-hole-edges {lp.size})")
    new_points, new_tris = [points], [tris]
    n = points.shape[0]
    for lp in loops:
        c = n
        n += 1
        new_points.append(points[lp].mean(axis=0, keepdims=True))
        # the loop runs the way its triangles traverse it; the patch must run it backwards
        new_tris.append(np.stack([np.roll(lp, -1), lp, np.full(lp.size, c)], axis=1))
    return np.vstack(new_points), np.vstack(new_tris), len(loops), int(sum(lp.size for lp in loops))


def closed_surface(points, triangles, *, name: str = "tissue surface", max_hole_edges: int = 60,
                   min_piece_fraction: float = 0.01, merge_tolerance: float = 1e-6) -> tuple[Mesh, SurfaceRepair]:
    """Repair a triangle surface into a closed, outward-oriented one (see the module).

    Parameters
    ----------
    points : (n, 3) float, mm
    triangles : (t, 3) int
    name : how errors name the surface (e.g. the file name)
    max_hole_edges : holes bounded by at most this many edges are closed
    min_piece_fraction : pieces with fewer triangles than this share of the whole are dropped
    merge_tolerance : vertices closer than this fraction of the extent are one vertex

    Returns
    -------
    (Mesh with one ``tri3`` block, its unused vertices dropped; what was repaired)

    Raises
    ------
    SurfaceError naming the defect, where it is and the remedy
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if not tris.size:
        raise SurfaceError(f"{name} holds no triangles; expected a closed triangulated surface")
    if tris.min() < 0 or tris.max() >= pts.shape[0]:
        raise SurfaceError(f"{name}: triangles refer to vertices outside 0..{pts.shape[0] - 1}")
    if not np.isfinite(pts).all():
        raise SurfaceError(f"{name}: {int((~np.isfinite(pts)).any(axis=1).sum())} vertices are not finite numbers")
    pts, tris, merged = _merge(pts, tris, merge_tolerance)
    tris, degenerate = _without_degenerate(pts, tris)
    tris, duplicate, internal = _without_duplicates(tris)
    if not tris.size:
        raise SurfaceError(f"{name}: no triangle is left after dropping degenerate and internal ones")
    _check_manifold(pts, tris, name)
    tris, dropped, dropped_tris = _drop_small_pieces(tris, min_piece_fraction)
    tris, flipped = _orient(pts, tris, name)
    pts, tris, holes, hole_edges = _fill_holes(pts, tris, max_hole_edges, name)
    used, tris = np.unique(tris, return_inverse=True)
    surface = Mesh(pts[used], {"tri3": tris.reshape(-1, 3)})
    report = SurfaceRepair(merged, degenerate, duplicate, internal, dropped, dropped_tris, flipped, holes, hole_edges)
    return surface, report


def read_tissue_surface(path, units: str = "mm", **repair) -> tuple[Mesh, SurfaceRepair]:
    """Read a tissue surface file (STL, OBJ, PLY, VTK, VTU, OFF) and :func:`closed_surface` it.

    ``units`` converts to mm; a surface whose size does not look like a face in mm is
    refused (:class:`~toolkit.common.meshes.io.UnitsError`). ``repair`` goes to :func:`closed_surface`.
    """
    from pathlib import Path


    surface = read_surface(path, units=units)
    return closed_surface(surface.points, surface.cells["tri3"], name=f"tissue surface {Path(path).name}", **repair)


def tissue_surface_of(mesh: Mesh) -> Mesh:
    """The closed soft-tissue surface of a volume mesh, as a segmentation would export it:
    its boundary triangulated, the two faces of a mouth slit merged (a closed mouth)."""

    # coincident nodes (the two faces of a mouth slit) become one: the slit's faces turn inner
    first, inverse = _coincident(mesh.points, 1e-6)
    cells = {t: inverse[c] for t, c in mesh.cells.items() if t in VOLUME_TYPES}
    surface, _ = closed_surface(mesh.points[first], triangulated_boundary(cells), name="boundary", max_hole_edges=0)
    return surface
