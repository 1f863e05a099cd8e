"""Geometry of every volume element at its quadrature points, block by block.

:func:`kinematics` maps each volume block of a (possibly mixed) mesh through its
reference element (:mod:`toolkit.common.fem`); both workflows use it (the impact workflow
with its tetrahedra and without mean dilatation). The default rules:

========  ==============================================  ==================
type      quadrature                                      mean dilatation
========  ==============================================  ==================
hex8      2x2x2 Gauss                                      yes
wedge6    3-point triangle x 2-point Gauss                 yes
tet4      1 point (the centroid)                           no (constant strain)
tet10     the 4-point degree-2 rule                        no
========  ==============================================  ==================

Mean dilatation (B-bar): the volumetric part of the energy uses the volume-averaged
gradients ``grad_c`` (see :mod:`toolkit.static.stiffness`).

On a block: :func:`deformation_gradient` ``F = I + sum_a u_a (x) dN_a/dX`` at the
quadrature points, :func:`element_forces` ``f_a = sum_q w_q P_q dN_a/dX`` per element and
:func:`internal_force` assembled over the nodes, :func:`lumped_mass` (HRZ). The per-point
loops are compiled with numba when it is available (:mod:`toolkit.common.fem.jit`), with
the numpy form kept as the readable reference.

Element indices are global (the mesh's numbering, surface blocks included): block
``b`` holds elements ``b.offset ... b.offset + len(b.conn) - 1``. Units: mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.common.fem.jit import njit, use_jit
from toolkit.common.fem.mapping import shape_gradients
from toolkit.common.fem.reference import reference_element
from toolkit.common.meshes.mesh import CellBlock, Mesh, MeshError

__all__ = ["BlockKinematics", "Kinematics", "kinematics", "QUADRATURE_ORDER", "MEAN_DILATATION_TYPES",
           "deformation_gradient", "element_forces", "internal_force", "lumped_mass"]

#: quadrature order per volume type (hex8 2x2x2, wedge6 3 x 2, tet4 1 point, tet10 4 points)
QUADRATURE_ORDER = {"hex8": 2, "wedge6": 2, "tet4": 1, "tet10": 2}
#: types whose volumetric part uses the volume-averaged gradients
MEAN_DILATATION_TYPES = ("hex8", "wedge6")


@dataclass(frozen=True, eq=False)
class BlockKinematics:
    """Geometry of the elements of one volume block at its quadrature points.

    Attributes
    ----------
    ctype : cell type
    offset : global index of the block's first element
    conn : (E, A) int64 — element nodes (the mesh's connectivity of the block)
    grad : (E, Q, A, 3) float, 1/mm — shape-function gradients
    weight : (E, Q) float, mm^3 — quadrature weights times det J
    grad_c : (E, A, 3) float, 1/mm — volume-averaged gradients (mean dilatation)
    volume : (E,) float, mm^3
    sri : bool — whether the volumetric part uses the averaged gradients
    """

    ctype: str
    offset: int
    conn: np.ndarray
    grad: np.ndarray
    weight: np.ndarray
    grad_c: np.ndarray
    volume: np.ndarray
    sri: bool

    @property
    def n_points(self) -> int:
        """Quadrature points in the block."""
        return self.weight.size

    def local(self, ids: np.ndarray) -> np.ndarray:
        """The global element ``ids`` in this block, as row indices into its arrays
        (:meth:`~toolkit.common.meshes.mesh.CellBlock.local`)."""
        return CellBlock(self.ctype, self.conn, self.offset).local(ids)


@dataclass(frozen=True, eq=False)
class Kinematics:
    """Geometry of every volume element, one :class:`BlockKinematics` per volume block.

    For a single-type mesh the block's arrays are also reachable directly
    (``kin.conn``, ``kin.grad``, ``kin.weight``, ``kin.grad_c``, ``kin.sri``); on a mixed
    mesh those raise and the caller iterates ``kin.blocks``. ``kin.volume`` is always
    the ``(n_volume_elements,)`` concatenation in block order.
    """

    blocks: tuple[BlockKinematics, ...]

    def _single(self, name: str) -> BlockKinematics:
        if len(self.blocks) != 1:
            raise MeshError(f"Kinematics.{name} needs a single volume block; this mesh has blocks "
                            f"{[b.ctype for b in self.blocks]}: iterate kin.blocks")
        return self.blocks[0]

    conn = property(lambda self: self._single("conn").conn, doc="(E, A) int64, single-block meshes")
    grad = property(lambda self: self._single("grad").grad, doc="(E, Q, A, 3) 1/mm, single-block meshes")
    weight = property(lambda self: self._single("weight").weight, doc="(E, Q) mm^3, single-block meshes")
    grad_c = property(lambda self: self._single("grad_c").grad_c, doc="(E, A, 3) 1/mm, single-block meshes")
    sri = property(lambda self: self._single("sri").sri, doc="mean dilatation, single-block meshes")

    @property
    def volume(self) -> np.ndarray:
        """Element volumes ``(n_volume_elements,)`` mm^3, blocks concatenated."""
        return np.concatenate([b.volume for b in self.blocks])

    @property
    def conns(self) -> tuple[np.ndarray, ...]:
        """Connectivity of every block (what :class:`~toolkit.static.stiffness.SparsePattern` takes)."""
        return tuple(b.conn for b in self.blocks)

    def inverted_elements(self) -> np.ndarray:
        """Global indices ``(k,)`` of elements with det J <= 0 at a quadrature point."""
        bad = [b.offset + np.flatnonzero((b.weight <= 0).any(axis=1)) for b in self.blocks]
        return np.concatenate(bad) if bad else np.zeros(0, dtype=np.int64)


def kinematics(mesh: Mesh, points: np.ndarray | None = None, mean_dilatation: bool | None = None) -> Kinematics:
    """Gradients and weights of every volume block of ``mesh``.

    Parameters
    ----------
    mesh : Mesh with one or several volume blocks (``hex8``, ``wedge6``, ``tet4``, ``tet10``)
    points : (n_points, 3) float, mm — another configuration of the same topology
    mean_dilatation : force the mean-dilatation split on (True) or off (False) for every
        block; default per type (:data:`MEAN_DILATATION_TYPES`)

    Returns
    -------
    Kinematics, one block per volume block in the mesh's order
    """
    x = mesh.points if points is None else mesh.with_points(points).points
    blocks = []
    for b in mesh.volume_blocks:
        grad, weight = shape_gradients(b.ctype, x[b.cells], QUADRATURE_ORDER[b.ctype])
        volume = weight.sum(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            grad_c = np.einsum("eqaj,eq->eaj", grad, weight) / volume[:, None, None]
        sri = b.ctype in MEAN_DILATATION_TYPES if mean_dilatation is None else bool(mean_dilatation)
        blocks.append(BlockKinematics(b.ctype, b.offset, b.cells, grad, weight, grad_c, volume, sri))
    if not blocks:
        raise MeshError(f"mesh has no volume block (cell types {list(mesh.cells)}); nothing to assemble")
    return Kinematics(tuple(blocks))


def deformation_gradient(kb: BlockKinematics, u: np.ndarray, grad: np.ndarray | None = None) -> np.ndarray:
    """``F (E, Q, 3, 3)`` at the quadrature points of block ``kb`` for nodal displacements
    ``u (n_nodes, 3)`` mm; ``grad (E, Q, A, 3)`` 1/mm other gradients than ``kb.grad``
    (``kb.grad_c[:, None]`` for the mean-dilatation part)."""
    grad = kb.grad if grad is None else grad
    u = np.ascontiguousarray(u, dtype=np.float64)
    if use_jit():
        F = np.empty(grad.shape[:2] + (3, 3))
        _deformation_gradient_loop(kb.conn, np.ascontiguousarray(grad), u, F)
        return F
    ue = u[kb.conn]  # (E, A, 3)
    F = np.matmul(np.swapaxes(ue, 1, 2)[:, None], grad)  # (E,1,3,A) @ (E,Q,A,3) -> (E,Q,3,3)
    F[..., 0, 0] += 1.0
    F[..., 1, 1] += 1.0
    F[..., 2, 2] += 1.0
    return F


def element_forces(grad: np.ndarray, weight: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Element internal forces ``(E, A, 3)`` N: ``f_ai = sum_q w_q P_ij dN_a/dX_j``.

    ``grad (E, Q, A, 3)`` 1/mm, ``weight (E, Q)`` mm^3, ``P (E, Q, 3, 3)`` MPa (first Piola-Kirchhoff).
    """
    return np.matmul(grad, np.swapaxes(P, -1, -2) * weight[..., None, None]).sum(axis=1)


def internal_force(kb: BlockKinematics, P: np.ndarray, n_nodes: int) -> np.ndarray:
    """Nodal internal forces ``(n_nodes, 3)`` N of block ``kb`` from ``P (E, Q, 3, 3)`` MPa."""
    if use_jit():
        f = np.zeros((n_nodes, 3))
        _internal_force_loop(kb.conn, kb.grad, kb.weight, np.ascontiguousarray(P, dtype=np.float64), f)
        return f
    fe = element_forces(kb.grad, kb.weight, P).reshape(-1, 3)
    idx = kb.conn.ravel()
    return np.stack([np.bincount(idx, weights=fe[:, k], minlength=n_nodes) for k in range(3)], axis=1)


def lumped_mass(kb: BlockKinematics, density: np.ndarray | float, n_nodes: int) -> np.ndarray:
    """Nodal lumped mass ``(n_nodes,)`` tonne of block ``kb``: each element's mass ``rho V``
    shared by the reference element's HRZ fractions
    (:attr:`~toolkit.common.fem.ReferenceElement.hrz_fractions`); ``density`` tonne/mm^3,
    scalar or ``(E,)``."""
    rho = np.broadcast_to(np.asarray(density, dtype=float), kb.volume.shape)
    m_e = rho * kb.volume
    frac = reference_element(kb.ctype).hrz_fractions
    return np.bincount(kb.conn.ravel(), weights=(m_e[:, None] * frac).ravel(), minlength=n_nodes)


@njit
def _deformation_gradient_loop(conn, grad, u, F):  # pragma: no cover - compiled
    """Compiled :func:`deformation_gradient`: ``F[e, q] = I + sum_a u[conn[e, a]] (x) grad[e, q, a]``."""
    E, Q, A, _ = grad.shape
    for e in range(E):
        for q in range(Q):
            for i in range(3):
                for j in range(3):
                    F[e, q, i, j] = 1.0 if i == j else 0.0
            for a in range(A):
                n = conn[e, a]
                for i in range(3):
                    ui = u[n, i]
                    for j in range(3):
                        F[e, q, i, j] += ui * grad[e, q, a, j]


@njit
def _internal_force_loop(conn, grad, weight, P, f):  # pragma: no cover - compiled
    """Compiled :func:`internal_force`: ``f[conn[e, a], i] += w[e, q] P[e, q, i, j] grad[e, q, a, j]``."""
    E, Q, A, _ = grad.shape
    for e in range(E):
        for q in range(Q):
            w = weight[e, q]
            for a in range(A):
                n = conn[e, a]
                for i in range(3):
                    s = 0.0
                    for j in range(3):
                        s += P[e, q, i, j] * grad[e, q, a, j]
                    f[n, i] += w * s
