"""Distance between two triangle surfaces along the reference surface's normals (mm).

Used to compare a predicted face with a reference (the lip-sliding paper's surface deviation
maps): for each reference vertex, the absolute distance to the other surface
measured along the reference vertex normal, summarised per region.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from toolkit.common.analysis._validate import _as_points, _as_triangles, _region_indices
from toolkit.common.meshes.topology import rim_edges

__all__ = ["vertex_normals", "SurfaceDeviation", "surface_deviation", "ClosestPoints", "closest_points",
           "barycentric", "interpolate_on_surface", "beyond_rim_onto_plane"]


def vertex_normals(points, triangles) -> np.ndarray:
    """Area-weighted unit vertex normals of a triangle surface.

    Each triangle adds its (unnormalised) normal ``(b - a) x (c - a)``, whose length is twice
    its area, to its three vertices; the sums are normalised. Orientation follows the
    triangles' winding.

    Parameters
    ----------
    points : (n_points, 3) float, mm
    triangles : (n_triangles, 3) int64

    Returns
    -------
    (n_points, 3) float, unit vectors; rows of zeros for vertices used by no triangle
    (or whose adjacent triangle normals cancel).
    """
    p = _as_points(points, "points")
    t = _as_triangles(triangles, p.shape[0], "triangles")
    return _vertex_normals(p, t)


def _vertex_normals(p: np.ndarray, t: np.ndarray) -> np.ndarray:
    fn = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    n = np.empty_like(p)
    flat = t.ravel()
    for c in range(3):
        n[:, c] = np.bincount(flat, weights=np.repeat(fn[:, c], 3), minlength=p.shape[0])
    length = np.linalg.norm(n, axis=1)
    scale = np.max(np.linalg.norm(fn, axis=1)) if fn.size else 1.0
    ok = length > 1e-12 * scale
    n[ok] /= length[ok, None]
    n[~ok] = 0.0
    return n


@dataclass(frozen=True, eq=False)
class SurfaceDeviation:
    """Absolute distance from each reference vertex to the other surface along its normal.

    Attributes
    ----------
    distance : (n_ref,) float, mm
        ``|t|`` of the nearest intersection of the line ``x + t n`` (reference vertex ``x``,
        unit area-weighted normal ``n``) with the other surface; the closest-point distance
        where the line misses it; NaN for reference points used by no reference triangle.
    hit : (n_ref,) bool
        True where the normal line hit the other surface.
    n_fallback : int
        Number of referenced vertices whose distance is a closest-point distance.
    summary : pandas.DataFrame
        Per region (then ``'all'``): ``n_vertices`` (evaluated ones), ``mean``, ``max``,
        ``rmse`` of ``distance`` in mm, NaNs ignored.
    """

    distance: np.ndarray
    hit: np.ndarray
    n_fallback: int
    summary: pd.DataFrame


def surface_deviation(
    points,
    triangles,
    reference_points,
    reference_triangles,
    regions: Mapping[str, np.ndarray] | None = None,
    *,
    k: int = 24,
    chunk_size: int = 8192,
) -> SurfaceDeviation:
    """Surface deviation along the reference normals (the lip-sliding paper's surface-deviation error).

    For each reference vertex ``x`` with unit area-weighted normal ``n``, the line
    ``x + t n`` (both directions, ``t`` in R) is intersected with the other surface by the
    Moller-Trumbore test; the distance is ``|t|`` of the nearest hit. Only the ``k`` triangles
    of the other surface whose centroids are nearest to ``x`` (cKDTree) are tested, so the
    cost is O(n_ref k log m) and memory O(chunk_size k). Where the line misses all candidates
    the distance is the closest-point distance from ``x`` to those candidate triangles, and the
    vertex is counted in ``n_fallback``. For smooth surfaces with triangles smaller than the
    deviation, increase ``k`` if ``n_fallback`` is unexpectedly large.

    Parameters
    ----------
    points : (n_points, 3) float, mm
        Vertices of the evaluated (e.g. predicted) surface.
    triangles : (n_triangles, 3) int64
    reference_points : (n_ref, 3) float, mm
        Vertices of the reference (e.g. post-operative) surface, where distances are measured.
    reference_triangles : (n_ref_triangles, 3) int64
    regions : mapping name -> reference vertex indices (int64) or (n_ref,) bool mask, optional
    k : int
        Candidate triangles per reference vertex (16-32 is typical).
    chunk_size : int
        Reference vertices processed at once (bounds memory at ~chunk_size * k * 200 bytes).

    Returns
    -------
    SurfaceDeviation
    """
    p = _as_points(points, "points")
    t = _as_triangles(triangles, p.shape[0], "triangles")
    rp = _as_points(reference_points, "reference_points")
    rt = _as_triangles(reference_triangles, rp.shape[0], "reference_triangles")
    if int(k) < 1 or int(chunk_size) < 1:
        raise ValueError(f"k={k} and chunk_size={chunk_size}, expected positive integers")
    idx = _region_indices(regions, rp.shape[0], "reference vertex")

    normals = _vertex_normals(rp, rt)
    used = np.zeros(rp.shape[0], dtype=bool)
    used[rt.ravel()] = True

    v0, v1, v2 = p[t[:, 0]], p[t[:, 1]], p[t[:, 2]]
    tree = cKDTree((v0 + v1 + v2) / 3.0)
    k_eff = min(int(k), t.shape[0])

    distance = np.full(rp.shape[0], np.nan)
    hit = np.zeros(rp.shape[0], dtype=bool)
    todo = np.flatnonzero(used)
    for start in range(0, todo.size, int(chunk_size)):
        rows = todo[start : start + int(chunk_size)]
        x = rp[rows]
        _, cand = tree.query(x, k=k_eff)
        cand = cand.reshape(len(rows), k_eff)
        a, b, c = v0[cand], v1[cand], v2[cand]
        t_hit = _line_triangle_t(x, normals[rows], a, b, c)
        dist = np.min(np.abs(t_hit), axis=1)  # inf where no candidate was hit
        ok = np.isfinite(dist)
        if not np.all(ok):
            miss = ~ok
            dist[miss] = _closest_point_distance(x[miss], a[miss], b[miss], c[miss])
        distance[rows] = dist
        hit[rows] = ok
    n_fallback = int(np.count_nonzero(used & ~hit))

    idx["all"] = np.arange(rp.shape[0], dtype=np.int64)
    rows_ = {}
    for name, i in idx.items():
        v = distance[i]
        v = v[np.isfinite(v)]
        if v.size == 0:
            rows_[name] = {"n_vertices": 0, "mean": np.nan, "max": np.nan, "rmse": np.nan}
        else:
            rows_[name] = {
                "n_vertices": int(v.size),
                "mean": float(v.mean()),
                "max": float(v.max()),
                "rmse": float(np.sqrt(np.mean(v**2))),
            }
    summary = pd.DataFrame.from_dict(rows_, orient="index")
    summary.index.name = "region"
    return SurfaceDeviation(distance=distance, hit=hit, n_fallback=n_fallback, summary=summary)


def _line_triangle_t(x, d, a, b, c, tol: float = 1e-9) -> np.ndarray:
    """Line parameter of the intersection of ``x + t d`` with triangles (Moller-Trumbore).

    x, d : (n, 3); a, b, c : (n, k, 3). Returns (n, k) ``t`` (any sign), inf where the line is
    parallel to the triangle's plane or passes outside it (barycentric tolerance ``tol``).
    """
    e1 = b - a
    e2 = c - a
    dd = d[:, None, :]
    pvec = np.cross(dd, e2)
    det = np.einsum("nki,nki->nk", e1, pvec)
    scale = np.linalg.norm(e1, axis=-1) * np.linalg.norm(e2, axis=-1)
    ok = np.abs(det) > 1e-12 * scale
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = x[:, None, :] - a
    u = np.einsum("nki,nki->nk", s, pvec) * inv
    q = np.cross(s, e1)
    v = np.einsum("ni,nki->nk", d, q) * inv
    tt = np.einsum("nki,nki->nk", e2, q) * inv
    inside = ok & (u >= -tol) & (v >= -tol) & (u + v <= 1.0 + tol)
    return np.where(inside, tt, np.inf)


def _closest_on_triangles(x, a, b, c) -> np.ndarray:
    """Closest point of each candidate triangle to its point.

    x : (n, 3); a, b, c : (n, k, 3). Vectorised closest point on a triangle (Ericson,
    Real-Time Collision Detection, 5.1.5), region by region. Returns (n, k, 3).
    """
    p = x[:, None, :]
    ab, ac, ap = b - a, c - a, p - a
    bp, cp = p - b, p - c

    def dot(u, w):
        return np.einsum("nki,nki->nk", u, w)

    d1, d2 = dot(ab, ap), dot(ac, ap)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4

    def safe_div(num, den):
        return num / np.where(den == 0.0, 1.0, den)

    # interior (default), then edges and vertices override in reverse priority order
    denom = va + vb + vc
    closest = a + ab * safe_div(vb, denom)[..., None] + ac * safe_div(vc, denom)[..., None]
    cases = [
        (
            (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
            b + (c - b) * safe_div(d4 - d3, (d4 - d3) + (d5 - d6))[..., None],
        ),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * safe_div(d2, d2 - d6)[..., None]),
        ((d6 >= 0) & (d5 <= d6), c),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * safe_div(d1, d1 - d3)[..., None]),
        ((d3 >= 0) & (d4 <= d3), b),
        ((d1 <= 0) & (d2 <= 0), a),
    ]
    for mask, point in cases:
        closest = np.where(mask[..., None], point, closest)
    return closest


def _closest_point_distance(x, a, b, c) -> np.ndarray:
    """Distance (n,) from points x (n, 3) to the nearest of their candidate triangles (n, k, 3)."""
    return np.min(np.linalg.norm(_closest_on_triangles(x, a, b, c) - x[:, None, :], axis=-1), axis=1)


@dataclass(frozen=True, eq=False)
class ClosestPoints:
    """Closest points of a triangle surface.

    Attributes
    ----------
    point : (n, 3) float, mm — closest point on the surface
    distance : (n,) float, mm
    triangle : (n,) int64 — index of the triangle holding it
    normal : (n, 3) float — unit normal of that triangle (its orientation)
    """

    point: np.ndarray
    distance: np.ndarray
    triangle: np.ndarray
    normal: np.ndarray


def closest_points(points, surface_points, triangles, k: int = 16, tree: cKDTree | None = None) -> ClosestPoints:
    """Closest point on a triangle surface for every query point (exact among candidates).

    Candidates are the ``k`` triangles whose centroids are nearest to the point (a
    cKDTree, or ``tree`` built on those centroids to reuse it); on surfaces whose
    triangles are of similar size this finds the exact closest point.

    Parameters
    ----------
    points : (n, 3) float, mm
    surface_points : (m, 3) float, mm
    triangles : (t, 3) int
    k : candidate triangles per point

    Returns
    -------
    ClosestPoints
    """
    x = _as_points(points, "points")
    sp = _as_points(surface_points, "surface_points")
    tri = _as_triangles(triangles, sp.shape[0], "triangles")
    v0, v1, v2 = sp[tri[:, 0]], sp[tri[:, 1]], sp[tri[:, 2]]
    if tree is None:
        tree = cKDTree((v0 + v1 + v2) / 3.0)
    k = int(min(k, tri.shape[0]))
    _, cand = tree.query(x, k=k)
    cand = cand.reshape(x.shape[0], k)
    cp = _closest_on_triangles(x, v0[cand], v1[cand], v2[cand])
    d = np.linalg.norm(cp - x[:, None, :], axis=-1)
    best = np.argmin(d, axis=1)
    rows = np.arange(x.shape[0])
    t_best = cand[rows, best]
    n = np.cross(v1[t_best] - v0[t_best], v2[t_best] - v0[t_best])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return ClosestPoints(cp[rows, best], d[rows, best], t_best.astype(np.int64), n)


def beyond_rim_onto_plane(points, cp: ClosestPoints, surface_points, triangles, rim: np.ndarray | None = None,
                          tol: float = 1e-6) -> tuple[ClosestPoints, np.ndarray]:
    """Closest points on an open surface extended beyond its rim by the planes of its rim triangles.

    A point whose closest point ``cp`` lies on the rim (on a rim edge or at a rim vertex) and
    off the normal through it has passed the surface's edge: it is projected onto the plane
    of that closest triangle instead, so points beyond the edge are not all pulled onto the
    rim line. Other points keep ``cp``.

    Parameters
    ----------
    points : (n, 3) float, mm — the query points of ``cp``
    cp : ClosestPoints of ``points`` on the surface
    surface_points : (m, 3) float, mm; triangles : (t, 3) int
    rim : (e, 2) rim edges (:func:`toolkit.common.meshes.topology.rim_edges`; computed when None)
    tol : barycentric tolerance for "on an edge", and mm for "off the normal"

    Returns
    -------
    (ClosestPoints on the extended surface, (n,) bool — the points beyond the rim)
    """
    x = np.asarray(points, dtype=float)
    sp = np.asarray(surface_points, dtype=float)
    t = np.asarray(triangles, dtype=np.int64)
    rim = rim_edges(t) if rim is None else np.asarray(rim, dtype=np.int64)
    n_nodes = sp.shape[0]
    rim_codes = rim[:, 0] * n_nodes + rim[:, 1]
    rim_vertex = np.zeros(n_nodes, dtype=bool)
    rim_vertex[rim.ravel()] = True
    tri = t[cp.triangle]
    b = barycentric(cp.point, sp[tri])
    on_rim = np.zeros(x.shape[0], dtype=bool)
    for k in range(3):
        a, c = tri[:, (k + 1) % 3], tri[:, (k + 2) % 3]
        code = np.minimum(a, c) * n_nodes + np.maximum(a, c)
        on_rim |= (b[:, k] < tol) & np.isin(code, rim_codes)  # on the edge opposite vertex k
        on_rim |= (b[:, k] > 1 - tol) & rim_vertex[tri[:, k]]  # at vertex k
    offset = x - cp.point
    normal_part = np.einsum("ij,ij->i", offset, cp.normal)
    tangential = np.linalg.norm(offset - normal_part[:, None] * cp.normal, axis=1)
    beyond = on_rim & (tangential > tol)
    point = np.where(beyond[:, None], x - normal_part[:, None] * cp.normal, cp.point)
    distance = np.where(beyond, np.abs(normal_part), cp.distance)
    return ClosestPoints(point, distance, cp.triangle, cp.normal), beyond


def barycentric(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentric coordinates ``(k, 3)`` of points ``p (k, 3)`` in the planes of the
    triangles ``tri (k, 3, 3)`` (mm); they sum to 1 and are all in [0, 1] inside."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.stack([1 - v - w, v, w], axis=1)


def interpolate_on_surface(points, surface_points, triangles, values) -> np.ndarray:
    """A vertex field of a triangle surface, interpolated at the closest surface point of
    each query point (barycentric, linear on each triangle).

    Used to compare fields of different meshes of one surface (e.g. the skin displacement
    of the coarse, paper and fine faces at common points).

    Parameters
    ----------
    points : (k, 3) float, mm
    surface_points : (n, 3) float, mm; triangles : (t, 3) int
    values : (n, ...) float, one per surface vertex

    Returns
    -------
    (k, ...) float
    """
    sp = _as_points(surface_points, "surface_points")
    tri = _as_triangles(triangles, sp.shape[0], "triangles")
    vals = np.asarray(values, dtype=float)
    if vals.shape[0] != sp.shape[0]:
        raise ValueError(f"values has {vals.shape[0]} rows, expected one per surface point ({sp.shape[0]})")
    cp = closest_points(points, sp, tri)
    corners = tri[cp.triangle]
    w = barycentric(cp.point, sp[corners])
    return np.einsum("kc,kc...->k...", w, vals[corners])
