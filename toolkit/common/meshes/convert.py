"""Lossless conversion between :class:`~toolkit.common.meshes.mesh.Mesh` and meshio,
pyvista and scikit-fem meshes.

- meshio: node sets are ``point_sets``, element sets ``cell_sets`` (per block),
  fields are ``point_data``/``cell_data`` (cell data split per block).
- pyvista/VTK has no sets: they travel as ``uint8`` masks named ``nodeset:NAME``
  (point data) and ``elset:NAME`` (cell data); :func:`from_pyvista` decodes them.
  Wedges are permuted between our (Abaqus/meshio) node order and VTK's
  (``[0, 2, 1, 3, 5, 4]``, the reference record's ``vtk_order``), as meshio does for VTU:
  VTK then extracts outward faces (VTK 9.7's volume and quality filters assume the
  opposite wedge order and report such wedges as negative; rendering is unaffected).
- scikit-fem meshes carry element sets as subdomains; node sets and fields stay
  on our side (pass them back to :func:`from_skfem`). The only public place where
  the ``(3, n)`` layout of scikit-fem appears is this module.
"""

from __future__ import annotations

import numpy as np

from toolkit.common.fem.reference import REFERENCE_ELEMENTS
from toolkit.common.meshes.mesh import CELL_TYPES, Mesh, MeshError

__all__ = [
    "to_meshio",
    "from_meshio",
    "to_pyvista",
    "from_pyvista",
    "to_skfem",
    "from_skfem",
    "skfem_node_map",
    "NODESET_PREFIX",
    "ELSET_PREFIX",
]

NODESET_PREFIX = "nodeset:"
ELSET_PREFIX = "elset:"

#: meshio cell type -> ours; ``tetra4`` is what meshio reads Abaqus C3D4H as
_FROM_MESHIO = {**{v[1]: k for k, v in CELL_TYPES.items()}, "tetra4": "tet4"}
#: VTK cell type ids
_VTK_IDS = {name: ref.vtk_id for name, ref in REFERENCE_ELEMENTS.items()}
_FROM_VTK = {v: k for k, v in _VTK_IDS.items()}
#: volume types scikit-fem reads through meshio
_SKFEM_TYPES = ("hex8", "tet4", "tet10")


def _block_slices(mesh: Mesh) -> dict[str, slice]:
    out, start = {}, 0
    for t, c in mesh.cells.items():
        out[t] = slice(start, start + c.shape[0])
        start += c.shape[0]
    return out


# ------------------------------------------------------------------ meshio
def to_meshio(mesh: Mesh):
    """A ``meshio.Mesh`` with sets and fields."""
    import meshio

    slices = _block_slices(mesh)
    cells = [meshio.CellBlock(CELL_TYPES[t][1], c) for t, c in mesh.cells.items()]
    cell_data = {k: [v[s] for s in slices.values()] for k, v in mesh.cell_data.items()}
    cell_sets = {}
    for name, ids in mesh.element_sets.items():
        cell_sets[name] = [ids[(ids >= s.start) & (ids < s.stop)] - s.start for s in slices.values()]
    return meshio.Mesh(
        mesh.points,
        cells,
        point_data=dict(mesh.point_data),
        cell_data=cell_data,
        point_sets={k: np.asarray(v) for k, v in mesh.node_sets.items()},
        cell_sets=cell_sets,
    )


