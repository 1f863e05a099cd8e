"""The mesh container shared by every workflow.

A :class:`Mesh` holds points ``(n_points, 3)`` in mm, cell blocks by type
(``hex8``, ``tet4``, ``tet10``, ``tri3``, ``quad4``), named node sets, named
element sets, and point/cell fields. It is immutable: transforms return new meshes
(``mesh.translated(u)``, ``mesh.with_node_sets(...)``).

Element numbering is global: the elements of the cell blocks are numbered
consecutively in block order, so element sets and cell fields index
``range(mesh.n_cells)``. Node ordering inside a cell follows VTK/meshio (which for
``tet10`` is also Abaqus C3D10's).

Conversions (lossless, sets and fields kept) live in :mod:`toolkit.common.convert`;
element quality in :mod:`toolkit.common.quality`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from types import MappingProxyType
from typing import Mapping

import numpy as np

__all__ = [
    "Mesh",
    "CELL_TYPES",
    "VOLUME_TYPES",
    "SURFACE_TYPES",
    "MeshError",
    "InvertedElementError",
    "DegenerateElementError",
]

#: nodes per cell, meshio name, spatial dimension of the reference cell
CELL_TYPES: Mapping[str, tuple[int, str, int]] = MappingProxyType(
    {
        "hex8": (8, "hexahedron", 3),
        "tet4": (4, "tetra", 3),
        "tet10": (10, "tetra10", 3),
        "tri3": (3, "triangle", 2),
        "quad4": (4, "quad", 2),
    }
)
VOLUME_TYPES = ("hex8", "tet4", "tet10")
SURFACE_TYPES = ("tri3", "quad4")


class MeshError(ValueError):
    """A mesh is malformed: bad shapes, indices out of range, NaN coordinates."""


class InvertedElementError(MeshError):
    """Elements have a non-positive Jacobian (inside-out or folded).

    Attributes
    ----------
    elements : (k,) int64
        Global indices of the offending elements, worst first.
    values : (k,) float
        Their scaled Jacobians.
    """

    def __init__(self, message: str, elements: np.ndarray, values: np.ndarray):
        super().__init__(message)
        self.elements = np.asarray(elements, dtype=np.int64)
        self.values = np.asarray(values, dtype=float)


class DegenerateElementError(InvertedElementError):
    """Elements are positive but flat (scaled Jacobian below the tolerance)."""


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
            raise MeshError(f"{ids.size} points have NaN/inf coordinates (first: {ids[:5].tolist()})")
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
                raise MeshError(f"node set {name!r} holds node {int(ids[-1] if ids[-1] >= n else ids[0])}; valid 0..{n - 1}")
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

    # ------------------------------------------------------------------ sizes
    @property
    def n_points(self) -> int:
        return self.points.shape[0]

    @property
    def n_cells(self) -> int:
        return sum(c.shape[0] for c in self.cells.values())

    @property
    def volume_type(self) -> str:
        """The one volume cell type of the mesh (``hex8``, ``tet4`` or ``tet10``)."""
        types = [t for t in self.cells if t in VOLUME_TYPES]
        if len(types) != 1:
            raise MeshError(f"mesh has volume cell types {types}; expected exactly one")
        return types[0]

    @property
    def volume_cells(self) -> np.ndarray:
        """Connectivity of the volume block, ``(n_elements, nodes_per_cell)`` int64."""
        return self.cells[self.volume_type]

    def block_offset(self, ctype: str) -> int:
        """Global index of the first element of block ``ctype``."""
        offset = 0
        for t, c in self.cells.items():
            if t == ctype:
                return offset
            offset += c.shape[0]
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
        """Node indices of set ``name``; a clear KeyError lists the sets present."""
        try:
            return self.node_sets[name]
        except KeyError:
            raise KeyError(f"no node set {name!r}; the mesh has {sorted(self.node_sets)}") from None

    def element_set(self, name: str) -> np.ndarray:
        """Global element indices of set ``name``."""
        try:
            return self.element_sets[name]
        except KeyError:
            raise KeyError(f"no element set {name!r}; the mesh has {sorted(self.element_sets)}") from None

    # ------------------------------------------------------------ transforms
    def with_points(self, points: np.ndarray) -> "Mesh":
        """Copy with new coordinates ``(n_points, 3)`` mm, topology unchanged."""
        points = np.asarray(points, dtype=float)
        if points.shape != self.points.shape:
            raise MeshError(f"new points have shape {points.shape}, expected {self.points.shape}")
        return replace(self, points=points)

    def translated(self, displacement: np.ndarray) -> "Mesh":
        """Copy moved by ``displacement``: ``(3,)`` rigid or ``(n_points, 3)`` per node, mm."""
        return self.with_points(self.points + np.asarray(displacement, dtype=float))

    def with_node_sets(self, **sets) -> "Mesh":
        """Copy with node sets added or replaced."""
        return replace(self, node_sets={**self.node_sets, **sets})

    def with_element_sets(self, **sets) -> "Mesh":
        return replace(self, element_sets={**self.element_sets, **sets})

    def with_point_data(self, **data) -> "Mesh":
        return replace(self, point_data={**self.point_data, **data})

    def with_cell_data(self, **data) -> "Mesh":
        return replace(self, cell_data={**self.cell_data, **data})

    def without_fields(self) -> "Mesh":
        """Copy with no point or cell data (geometry, topology and sets only)."""
        return replace(self, point_data={}, cell_data={})

    # ------------------------------------------------------------- geometry
    def boundary_faces(self) -> np.ndarray:
        """Faces on the boundary of the volume block, outward-oriented.

        Returns
        -------
        (n_faces, 3) or (n_faces, 4) int64
            Triangles for tetrahedra (corner nodes only for ``tet10``), quads for
            hexahedra, in the mesh's node numbering, ordered counter-clockwise when
            seen from outside.
        """
        from toolkit.common.topology import boundary_faces

        return boundary_faces(self.volume_type, self.volume_cells)

    def surface(self) -> "Mesh":
        """The boundary surface as a ``tri3``/``quad4`` mesh with compacted points.

        Point data ``parent_node`` (int64) maps each surface point to its node in
        this mesh; node sets are restricted to the surface and renumbered.
        """
        faces = self.boundary_faces()
        used = np.unique(faces)
        renumber = np.full(self.n_points, -1, dtype=np.int64)
        renumber[used] = np.arange(used.size)
        ctype = "quad4" if faces.shape[1] == 4 else "tri3"
        sets = {}
        for name, ids in self.node_sets.items():
            keep = renumber[ids]
            sets[name] = keep[keep >= 0]
        pdata = {k: v[used] for k, v in self.point_data.items()}
        pdata["parent_node"] = used
        return Mesh(self.points[used], {ctype: renumber[faces]}, node_sets=sets, point_data=pdata)

    def scaled_jacobian(self) -> np.ndarray:
        """Per-element scaled Jacobian of the volume block, ``(n_elements,)``.

        1 for an ideal cube/regular tetrahedron, <= 0 for inverted elements. See
        :func:`toolkit.common.quality.scaled_jacobian` for the definitions.
        """
        from toolkit.common.quality import scaled_jacobian

        return scaled_jacobian(self.volume_type, self.points[self.volume_cells])

    def check(self, min_scaled_jacobian: float = 1e-3) -> "Mesh":
        """Raise if any volume element is inverted or degenerate; return ``self``.

        Raises
        ------
        InvertedElementError
            Scaled Jacobian <= 0; the message names the first (worst) elements.
        DegenerateElementError
            0 < scaled Jacobian < ``min_scaled_jacobian``.
        """
        from toolkit.common.quality import check_elements

        check_elements(self.volume_type, self.points[self.volume_cells], min_scaled_jacobian,
                       offset=self.block_offset(self.volume_type))
        return self

    # ----------------------------------------------------------- conversion
    def to_meshio(self):
        """meshio.Mesh with sets as ``point_sets``/``cell_sets`` and fields as data."""
        from toolkit.common.convert import to_meshio

        return to_meshio(self)

    @classmethod
    def from_meshio(cls, m) -> "Mesh":
        from toolkit.common.convert import from_meshio

        return from_meshio(m)

    def to_pyvista(self):
        """pyvista.UnstructuredGrid; sets travel as ``nodeset:NAME``/``elset:NAME`` masks."""
        from toolkit.common.convert import to_pyvista

        return to_pyvista(self)

    @classmethod
    def from_pyvista(cls, grid) -> "Mesh":
        from toolkit.common.convert import from_pyvista

        return from_pyvista(grid)

    def to_skfem(self):
        """scikit-fem mesh of the volume block (``MeshHex1``, ``MeshTet1``, ``MeshTet2``).

        Element sets become skfem subdomains. scikit-fem may renumber nodes (it puts
        the vertices of quadratic meshes first); :func:`toolkit.common.convert.skfem_node_map`
        gives the map, which is the identity for the phantoms.
        """
        from toolkit.common.convert import to_skfem

        return to_skfem(self)

    @classmethod
    def from_skfem(cls, skmesh, **kwargs) -> "Mesh":
        from toolkit.common.convert import from_skfem

        return from_skfem(skmesh, **kwargs)

    # --------------------------------------------------------------- equality
    def equals(self, other: "Mesh", atol: float = 0.0) -> bool:
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
