"""The phantom as a segmentation would give it: a closed tissue surface, the bony segments'
surfaces and the commissures, for trying :func:`toolkit.mesh.mesh_face` and for the round
trip that compares its meshes with the phantom's own."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolkit.common.meshes.io import atomic_path
from toolkit.common.meshes.mesh import Mesh
from toolkit.common.phantoms.phantom import FacePhantom
from toolkit.mesh.surface import tissue_surface_of

__all__ = ["PhantomSurfaces", "phantom_surfaces", "write_surfaces"]


@dataclass(frozen=True)
class PhantomSurfaces:
    """tissue : closed ``tri3`` surface (mouth closed), mm; bones : segment -> ``tri3``
    surface, mm; commissures : (2, 3) mm, the slit's ends on the skin (left, right)."""

    tissue: Mesh
    bones: dict[str, Mesh]
    commissures: np.ndarray


#: the phantom's bone-side node sets of each segment
_SEGMENT_SETS = {"lefort": ("maxilla", "mucosa_lefort"), "distal": ("mandible", "mucosa_distal"),
                 "proximal_left": ("mucosa_proximal_left",), "proximal_right": ("mucosa_proximal_right",),
                 "skull": ("mucosa_skull",)}


def _trimmed(phantom: FacePhantom) -> dict[str, Mesh]:
    """Each bone surface cut back to its own segment, as a planning system exports the segments
    after the osteotomies. (The phantom extends each surface two cells past its segment, so
    neighbouring surfaces overlap.) A triangle stays when the nearest bone-side node of the
    phantom belongs to its segment."""
    from scipy.spatial import cKDTree

    m = phantom.mesh
    names = [n for n in _SEGMENT_SETS if n in phantom.segments]
    ids = [np.concatenate([m.node_sets[s] for s in _SEGMENT_SETS[n] if s in m.node_sets]) for n in names]
    owner = np.concatenate([np.full(len(i), k) for k, i in enumerate(ids)])
    tree = cKDTree(m.points[np.concatenate(ids)])
    out = {}
    for k, name in enumerate(names):
        surface = phantom.segments[name].surface
        tris = surface.cells["tri3"]
        keep = owner[tree.query(surface.points[tris].mean(axis=1))[1]] == k
        used, local = np.unique(tris[keep], return_inverse=True)
        out[name] = Mesh(surface.points[used], {"tri3": local.reshape(-1, 3)})
    return out


def phantom_surfaces(phantom: FacePhantom) -> PhantomSurfaces:
    """The surfaces of a hexahedral face phantom (:func:`toolkit.common.face_hex`): its closed
    tissue surface, its bone surfaces cut back to their segments (they do not overlap, as
    after a virtual osteotomy) and its commissures."""

    m = phantom.mesh
    skin = np.zeros(m.n_points, dtype=bool)
    skin[m.node_sets["skin"]] = True
    lip = m.node_sets["upper_lip_face"]
    p = m.points[lip[skin[lip]]]
    commissures = np.stack([p[np.argmax(p[:, 0])], p[np.argmin(p[:, 0])]])
    return PhantomSurfaces(tissue_surface_of(m), _trimmed(phantom), commissures)


def write_surfaces(folder, surfaces: PhantomSurfaces, suffix: str = ".stl") -> dict[str, Path]:
    """Write ``tissue`` and each bone as ``folder/NAME.stl`` (binary STL, or ``suffix``
    ``.ply``/``.obj``/``.vtk``/``.off``) and ``commissures.txt`` (two lines ``X,Y,Z``, the
    ``--commissures`` values). Returns name -> path."""
    import meshio


    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for name, surface in {"tissue": surfaces.tissue, **surfaces.bones}.items():
        path = folder / f"{name}{suffix}"
        with atomic_path(path) as tmp:
            meshio.write(tmp, meshio.Mesh(surface.points, [("triangle", surface.cells["tri3"])]),
                         file_format=None if suffix != ".stl" else "stl", **({"binary": True} if suffix == ".stl"
                                                                              else {}))
        out[name] = path
    path = folder / "commissures.txt"
    with atomic_path(path) as tmp:
        tmp.write_text("".join(",".join(f"{v:.3f}" for v in c) + "\n" for c in surfaces.commissures))
    out["commissures"] = path
    return out
