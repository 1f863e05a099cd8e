"""The static face phantom with its bone surfaces apart from the tissue, as segmented faces come.

A CT segmentation never puts the soft tissue exactly on the bone: on a real face mesh the
mucosa nodes lie 1.2 mm (median), 2.7 mm (90th percentile) and up to ~20 mm off the
segmented bone surface, and the bone surface is rougher than the tissue's inner boundary
(voxel steps, teeth, thin cortical walls). :func:`off_bone` reproduces that on a
:class:`~toolkit.common.phantoms.phantom.FacePhantom`: every vertex of every bone surface moves away
from the tissue, along its normal, by its own random log-normal offset (median ``median``,
90th percentile ``p90``, at most ``max_offset``). The tissue mesh, its node sets and the
plans stay as they are; only the segments' surfaces change. Projecting the mucosa onto such
a surface moves neighbouring nodes by different millimetres, which is what inverts elements
of a real mesh at the first increment. Units mm.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from toolkit.common.analysis.surface_distance import vertex_normals
from toolkit.common.phantoms.phantom import FacePhantom

__all__ = ["off_bone"]

_Z90 = 1.2815515655446004  # 90th percentile of the standard normal distribution


def off_bone(phantom: FacePhantom, median: float = 2.5, p90: float = 8.0, max_offset: float = 10.0,
             seed: int | np.random.Generator = 0) -> FacePhantom:
    """The phantom with each bone surface vertex moved away from the tissue by a random offset.

    Parameters
    ----------
    phantom : a FacePhantom (hexahedral, tetrahedral or mixed: the mesh is not changed)
    median, p90 : mm, median and 90th percentile of the vertex offsets (log-normal); the
        mucosa nodes' distances to the moved surfaces are smaller (a node's closest point is on
        the nearest of the neighbouring vertices' offsets; ``benchmarks/off_bone.py`` reports
        them on the ``paper`` phantom), and with the defaults a 5 mm mandibular advance inverts
        elements at the first increment when the mucosa is projected onto the bone
    max_offset : mm, the largest vertex offset
    seed : random seed or Generator of the offsets

    Returns
    -------
    FacePhantom with the same mesh and moved segment surfaces
    """
    if not 0.0 < median < p90:
        raise ValueError(f"median = {median!r}, p90 = {p90!r} mm; expected 0 < median < p90")
    if not max_offset > 0:
        raise ValueError(f"max_offset = {max_offset!r} mm; expected a positive length")
    rng = np.random.default_rng(seed)
    sigma = np.log(p90 / median) / _Z90
    mesh = phantom.mesh
    skin = mesh.points[mesh.node_sets["skin"]] if "skin" in mesh.node_sets else mesh.points
    tissue = cKDTree(skin)
    segments = {}
    for name, segment in phantom.segments.items():
        surface = segment.surface
        pts = surface.points
        normals = vertex_normals(pts, surface.cells["tri3"])
        # away from the tissue: against the direction to the nearest skin node
        _, near = tissue.query(pts)
        towards = skin[near] - pts
        side = np.where(np.einsum("ij,ij->i", normals, towards) >= 0, 1.0, -1.0)
        offset = np.minimum(median * np.exp(sigma * rng.standard_normal(pts.shape[0])), max_offset)
        segments[name] = replace(segment, surface=surface.with_points(pts - (side * offset)[:, None] * normals))
    return replace(phantom, segments=segments)