def from_meshio(m) -> Mesh:
    """A :class:`Mesh` from a ``meshio.Mesh``; unsupported cell types raise ``MeshError``.

    Blocks of the same type are merged (Abaqus files often hold one block per
    element set); element sets and cell data follow the merge.
    """
    pts = np.asarray(m.points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise MeshError(f"meshio points have shape {pts.shape}, expected (n, 3)")
    if pts.shape[1] == 2:
        pts = np.column_stack([pts, np.zeros(len(pts))])
    # blocks are grouped by our type (stable); element ids follow the new order
    types = []
    for block in m.cells:
        if block.type not in _FROM_MESHIO:
            raise MeshError(
                f"cell type {block.type!r} is not supported; expected one of "
                f"{sorted(_FROM_MESHIO)} (our {sorted(CELL_TYPES)})"
            )
        types.append(_FROM_MESHIO[block.type])
    order = list(dict.fromkeys(types))
    sizes = [len(b.data) for b in m.cells]
    new_start = 0
    by_type_blocks = {t: [i for i, tt in enumerate(types) if tt == t] for t in order}
    block_new_start = {}
    for t in order:
        for i in by_type_blocks[t]:
            block_new_start[i] = new_start
            new_start += sizes[i]
    cells = {t: np.concatenate([np.asarray(m.cells[i].data) for i in by_type_blocks[t]]) for t in order}

    def merge(per_block):
        parts = [np.asarray(per_block[i]) for t in order for i in by_type_blocks[t]]
        return np.concatenate(parts) if parts else np.zeros(0)

    cell_data = {k: merge(v) for k, v in m.cell_data.items()}
    element_sets = {}
    for name, per_block in (m.cell_sets or {}).items():
        ids = [np.asarray(per_block[i], dtype=np.int64) + block_new_start[i]
               for i in range(min(len(m.cells), len(per_block))) if per_block[i] is not None and len(per_block[i])]
        element_sets[name] = np.concatenate(ids) if ids else np.zeros(0, dtype=np.int64)
    return Mesh(
        pts,
        cells,
        node_sets={k: np.asarray(v) for k, v in (m.point_sets or {}).items()},
        element_sets=element_sets,
        point_data=dict(m.point_data),
        cell_data=cell_data,
    )


# ----------------------------------------------------------------- pyvista
def to_pyvista(mesh: Mesh):
    """A ``pyvista.UnstructuredGrid``; sets become ``nodeset:``/``elset:`` masks."""
    import pyvista as pv

    conn = []
    types = []
    for t, c in mesh.cells.items():
        k = c.shape[1]
        c = c[:, REFERENCE_ELEMENTS[t].vtk_order]  # our node order -> VTK's (wedges differ)
        conn.append(np.hstack([np.full((c.shape[0], 1), k), c]).ravel())
        types.append(np.full(c.shape[0], _VTK_IDS[t], dtype=np.uint8))
    grid = pv.UnstructuredGrid(
        np.concatenate(conn) if conn else np.zeros(0, dtype=np.int64),
        np.concatenate(types) if types else np.zeros(0, dtype=np.uint8),
        mesh.points.copy(),
    )
    for k, v in mesh.point_data.items():
        grid.point_data[k] = np.asarray(v)
    for k, v in mesh.cell_data.items():
        grid.cell_data[k] = np.asarray(v)
    for name, ids in mesh.node_sets.items():
        mask = np.zeros(mesh.n_points, dtype=np.uint8)
        mask[ids] = 1
        grid.point_data[NODESET_PREFIX + name] = mask
    for name, ids in mesh.element_sets.items():
        mask = np.zeros(mesh.n_cells, dtype=np.uint8)
        mask[ids] = 1
        grid.cell_data[ELSET_PREFIX + name] = mask
    return grid


def from_pyvista(grid) -> Mesh:
    """A :class:`Mesh` from a pyvista/VTK unstructured grid (or any pyvista dataset).

    Cells are grouped into one block per type in order of first appearance, keeping
    VTK's order within a type (meshers often interleave types); cell data and
    ``elset:`` masks follow, so element ``k`` of the mesh is VTK cell ``perm[k]`` with
    ``perm`` the stable sort of the cells by block. Wedges are permuted from VTK's node
    order to ours.
    """
    import pyvista as pv

    if not isinstance(grid, pv.UnstructuredGrid):
        grid = grid.cast_to_unstructured_grid()
    cells_dict = grid.cells_dict
    unknown = sorted(set(cells_dict) - set(_FROM_VTK))
    if unknown:
        raise MeshError(f"VTK cell type ids {unknown} are not supported; expected {sorted(_FROM_VTK)} "
                        f"({sorted(_VTK_IDS)})")
    celltypes = np.asarray(grid.celltypes)
    order = list(dict.fromkeys(celltypes.tolist()))
    perm = np.concatenate([np.flatnonzero(celltypes == t) for t in order]) if order else np.zeros(0, dtype=np.int64)
    # VTK node order -> ours (VTK node k is our node vtk_order[k]; wedges differ)
    cells = {_FROM_VTK[t]: np.asarray(cells_dict[t])[:, np.argsort(REFERENCE_ELEMENTS[_FROM_VTK[t]].vtk_order)]
             for t in order}
    node_sets, element_sets, pdata, cdata = {}, {}, {}, {}
    for k in grid.point_data.keys():
        v = np.asarray(grid.point_data[k])
        if k.startswith(NODESET_PREFIX):
            node_sets[k[len(NODESET_PREFIX):]] = np.flatnonzero(v)
        elif k not in ("vtkOriginalPointIds",):
            pdata[k] = v
    for k in grid.cell_data.keys():
        v = np.asarray(grid.cell_data[k])[perm]
        if k.startswith(ELSET_PREFIX):
            element_sets[k[len(ELSET_PREFIX):]] = np.flatnonzero(v)
        elif k not in ("vtkOriginalCellIds",):
            cdata[k] = v
    return Mesh(np.asarray(grid.points, dtype=float), cells, node_sets, element_sets, pdata, cdata)


# --------------------------------------------------------------- scikit-fem
def to_skfem(mesh: Mesh):
    """scikit-fem mesh (``MeshHex1``, ``MeshTet1``, ``MeshTet2``) of the volume block.

    Element sets become subdomains (indices into that block). Points are passed
    as scikit-fem's ``(3, n)``; see :func:`skfem_node_map` for the node order.
    """
    import meshio
    from skfem.io.meshio import from_meshio as sk_from_meshio

    ctype = mesh.volume_type
    if ctype not in _SKFEM_TYPES:
        raise MeshError(f"scikit-fem conversion supports {list(_SKFEM_TYPES)}, not {ctype!r} (scikit-fem reads no "
                        "meshio wedges); the static assembly does not need it (toolkit.common.fem.kinematics)")
    off = mesh.block_offset(ctype)
    n = mesh.cells[ctype].shape[0]
    cell_sets = {}
    for name, ids in mesh.element_sets.items():
        sel = ids[(ids >= off) & (ids < off + n)] - off
        if sel.size:
            cell_sets[name] = [sel]
    m = meshio.Mesh(mesh.points, [meshio.CellBlock(CELL_TYPES[ctype][1], mesh.cells[ctype])], cell_sets=cell_sets)
    return sk_from_meshio(m)


def skfem_node_map(mesh: Mesh, skmesh) -> np.ndarray:
    """Index in ``skmesh``'s nodes (``doflocs`` columns) of every node of ``mesh``.

    Returns
    -------
    (n_points,) int64; -1 for nodes used by no element of the converted block.
    """
    from skfem.io.meshio import HEX_MAPPING

    ctype = mesh.volume_type
    conn = mesh.cells[ctype]
    dofs = np.asarray(skmesh.dofs.element_dofs) if ctype == "tet10" else np.asarray(skmesh.t)
    if ctype == "hex8":
        dofs = dofs[HEX_MAPPING[:8]]
    out = np.full(mesh.n_points, -1, dtype=np.int64)
    out[conn.ravel()] = dofs.T.ravel()
    return out


def from_skfem(skmesh, node_sets=None, point_data=None, cell_data=None) -> Mesh:
    """A :class:`Mesh` from a scikit-fem mesh (subdomains become element sets).

    Node sets and fields, which scikit-fem does not carry, may be passed in the
    skfem node numbering.
    """
    from skfem.io.meshio import to_meshio as sk_to_meshio

    m = sk_to_meshio(skmesh, encode_cell_data=False)
    cells = {_FROM_MESHIO[b.type]: b.data for b in m.cells}
    pts = np.asarray(m.points, dtype=float)
    if pts.shape[1] == 2:
        pts = np.column_stack([pts, np.zeros(len(pts))])
    subdomains = getattr(skmesh, "subdomains", None) or {}
    return Mesh(
        pts,
        cells,
        node_sets=node_sets or {},
        element_sets={k: np.asarray(v) for k, v in subdomains.items()},
        point_data=point_data or {},
        cell_data=cell_data or {},
    )
