"""The static face phantom re-meshed with other cell types, as real face meshes come.

Patient meshes are rarely all hexahedra: tetrahedral meshers give ``tet4``, hex-dominant
ones mix hexahedra with wedges. :func:`remeshed` turns a hexahedral
:class:`~toolkit.common.phantoms.phantom.FacePhantom` into either, on the same nodes, so every node
set, the bony segments and the plans stay valid and results can be compared node by node:

- ``tet4``: every hexahedron split into 6 Kuhn tetrahedra (conforming);
- ``mixed``: a random ``wedge_fraction`` of the through-thickness columns split into 2
  wedges each (prism axis bone to skin: wedges meet the hexahedra on quadrilaterals and
  each other on their triangles), the rest left hexahedral.

Element sets (``lip_muscle``) and cell fields (``fibre_direction``) follow the elements
they were split from. :func:`jittered` moves the interior nodes at random until the worst
element is as poor as a given scaled Jacobian (real meshes have slivers). Units mm.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from toolkit.common.meshes.mesh import Mesh
from toolkit.common.meshes.topology import kuhn_tets, triangulated_boundary, wedges_from_hexes
from toolkit.common.phantoms.phantom import FACE_RESOLUTIONS, FacePhantom

__all__ = ["remeshed", "jittered", "REMESH_TYPES"]

REMESH_TYPES = ("tet4", "mixed")
#: phantom VTK hex position of each local (u, v, w) corner bit triple (see phantom._hex_connectivity)
_PHANTOM_ORDER = [(0, 0, 0), (0, 1, 0), (1, 1, 0), (1, 0, 0), (0, 0, 1), (0, 1, 1), (1, 1, 1), (1, 0, 1)]


def _corners(hexes: np.ndarray) -> np.ndarray:
    """Corners ``(n, 2, 2, 2)`` indexed by local (u, v, w) bits from phantom hex8 cells."""
    c = np.empty((hexes.shape[0], 2, 2, 2), dtype=np.int64)
    for pos, (i, j, k) in enumerate(_PHANTOM_ORDER):
        c[:, i, j, k] = hexes[:, pos]
    return c


def _split(mesh: Mesh, blocks: dict, parents: np.ndarray) -> Mesh:
    """``mesh`` with new cell ``blocks``; ``parents[e']`` is the old element of new element e'."""
    inverse = {}
    for name, ids in mesh.element_sets.items():
        member = np.zeros(mesh.n_cells, dtype=bool)
        member[ids] = True
        inverse[name] = np.flatnonzero(member[parents])
    cell_data = {k: v[parents] for k, v in mesh.cell_data.items()}
    return Mesh(mesh.points, blocks, node_sets=dict(mesh.node_sets), element_sets=inverse,
                point_data=dict(mesh.point_data), cell_data=cell_data)


def remeshed(phantom: FacePhantom, cell_type: str = "mixed", wedge_fraction: float = 0.4,
             seed: int | np.random.Generator = 0) -> FacePhantom:
    """The phantom on the same nodes with ``tet4`` or mixed ``hex8`` + ``wedge6`` cells.

    Parameters
    ----------
    phantom : a hexahedral FacePhantom (from :func:`~toolkit.common.phantoms.phantom.face_hex`)
    cell_type : ``tet4`` or ``mixed``
    wedge_fraction : share of the through-thickness columns split into wedges (``mixed``)
    seed : chooses those columns

    Returns
    -------
    FacePhantom with the new mesh (same points, node sets, segments)
    """
    if cell_type not in REMESH_TYPES:
        raise ValueError(f"cell_type = {cell_type!r}; expected one of {REMESH_TYPES}")
    if not 0.0 <= wedge_fraction <= 1.0:
        raise ValueError(f"wedge_fraction = {wedge_fraction!r}; expected a number in [0, 1]")
    mesh = phantom.mesh
    if set(mesh.cells) != {"hex8"}:
        raise ValueError(f"remeshed needs the hexahedral phantom, got cell types {sorted(mesh.cells)}")
    hexes = mesh.cells["hex8"]
    E = hexes.shape[0]
    corners = _corners(hexes)
    if cell_type == "tet4":
        tets = kuhn_tets(corners, mesh.points)  # tet t of hex e is row t * E + e
        return replace(phantom, mesh=_split(mesh, {"tet4": tets}, np.tile(np.arange(E), 6)))
    res = phantom.resolution
    n_u, n_v, n_w = FACE_RESOLUTIONS[res] if isinstance(res, str) else res
    if n_u * n_v * n_w != E:
        raise ValueError(f"the phantom has {E} hexahedra, not the {n_u} x {n_v} x {n_w} of its resolution")
    rng = np.random.default_rng(seed)
    columns = rng.random(n_u * n_v) < wedge_fraction  # element e = (i * n_v + j) * n_w + k
    split = np.repeat(columns, n_w)
    kept, cut = np.flatnonzero(~split), np.flatnonzero(split)
    wedges = wedges_from_hexes(corners[cut], mesh.points)  # the first wedge of every cell, then the second
    blocks = {"hex8": hexes[kept]} if kept.size else {}
    if cut.size:
        blocks["wedge6"] = wedges
    parents = np.concatenate([kept, cut, cut])
    return replace(phantom, mesh=_split(mesh, blocks, parents))


def jittered(phantom: FacePhantom, min_quality: float = 0.01, amplitude: float = 1.5,
             seed: int | np.random.Generator = 0) -> FacePhantom:
    """The phantom with its interior nodes moved at random, down to a poor worst element.

    Interior nodes (on no boundary face) move by up to ``amplitude`` mm per axis; the moves
    of nodes around elements that would fall below ``min_quality`` are shrunk (x 0.8, up
    to 100 times) until none does, so the worst scaled Jacobian ends just above it.

    Returns
    -------
    FacePhantom with the moved mesh (same topology, sets and segments)
    """

    if not 0.0 < min_quality < 1.0:
        raise ValueError(f"min_quality = {min_quality!r}; expected a number in (0, 1)")
    mesh = phantom.mesh
    interior = np.ones(mesh.n_points, dtype=bool)
    interior[np.unique(triangulated_boundary(mesh.cells))] = False
    rng = np.random.default_rng(seed)
    move = np.zeros((mesh.n_points, 3))
    move[interior] = rng.uniform(-amplitude, amplitude, (int(interior.sum()), 3))
    for _ in range(100):
        sj = mesh.with_points(mesh.points + move).scaled_jacobian()
        if sj.min() > min_quality:
            break
        bad = np.zeros(mesh.n_points, dtype=bool)
        start = 0
        for block in mesh.volume_blocks:
            n = block.cells.shape[0]
            bad[block.cells[sj[start:start + n] <= min_quality].ravel()] = True
            start += n
        move[bad] *= 0.8
    return replace(phantom, mesh=mesh.with_points(mesh.points + move))
