"""Bone surfaces from files: a patient's bony segments as triangle surfaces.

A real planning case comes as a face mesh plus the segmented bones (STL, OBJ, PLY, VTK,
VTU or OFF, in mm), e.g. ``maxilla.stl`` for the Le Fort I segment and
``mandible.stl`` for the distal mandible, read and oriented towards the soft tissue by
:mod:`toolkit.common.meshes.surfaces`; :func:`segments_from_files` turns a set of them into the
:class:`~toolkit.common.phantoms.phantom.BoneSegment` mapping :func:`~toolkit.static.simulate.simulate`
takes, attached and sliding on the face mesh's node sets as for the phantoms.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from toolkit.common.meshes.axes import mesh_to_toolkit
from toolkit.common.meshes.mesh import VOLUME_TYPES, Mesh
from toolkit.common.meshes.surfaces import orient_surface, read_surface
from toolkit.common.phantoms.phantom import BoneSegment
from toolkit.static.boundary import ATTACHMENT_SETS

__all__ = ["segments_from_files"]


def segments_from_files(face: Mesh, bones: Mapping[str, str | Path | Mesh], pivots: Mapping[str, np.ndarray],
                        units: str = "mm", axes: str = "toolkit") -> dict:
    """Bony segments from surface files for a face mesh.

    Parameters
    ----------
    face : the face mesh (mm) with the node sets of the phantoms: attachments ``maxilla``
        (Le Fort I) and ``mandible`` (distal), ``mucosa_sliding`` and optionally per-segment
        ``mucosa_<segment>`` sets
    bones : segment name (``lefort``, ``distal``, ``proximal_left``, ``proximal_right``,
        ``skull``) -> surface file or tri3 Mesh (mm)
    pivots : segment name -> (3,) mm pivot (the plan's; segments without one pivot about
        their surface centroid)
    units : length unit of the files
    axes : axes of the surfaces, files or Meshes (:data:`toolkit.common.meshes.axes.AXES`), converted to
        the toolkit's

    Returns
    -------
    dict name -> BoneSegment, surfaces oriented towards the face's bone-side nodes
    """

    unknown = sorted(set(bones) - set(ATTACHMENT_SETS))
    if unknown:
        raise ValueError(f"unknown bone segments {unknown}; expected some of {sorted(ATTACHMENT_SETS)}")
    # element centroids lie inside the soft tissue (bone-side nodes would lie on the bone itself)
    toward = np.concatenate([face.points[c].mean(axis=1) for t, c in face.cells.items() if t in VOLUME_TYPES])
    out = {}
    for name, source in bones.items():
        surface = mesh_to_toolkit(source if isinstance(source, Mesh) else read_surface(source, units=units), axes)
        surface = orient_surface(surface, toward)
        attached = ATTACHMENT_SETS[name]
        pivot = pivots.get(name)
        out[name] = BoneSegment(name, surface, np.asarray(surface.points.mean(axis=0) if pivot is None else pivot,
                                                          dtype=float),
                                attached if attached in face.node_sets else None,
                                f"mucosa_{name}" if f"mucosa_{name}" in face.node_sets else None)
    return out
