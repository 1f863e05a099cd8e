"""The mesh container shared by every workflow.

A :class:`Mesh` holds points ``(n_points, 3)`` in mm, cell blocks by type
(``hex8``, ``wedge6``, ``tet4``, ``tet10``, ``tri3``, ``quad4``), named node sets,
named element sets, and point/cell fields. It is immutable: transforms return new
meshes (``mesh.translated(u)``, ``mesh.with_node_sets(...)``).

A mesh may hold several volume blocks, as real face meshes do (hexahedra with wedges
and tetrahedra where the hexahedral mesher gave up): at most one block per type.
Element numbering is global: the elements of the cell blocks are numbered
consecutively in block order, so element sets and cell fields index
``range(mesh.n_cells)`` and may span blocks. :attr:`Mesh.volume_blocks` lists the
volume blocks with the global index of their first element::

    for block in mesh.volume_blocks:      # CellBlock(ctype, cells, offset)
        x = mesh.points[block.cells]      # (n_b, nodes_per_cell, 3) mm
        ids = block.elements              # global element indices of the block

Single-type meshes can use :attr:`Mesh.volume_type` and :attr:`Mesh.volume_cells`,
which raise a :class:`MeshError` naming the types on a mixed mesh.

Node ordering inside a cell is that of the cell's reference element
(:mod:`toolkit.common.fem.reference`): VTK/meshio for ``hex8``/``tet4``/``tet10``
(which for ``tet10`` is also Abaqus C3D10's) and meshio/Abaqus C3D6/gmsh for
``wedge6`` (the (0, 1, 2) triangle's normal points into the element).

Conversions (lossless, sets and fields kept) live in :mod:`toolkit.common.meshes.convert`;
element quality in :mod:`toolkit.common.meshes.quality`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from types import MappingProxyType
from typing import NamedTuple

import numpy as np

from toolkit.common.errors import DegenerateElementError, InvertedElementError, MeshError, MissingSetError
from toolkit.common.fem.reference import REFERENCE_ELEMENTS
from toolkit.common.meshes.quality import check_blocks, scaled_jacobian
from toolkit.common.meshes.topology import boundary_face_blocks

__all__ = [
    "Mesh",
    "CellBlock",
    "CELL_TYPES",
    "VOLUME_TYPES",
    "SURFACE_TYPES",
    "MeshError",
    "MissingSetError",
    "InvertedElementError",
    "DegenerateElementError",
]

#: nodes per cell, meshio name, spatial dimension of the reference cell (from the reference records)
CELL_TYPES: Mapping[str, tuple[int, str, int]] = MappingProxyType(
    {name: (ref.n_nodes, ref.meshio, ref.dim) for name, ref in REFERENCE_ELEMENTS.items()}
)
VOLUME_TYPES = tuple(name for name, ref in REFERENCE_ELEMENTS.items() if ref.dim == 3)
SURFACE_TYPES = tuple(name for name, ref in REFERENCE_ELEMENTS.items() if ref.dim == 2)


class CellBlock(NamedTuple):
    """One cell block of a mesh.

    Attributes
    ----------
    ctype : cell type (a key of :data:`CELL_TYPES`)
    cells : (n_b, nodes_per_cell) int64 connectivity
    offset : global index of the block's first element
    """

    ctype: str
    cells: np.ndarray
    offset: int

    @property
    def n_cells(self) -> int:
        return self.cells.shape[0]

    @property
    def elements(self) -> np.ndarray:
        """Global element indices ``(n_b,)`` int64 of the block."""
        return np.arange(self.offset, self.offset + self.cells.shape[0], dtype=np.int64)

    def local(self, ids: np.ndarray) -> np.ndarray:
        """The global element ``ids`` that lie in this block, as indices into :attr:`cells`."""
        ids = np.asarray(ids, dtype=np.int64)
        return ids[(ids >= self.offset) & (ids < self.offset + self.cells.shape[0])] - self.offset


def _frozen(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


def _as_index(a, name: str) -> np.ndarray:
    arr = np.asarray(a)
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        if not np.all(np.mod(arr, 1) == 0):
            raise MeshError(f"{name} must hold integer indices, got dtype {arr.dtype}")
    return np.ascontiguousarray(arr, dtype=np.int64)


@dataclass(frozen=True, eq=False)
class Mesh:
    """Points, cell blocks, node/element sets and fields; units mm.

    Parameters
    ----------
    points : (n_points, 3) float, mm
    cells : mapping ``type -> (n_cells_of_type, nodes_per_cell) int``
        Types from :data:`CELL_TYPES`. Block order fixes the global element numbering.
    node_sets : mapping ``name -> (k,) int``
        Node indices (sorted and de-duplicated on construction).
    element_sets : mapping ``name -> (k,) int``
        Global element indices.
    point_data : mapping ``name -> (n_points, ...)`` arrays
    cell_data : mapping ``name -> (n_cells, ...)`` arrays (all blocks concatenated)
    """

    points: np.ndarray
    cells: Mapping[str, np.ndarray]
    node_sets: Mapping[str, np.ndarray] = field(default_factory=dict)
    element_sets: Mapping[str, np.ndarray] = field(default_factory=dict)
    point_data: Mapping[str, np.ndarray] = field(default_factory=dict)
    cell_data: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        pts = np.ascontiguousarray(self.points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise MeshError(f"points has shape {pts.shape}, expected (n_points, 3)")
        bad = ~np.isfinite(pts).all(axis=1)
        if bad.any():
            ids = np.flatnonzero(bad)
            raise MeshError(f"{ids.size} points have NaN/inf coordinates (first point indices, from 0:"
                            f" {ids[:5].tolist()}); expected finite coordinates (mm)")
        n = pts.shape[0]
        cells = {}
        for ctype, conn in dict(self.cells).items():
            if ctype not in CELL_TYPES:
                raise MeshError(f"unknown cell type {ctype!r}; expected one of {sorted(CELL_TYPES)}")
            conn = _as_index(conn, f"cells[{ctype!r}]")
            k = CELL_TYPES[ctype][0]
            if conn.ndim != 2 or conn.shape[1] != k:
                raise MeshError(f"cells[{ctype!r}] has shape {conn.shape}, expected (n_cells, {k})")
            if conn.size and (conn.min() < 0 or conn.max() >= n):
                raise MeshError(
                    f"cells[{ctype!r}] refers to node {int(conn.max()) if conn.max() >= n else int(conn.min())}"
                    f" but the mesh has {n} points (valid 0..{n - 1})"
                )
            cells[ctype] = _frozen(conn)
        n_cells = sum(c.shape[0] for c in cells.values())
        node_sets = {}
        for name, ids in dict(self.node_sets).items():
            ids = np.unique(_as_index(ids, f"node set {name!r}").ravel())
            if ids.size and (ids[0] < 0 or ids[-1] >= n):
                bad = int(ids[-1] if ids[-1] >= n else ids[0])
                raise MeshError(f"node set {name!r} holds node {bad}; valid 0..{n - 1}")
            node_sets[name] = _frozen(ids)
        element_sets = {}
        for name, ids in dict(self.element_sets).items():
            ids = np.unique(_as_index(ids, f"element set {name!r}").ravel())
            if ids.size and (ids[0] < 0 or ids[-1] >= n_cells):
                raise MeshError(
                    f"element set {name!r} holds element {int(ids[-1] if ids[-1] >= n_cells else ids[0])};"
                    f" valid 0..{n_cells - 1}"
                )
            element_sets[name] = _frozen(ids)
        point_data = {}
        for name, a in dict(self.point_data).items():
            a = np.ascontiguousarray(a)
            if a.shape[:1] != (n,):
                raise MeshError(f"point_data[{name!r}] has shape {a.shape}, expected ({n}, ...)")
            point_data[name] = _frozen(a)
        cell_data = {}
        for name, a in dict(self.cell_data).items():
            a = np.ascontiguousarray(a)
            if a.shape[:1] != (n_cells,):
                raise MeshError(f"cell_data[{name!r}] has shape {a.shape}, expected ({n_cells}, ...)")
            cell_data[name] = _frozen(a)
        object.__setattr__(self, "points", _frozen(pts))
        object.__setattr__(self, "cells", MappingProxyType(cells))
        object.__setattr__(self, "node_sets", MappingProxyType(node_sets))
        object.__setattr__(self, "element_sets", MappingProxyType(element_sets))
        object.__setattr__(self, "point_data", MappingProxyType(point_data))
        object.__setattr__(self, "cell_data", MappingProxyType(cell_data))

    def __reduce__(self):
        # the read-only mappings (mappingproxy) cannot be pickled: rebuild from plain dicts, which
        # makes meshes picklable (process pools) and deep-copyable
        return (type(self), (self.points, dict(self.cells), dict(self.node_sets), dict(self.element_sets),
                             dict(self.point_data), dict(self.cell_data)))

    # ------------------------------------------------------------------ sizes
    @property
    def n_points(self) -> int:
        return self.points.shape[0]

    @property
    def n_cells(self) -> int:
        return sum(c.shape[0] for c in self.cells.values())

    @property
    def blocks(self) -> tuple[CellBlock, ...]:
        """Every cell block (volume and surface) in global element order."""
        out, offset = [], 0
        for ctype, conn in self.cells.items():
            out.append(CellBlock(ctype, conn, offset))
            offset += conn.shape[0]
        return tuple(out)

    @property
    def volume_blocks(self) -> tuple[CellBlock, ...]:
        """The volume blocks (``hex8``, ``wedge6``, ``tet4``, ``tet10``) in global element order."""
        return tuple(b for b in self.blocks if b.ctype in VOLUME_TYPES)

    @property
    def volume_types(self) -> tuple[str, ...]:
        """The volume cell types present, in block order."""
        return tuple(t for t in self.cells if t in VOLUME_TYPES)

    @property
    def n_volume_cells(self) -> int:
        """Number of volume elements over all volume blocks."""
        return sum(b.n_cells for b in self.volume_blocks)

    @property
    def volume_type(self) -> str:
        """The one volume cell type of a single-type mesh (``hex8``, ``wedge6``, ``tet4`` or ``tet10``).

        Raises :class:`MeshError` naming the types when the mesh has none or several
        (mixed meshes: iterate :attr:`volume_blocks`).
        """
        types = self.volume_types
        if len(types) != 1:
            hint = " (a mixed mesh: iterate mesh.volume_blocks instead)" if types else ""
            raise MeshError(f"mesh has volume cell types {list(types)}; expected exactly one here{hint}")
        return types[0]

    @property
    def volume_cells(self) -> np.ndarray:
        """Connectivity of the single volume block, ``(n_elements, nodes_per_cell)`` int64."""
        return self.cells[self.volume_type]

    def block_offset(self, ctype: str) -> int:
        """Global index of the first element of block ``ctype``."""
        for b in self.blocks:
            if b.ctype == ctype:
                return b.offset
        raise KeyError(f"no cell block {ctype!r}; the mesh has {list(self.cells)}")

    @cached_property
    def bounds(self) -> np.ndarray:
        """``(2, 3)`` min and max corner, mm."""
        return np.stack([self.points.min(axis=0), self.points.max(axis=0)])

    @property
    def extent(self) -> np.ndarray:
        """Bounding-box edge lengths ``(3,)``, mm."""
        return self.bounds[1] - self.bounds[0]

    def node_set(self, name: str) -> np.ndarray:
        """Node indices of set ``name``; a :class:`MissingSetError` (a ``KeyError``) lists the sets present."""
        try:
            return self.node_sets[name]
        except KeyError:
            raise MissingSetError(f"no node set {name!r}; the mesh has {sorted(self.node_sets)}") from None

    def element_set(self, name: str) -> np.ndarray:
        """Global element indices of set ``name``."""
        try:
            return self.element_sets[name]
        except KeyError:
            raise MissingSetError(f"no element set {name!r}; the mesh has {sorted(self.element_sets)}") from None

    # ------------------------------------------------------------ transforms
    def with_points(self, points: np.ndarray) -> Mesh:
        """Copy with new coordinates ``(n_points, 3)`` mm, topology unchanged."""
        points = np.asarray(points, dtype=float)
        if points.shape != self.points.shape:
            raise MeshError(f"new points have shape {points.shape}, expected {self.points.shape}")
        return replace(self, points=points)

    def translated(self, displacement: np.ndarray) -> Mesh:
        """Copy moved by ``displacement``: ``(3,)`` rigid or ``(n_points, 3)`` per node, mm."""
        return self.with_points(self.points + np.asarray(displacement, dtype=float))

    def with_node_sets(self, **sets) -> Mesh:
        """Copy with node sets added or replaced."""
        return replace(self, node_sets={**self.node_sets, **sets})

    def with_element_sets(self, **sets) -> Mesh:
        return replace(self, element_sets={**self.element_sets, **sets})

    def with_point_data(self, **data) -> Mesh:
        return replace(self, point_data={**self.point_data, **data})

    def with_cell_data(self, **data) -> Mesh:
        return replace(self, cell_data={**self.cell_data, **data})

    def without_fields(self) -> Mesh:
        """Copy with no point or cell data (geometry, topology and sets only)."""
        return replace(self, point_data={}, cell_data={})

    # ------------------------------------------------------------- geometry
    def boundary_face_blocks(self) -> dict[str, np.ndarray]:
        """Boundary faces of all volume blocks by face type, outward-oriented.

        Returns
        -------
        ``{"tri3": (k, 3), "quad4": (m, 4)}`` int64 (types with no face left out), in the
        mesh's node numbering (corner nodes only for ``tet10``), counter-clockwise seen
        from outside. A face shared by two cells, of the same type or not, is interior.
        """
        return boundary_face_blocks(self.cells)

    def boundary_faces(self) -> np.ndarray:
        """Faces on the boundary of the volume blocks, outward-oriented, as one array.

        Returns
        -------
        (n_faces, 3) or (n_faces, 4) int64
            Triangles for tetrahedra (corner nodes only for ``tet10``), quads for
            hexahedra, counter-clockwise seen from outside. A boundary with both
            triangles and quads (wedges, mixed meshes) raises :class:`MeshError`: use
            :meth:`boundary_face_blocks` or
            :func:`toolkit.common.meshes.topology.triangulated_boundary` there.
        """
        blocks = self.boundary_face_blocks()
        if len(blocks) > 1:
            raise MeshError(f"the boundary has {', '.join(f'{len(v)} {k}' for k, v in blocks.items())} faces"
                            f" (volume types {list(self.volume_types)}); one array needs one face type:"
                            " use mesh.boundary_face_blocks() or topology.triangulated_boundary(mesh.cells)")
        if not blocks:
            if not self.volume_types:
                raise MeshError(f"mesh has no volume block (cell types {list(self.cells)}); no boundary faces")
            size = 4 if self.volume_types == ("hex8",) else 3
            return np.zeros((0, size), dtype=np.int64)
        return next(iter(blocks.values()))

    def surface(self) -> Mesh:
        """The boundary surface as a ``tri3``/``quad4`` mesh with compacted points.

        A mixed boundary gives both blocks (``tri3`` first). Point data ``parent_node``
        (int64) maps each surface point to its node in this mesh; node sets are
        restricted to the surface and renumbered.
        """
        faces = self.boundary_face_blocks()
        used = np.unique(np.concatenate([f.ravel() for f in faces.values()])) if faces else \
            np.zeros(0, dtype=np.int64)
        renumber = np.full(self.n_points, -1, dtype=np.int64)
        renumber[used] = np.arange(used.size)
        sets = {}
        for name, ids in self.node_sets.items():
            keep = renumber[ids]
            sets[name] = keep[keep >= 0]
        pdata = {k: v[used] for k, v in self.point_data.items()}
        pdata["parent_node"] = used
        cells = {ctype: renumber[f] for ctype, f in faces.items()}
        return Mesh(self.points[used], cells, node_sets=sets, point_data=pdata)

    def scaled_jacobian(self) -> np.ndarray:
        """Per-element scaled Jacobian of all volume blocks, ``(n_volume_cells,)``.

        Blocks are concatenated in global element order (so the index is the global
        element index when the volume blocks come first, as in the phantoms and in
        files read here). 1 for an ideal cube / regular tetrahedron / right prism on an
        equilateral triangle, <= 0 for inverted elements. See
        :func:`toolkit.common.meshes.quality.scaled_jacobian` for the definitions.
        """
        parts = [scaled_jacobian(b.ctype, self.points[b.cells]) for b in self.volume_blocks]
        return np.concatenate(parts) if parts else np.zeros(0)

    def check(self, min_scaled_jacobian: float = 1e-3) -> Mesh:
        """Raise if any volume element is inverted or degenerate; return ``self``.

        All volume blocks are checked; messages give global element indices.

        Raises
        ------
        InvertedElementError
            Scaled Jacobian <= 0; the message names the first (worst) elements.
        DegenerateElementError
            0 < scaled Jacobian < ``min_scaled_jacobian``.
        """
        check_blocks(self.points, self.volume_blocks, min_scaled_jacobian)
        return self

    # --------------------------------------------------------------- equality
    def equals(self, other: Mesh, atol: float = 0.0) -> bool:
        """True if points (within ``atol`` mm), cells, sets and fields all match."""
        if not isinstance(other, Mesh) or self.points.shape != other.points.shape:
            return False
        if not np.allclose(self.points, other.points, atol=atol, rtol=0):
            return False
        if list(self.cells) != list(other.cells):
            return False
        if any(not np.array_equal(self.cells[k], other.cells[k]) for k in self.cells):
            return False
        for a, b in ((self.node_sets, other.node_sets), (self.element_sets, other.element_sets)):
            if set(a) != set(b) or any(not np.array_equal(a[k], b[k]) for k in a):
                return False
        for a, b in ((self.point_data, other.point_data), (self.cell_data, other.cell_data)):
            if set(a) != set(b) or any(not np.allclose(a[k], b[k], atol=atol) for k in a):
                return False
        return True

    def __repr__(self) -> str:
        blocks = ", ".join(f"{t}: {c.shape[0]}" for t, c in self.cells.items())
        return (
            f"Mesh({self.n_points} points; {blocks}; node sets {sorted(self.node_sets)};"
            f" element sets {sorted(self.element_sets)})"
        )
