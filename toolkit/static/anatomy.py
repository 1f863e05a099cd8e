"""Where plans are placed on a meshed face: the segments' pivots, the condyles and the dental arch.

A phantom carries these (:class:`~toolkit.common.phantoms.phantom.FacePhantom`). A face meshed from a
patient's surfaces (``toolkit mesh``) carries only node sets and bone surfaces, so
:func:`face_anatomy` derives them by documented rules, each overridable:

- **condyles** ``(2, 3)`` mm, left (x > 0) then right: the centroid of the bone surface within
  ``CONDYLE_BAND_MM`` of the top of each proximal segment (the condylar head is the highest
  part of a ramus); without proximal segments, of each side of the distal segment (split at
  the centroid of the ``maxilla`` set). Give ``condyles`` when the surfaces stop below the
  joints (a truncated segmentation, or the phantom, whose condyles lie outside its tissue).
- **pivots**: Le Fort I about the centroid of the ``maxilla`` set (the phantom's rule); the
  distal segment about the midpoint of the condyles; each proximal segment about its condyle.
- **dental arch** ``(k, 3)`` mm: the Le Fort I surface within ``ARCH_BAND_MM`` of its lowest
  point, where the maxillary teeth meet the mandibular ones; :func:`~toolkit.static.plan.jaw_closing`
  measures how far a plan drives the lower teeth through it.

:func:`~toolkit.static.plan.sample_plans` and :meth:`~toolkit.static.plan.SurgicalPlan.for_phantom`
take a :class:`FaceAnatomy` wherever they take a phantom.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from toolkit.common.errors import ToolkitError
from toolkit.common.fem.fibres import with_lip_fibres
from toolkit.common.meshes.mesh import Mesh
from toolkit.static.bones import segments_from_files
from toolkit.static.boundary import BoundaryError, segments_from_mesh

__all__ = ["FaceAnatomy", "face_anatomy", "AnatomyError", "CONDYLE_BAND_MM", "ARCH_BAND_MM"]

#: mm below the top of a proximal segment whose surface points average to its condyle
CONDYLE_BAND_MM = 5.0
#: mm above the lowest point of the Le Fort I surface taken as the dental arch
ARCH_BAND_MM = 2.0


class AnatomyError(ToolkitError, ValueError):
    """A meshed face lacks what plans are placed by (a segment, the ``maxilla`` set)."""


@dataclass(frozen=True, eq=False)
class FaceAnatomy:
    """A meshed face with the bony landmarks plans need (the phantom's equivalents).

    Attributes
    ----------
    mesh : the face Mesh, mm, with the phantom's node sets
    segments : name -> BoneSegment (surface and pivot, mm)
    condyles : (2, 3) float, mm — left (x > 0) then right
    arch : (k, 3) float, mm — the dental arch (:func:`~toolkit.static.plan.dental_arch`)
    """

    mesh: Mesh
    segments: Mapping
    condyles: np.ndarray
    arch: np.ndarray


def face_anatomy(mesh: Mesh, bones: Mapping[str, str | Path | Mesh] | None = None, *,
                 condyles: np.ndarray | None = None, units: str = "mm") -> FaceAnatomy:
    """The landmarks of a meshed face (rules in the module docstring).

    Parameters
    ----------
    mesh : face Mesh (mm) with ``maxilla`` and ``mandible`` and its bone-side sets, e.g. from
        :func:`toolkit.mesh.mesh_face`
    bones : segment name -> surface file or tri3 Mesh (mm), replacing the surfaces rebuilt from
        the mesh's bone-side faces (``lefort`` and ``distal`` are needed one way or the other)
    condyles : (2, 3) mm, left (x > 0) then right, instead of the rule
    units : length unit of the bone files

    Raises
    ------
    AnatomyError when the mesh has no ``maxilla`` set, ``lefort`` or ``distal`` has no surface,
    or ``condyles`` is not two points
    """

    if "maxilla" not in mesh.node_sets or not len(mesh.node_sets["maxilla"]):
        raise AnatomyError("the face mesh has no 'maxilla' node set (tissue attached to the Le Fort I segment); "
                           "mesh the face with `toolkit mesh`, which labels it")
    try:
        segments = segments_from_mesh(mesh, {})
    except BoundaryError:
        segments = {}
    segments.update(segments_from_files(mesh, dict(bones or {}), {}, units=units))
    missing = [name for name in ("lefort", "distal") if name not in segments]
    if missing:
        raise AnatomyError(f"no bone surface for {missing}: the mesh has no bone-side faces of these segments; "
                           "give them (command line: --bone lefort=maxilla.stl --bone distal=mandible.stl)")
    if condyles is None:
        condyles = _condyles(segments, mesh.points[mesh.node_sets["maxilla"]].mean(axis=0))
    condyles = np.asarray(condyles, dtype=float)
    if condyles.shape != (2, 3) or not np.isfinite(condyles).all():
        raise AnatomyError(f"condyles has shape {condyles.shape}; expected two points (2, 3) mm, left (x > 0) "
                           "then right (command line: --condyles X,Y,Z:X,Y,Z)")
    pivots = {"lefort": mesh.points[mesh.node_sets["maxilla"]].mean(axis=0), "distal": condyles.mean(axis=0),
              "proximal_left": condyles[0], "proximal_right": condyles[1]}
    segments = {name: replace(seg, pivot=np.array(pivots.get(name, seg.surface.points.mean(axis=0)), dtype=float))
                for name, seg in segments.items()}
    lefort = segments["lefort"].surface.points
    arch = lefort[lefort[:, 2] <= lefort[:, 2].min() + ARCH_BAND_MM]
    return FaceAnatomy(with_lip_fibres(mesh), segments, condyles, arch)


def _condyles(segments: Mapping, centre: np.ndarray) -> np.ndarray:
    """Left then right condyle ``(2, 3)`` mm by the top-band rule (module docstring)."""
    if "proximal_left" in segments and "proximal_right" in segments:
        sides = [segments["proximal_left"].surface.points, segments["proximal_right"].surface.points]
    else:
        pts = segments["distal"].surface.points
        sides = [pts[pts[:, 0] > centre[0]], pts[pts[:, 0] <= centre[0]]]
        if not all(len(s) for s in sides):
            raise AnatomyError("the distal segment's surface lies on one side of the face's midline; give the "
                               "condyles (command line: --condyles X,Y,Z:X,Y,Z)")
    return np.stack([p[p[:, 2] >= p[:, 2].max() - CONDYLE_BAND_MM].mean(axis=0) for p in sides])
