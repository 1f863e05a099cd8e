"""Segmentation damage: the phantom's clean surfaces made to look like a planning system's export.

A real segmentation is not the phantom's clean room. Its bone surfaces come with the triangle
winding mixed in patches, open along the saw cuts of the virtual osteotomy, in several pieces,
with small holes, at another resolution; and the tissue's inner surface stands off the bone by a
few mm where thresholds and smoothing left a gap. Each function here makes one of these from clean
surfaces, so that :func:`toolkit.mesh.mesh_face` can be shown to label the damaged face as it
labels the clean one (``benchmarks/segmentation_damage.py``, ``tests/mesh/test_damage.py``).

Every function is pure (new meshes out) and draws its randomness from the ``rng`` it is given.
Surfaces are ``tri3`` :class:`~toolkit.common.meshes.mesh.Mesh` objects in mm.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from scipy.spatial import cKDTree

from toolkit.common.meshes.mesh import Mesh

__all__ = ["DAMAGE", "flipped_in_patches", "kerfed", "with_holes", "in_pieces", "remeshed", "off_bone", "damaged"]

#: damage kinds :func:`damaged` applies, each with the measured default of its function
DAMAGE = ("flipped", "kerf", "holes", "pieces", "coarser", "finer", "off_bone", "all")


def _kept(surface: Mesh, keep: np.ndarray) -> Mesh:
    """The surface with only the triangles ``keep`` (bool) and the points they use."""
    tris = surface.cells["tri3"][keep]
    used, local = np.unique(tris, return_inverse=True)
    return Mesh(surface.points[used], {"tri3": local.reshape(-1, 3)})


def _centroids(surface: Mesh) -> np.ndarray:
    return surface.points[surface.cells["tri3"]].mean(axis=1)


def flipped_in_patches(surface: Mesh, fraction: float, rng: np.random.Generator, patch_mm: float = 8.0) -> Mesh:
    """The surface with about ``fraction`` of its triangles' winding reversed, in round patches
    of radius ``patch_mm`` (mm) about random triangles (as STL exports mix windings by region)."""
    c = _centroids(surface)
    tree = cKDTree(c)
    flip = np.zeros(c.shape[0], dtype=bool)
    for seed in rng.permutation(c.shape[0]):
        if flip.mean() >= fraction:
            break
        flip[tree.query_ball_point(c[seed], patch_mm)] = True
    tris = surface.cells["tri3"].copy()
    tris[flip] = tris[flip][:, [0, 2, 1]]
    return Mesh(surface.points, {"tri3": tris})


def kerfed(bones: Mapping[str, Mesh], width_mm: float) -> dict[str, Mesh]:
    """Each bone with the triangles within ``width_mm / 2`` of another segment's bone removed:
    the saw cut (kerf) of the osteotomy, which leaves every segment open along its cut line.
    Bones whose edges are longer than the kerf are split first (:func:`remeshed`, the same
    geometry) so that the cut follows the line."""
    from toolkit.common.analysis.surface_distance import closest_points

    out = {}
    for name, surface in bones.items():
        others = [b for k, b in bones.items() if k != name]
        if not others:
            out[name] = surface
            continue
        x = surface.points[surface.cells["tri3"]]
        edge = float(np.linalg.norm(x[:, 1] - x[:, 0], axis=1).mean())
        if edge > width_mm:
            surface = remeshed(surface, 4.0 ** int(np.ceil(np.log2(2 * edge / width_mm))))
        near = np.min([closest_points(surface.points, b.points, b.cells["tri3"]).distance for b in others], axis=0)
        keep = ~(near[surface.cells["tri3"]] < 0.5 * width_mm).any(axis=1)
        out[name] = _kept(surface, keep)
    return out


def with_holes(surface: Mesh, count: int, radius_mm: float, rng: np.random.Generator) -> Mesh:
    """The surface with ``count`` round holes of radius ``radius_mm`` (mm) about random points
    of it (thin bone that a threshold lost)."""
    c = _centroids(surface)
    centres = c[rng.choice(c.shape[0], size=min(count, c.shape[0]), replace=False)]
    hit = cKDTree(c).query_ball_point(centres, radius_mm)
    keep = np.ones(c.shape[0], dtype=bool)
    keep[np.concatenate([np.asarray(h, dtype=np.int64) for h in hit])] = False
    return _kept(surface, keep)


def in_pieces(surface: Mesh, cuts: int, width_mm: float, rng: np.random.Generator) -> Mesh:
    """The surface broken into pieces by ``cuts`` strips ``width_mm`` wide along random planes
    through its centre (a segmentation that fell apart at thin cortex)."""
    c = _centroids(surface)
    centre = c.mean(axis=0)
    keep = np.ones(c.shape[0], dtype=bool)
    for _ in range(cuts):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        offset = rng.uniform(-0.2, 0.2) * np.ptp((c - centre) @ n)
        keep &= np.abs((c - centre) @ n - offset) > 0.5 * width_mm
    return _kept(surface, keep)


def remeshed(surface: Mesh, factor: float) -> Mesh:
    """The surface at another resolution: ``factor > 1`` splits every triangle into four,
    ``log4(factor)`` times rounded (the same geometry, finer); ``factor < 1`` keeps about that
    share of the triangles by quadric decimation (coarser, the shape approximated)."""
    import pyvista as pv

    tris = surface.cells["tri3"]
    poly = pv.PolyData(surface.points, np.column_stack([np.full(len(tris), 3), tris]).ravel())
    if factor > 1:
        poly = poly.subdivide(max(1, round(np.log(factor) / np.log(4))), "linear")  # 4**k triangles
    elif factor < 1:
        poly = poly.decimate(1.0 - factor)
    else:
        return surface
    poly = poly.triangulate().clean()
    return Mesh(np.asarray(poly.points, dtype=float), {"tri3": np.asarray(poly.faces).reshape(-1, 4)[:, 1:]})


def off_bone(tissue: Mesh, bones: Mapping[str, Mesh], max_mm: float, rng: np.random.Generator,
             wavelength_mm: float = 40.0) -> dict[str, Mesh]:
    """The bones moved away from the tissue by 0 to ``max_mm`` (mm): every bone vertex along its own
    normal, turned away from the tissue (the side most of the bone's normals share with the tissue
    surface's outward normal at their closest tissue points), by a smooth random field (sines of
    ``wavelength_mm``), so that the tissue's inner surface stands 0-``max_mm`` off the bone as a
    segmentation leaves it. The
    tissue (a closed surface) stays as it is, so the phantom's own mesh can be run on the same
    bones (``benchmarks/segmentation_damage.py``). Apply it to consistently wound bones, each one
    sheet (before :func:`flipped_in_patches`)."""
    from toolkit.common.analysis.surface_distance import closest_points, vertex_normals

    x = tissue.points[tissue.cells["tri3"]]
    outward = 1.0 if np.einsum("ij,ij->i", x[:, 0], np.cross(x[:, 1], x[:, 2])).sum() > 0 else -1.0
    k = rng.normal(size=(3, 3))
    k *= 2 * np.pi / wavelength_mm / np.linalg.norm(k, axis=1, keepdims=True)
    phase = rng.uniform(0, 2 * np.pi, size=3)
    out = {}
    for name, bone in bones.items():
        p = bone.points
        normal = vertex_normals(p, bone.cells["tri3"])
        away = outward * closest_points(p, tissue.points, tissue.cells["tri3"]).normal
        side = 1.0 if np.einsum("ij,ij->i", normal, away).sum() >= 0 else -1.0  # the bone's side, as a whole
        field = 0.5 + np.sin(p @ k.T + phase).sum(axis=1) / 6.0  # in [0, 1]
        out[name] = Mesh(p + side * (max_mm * field)[:, None] * normal, {"tri3": bone.cells["tri3"]})
    return out


def damaged(tissue: Mesh, bones: Mapping[str, Mesh], kind: str, rng: np.random.Generator):
    """``(tissue, bones)`` with one kind of :data:`DAMAGE` applied at the strength the tests and
    the benchmark use (``all``: the bones off the tissue, then every export damage but the
    resolution changes):

    - ``flipped``: 30 % of each bone's triangles reversed in 8 mm patches;
    - ``kerf``: a 1 mm saw cut between every two segments;
    - ``holes``: three holes of 3 mm radius in each bone;
    - ``pieces``: each bone broken by two 1.5 mm strips;
    - ``coarser`` / ``finer``: each bone at half / four times its triangles;
    - ``off_bone``: the bones 0-5 mm off the tissue's inner surface.
    """
    if kind not in DAMAGE:
        raise ValueError(f"damage kind {kind!r}; expected one of {list(DAMAGE)}")
    bones = dict(bones)
    kinds = ["off_bone", "flipped", "kerf", "holes", "pieces"] if kind == "all" else [kind]
    for k in kinds:
        if k == "off_bone":
            bones = off_bone(tissue, bones, 5.0, rng)
        elif k == "kerf":
            bones = kerfed(bones, 1.0)
        else:
            step = {"flipped": lambda s: flipped_in_patches(s, 0.3, rng),
                    "holes": lambda s: with_holes(s, 3, 3.0, rng),
                    "pieces": lambda s: in_pieces(s, 2, 1.5, rng),
                    "coarser": lambda s: remeshed(s, 0.5), "finer": lambda s: remeshed(s, 4.0)}[k]
            bones = {name: step(s) for name, s in bones.items()}
    return tissue, bones
