"""The phantom as a segmentation would give it: a closed tissue surface, the bony segments'
surfaces and the commissures, for trying :func:`toolkit.mesh.mesh_face` and for the round
trip that compares its meshes with the phantom's own."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolkit.common.mesh import Mesh
from toolkit.common.phantom import FacePhantom

__all__ = ["PhantomSurfaces", "phantom_surfaces", "write_surfaces"]


@dataclass(frozen=True)
class PhantomSurfaces:
    """tissue : closed ``tri3`` surface (mouth closed), mm; bones : segment -> ``tri3``
    surface, mm; commissures : (2, 3) mm, the slit's ends on the skin (left, right)."""

    tissue: Mesh
    bones: dict[str, Mesh]
    commissures: np.ndarray


def phantom_surfaces(phantom: FacePhantom) -> PhantomSurfaces:
    """The surfaces of a hexahedral face phantom (:func:`toolkit.common.face_hex`)."""
    from toolkit.mesh.surface import tissue_surface_of

    m = phantom.mesh
    skin = np.zeros(m.n_points, dtype=bool)
    skin[m.node_sets["skin"]] = True
    lip = m.node_sets["upper_lip_face"]
    p = m.points[lip[skin[lip]]]
    commissures = np.stack([p[np.argmax(p[:, 0])], p[np.argmin(p[:, 0])]])
    bones = {name: seg.surface for name, seg in phantom.segments.items()}
    return PhantomSurfaces(tissue_surface_of(m), bones, commissures)


def write_surfaces(folder, surfaces: PhantomSurfaces, suffix: str = ".stl") -> dict[str, Path]:
    """Write ``tissue`` and each bone as ``folder/NAME.stl`` (binary STL, or ``suffix``
    ``.ply``/``.obj``/``.vtk``/``.off``) and ``commissures.txt`` (two lines ``X,Y,Z``, the
    ``--commissures`` values). Returns name -> path."""
    import meshio

    from toolkit.common.io import atomic_path

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
