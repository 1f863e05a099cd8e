"""Vectorized finite-element assembly for solid elements (hex8, wedge6, tet4, tet10),
on meshes that mix them.

Shape-function gradients and quadrature weights come from the reference-element records
(:mod:`toolkit.common.fem`, through :func:`toolkit.common.fem.kinematics.kinematics`), one
volume block at a time; element matrices are built with batched ``numpy.matmul`` over the
elements of a block and scattered into one CSR matrix for all blocks through the shared
:class:`~toolkit.common.fem.assembly.SparsePattern` (``numpy.bincount``), with no Python loop
over elements.

Volumetric locking (nu -> 0.5) is avoided on hexahedra and wedges by the
**mean-dilatation (B-bar) split**: the ``lam (tr eps)^2`` part of the energy (the
``lam (ln J)^2`` part for Neo-Hookean) is evaluated once per element with the
volume-averaged shape-function gradients, the rest at the Gauss points. Averaging the
gradients over the element (rather than taking them at the centre, i.e. plain selective
reduced integration) keeps the patch test exact on distorted elements.

Materials are assigned by global element sets (:class:`MaterialAssignment`), which may
span blocks. Degrees of freedom are node-major: dof ``3 * node + component``. Units: mm,
MPa, N (forces), mJ (energies).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from toolkit.common.fem.assembly import SparsePattern, element_tangent
from toolkit.common.fem.kinematics import BlockKinematics, Kinematics, deformation_gradient, element_forces, kinematics
from toolkit.common.fem.materials import LinearElastic
from toolkit.common.meshes.mesh import Mesh

__all__ = ["Kinematics", "BlockKinematics", "kinematics", "MaterialAssignment",
           "linear_stiffness", "neo_hookean_system", "neo_hookean_energy", "small_strain"]


@dataclass(frozen=True)
class MaterialAssignment:
    """Material of every element: a default plus overrides by element set.

    ``MaterialAssignment(LinearElastic(), {"lip_muscle": TransverselyIsotropic()})`` is the
    lip-sliding paper's face; a transversely isotropic material reads the cell field
    ``fibre_direction`` of the mesh.
    """

    default: object = LinearElastic()
    regions: Mapping[str, object] = None

    def groups(self, mesh: Mesh) -> list[tuple[np.ndarray, object]]:
        """``[(element indices, material), ...]`` covering every element once."""
        owner = np.full(mesh.n_cells, -1)
        mats = [self.default]
        for name, mat in (self.regions or {}).items():
            owner[mesh.element_set(name)] = len(mats)
            mats.append(mat)
        owner[owner < 0] = 0
        return [(np.flatnonzero(owner == k), m) for k, m in enumerate(mats) if np.any(owner == k)]

    @property
    def is_linear(self) -> bool:
        """Whether every material is small-strain linear (``material.linear``)."""
        return all(getattr(m, "linear", False) for m in [self.default, *(self.regions or {}).values()])

    def voigt(self, mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
        """Per-element Voigt stiffness ``(E, 6, 6)`` MPa and volumetric lambda ``(E,)`` MPa."""
        D = np.empty((mesh.n_cells, 6, 6))
        lam = np.empty(mesh.n_cells)
        for ids, mat in self.groups(mesh):
            if not getattr(mat, "linear", False):
                raise TypeError(f"{type(mat).__name__} is not a linear material; use neo_hookean_system")
            needs_fibre = getattr(mat, "needs_fibre", False)
            if needs_fibre and "fibre_direction" not in mesh.cell_data:
                raise KeyError(f"a {type(mat).__name__} material needs the cell field 'fibre_direction'")
            D[ids] = mat.stiffness(mesh.cell_data["fibre_direction"][ids]) if needs_fibre \
                else np.broadcast_to(mat.stiffness(), (ids.size, 6, 6))
            lam[ids] = mat.volumetric_lambda()
        return D, lam


def _strain_matrix(g: np.ndarray) -> np.ndarray:
    """Voigt B matrices ``(..., 6, 3A)`` from gradients ``(..., A, 3)``."""
    A = g.shape[-2]
    B = np.zeros(g.shape[:-2] + (6, 3 * A))
    for k in range(3):
        B[..., k, k::3] = g[..., k]
    B[..., 3, 1::3], B[..., 3, 2::3] = g[..., 2], g[..., 1]
    B[..., 4, 0::3], B[..., 4, 2::3] = g[..., 2], g[..., 0]
    B[..., 5, 0::3], B[..., 5, 1::3] = g[..., 1], g[..., 0]
    return B


def _block_stiffness(kb: BlockKinematics, D: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Element stiffness matrices ``(E, 3A, 3A)`` N/mm of one block; ``D (E, 6, 6)``, ``lam (E,)`` MPa."""
    m = np.array([1.0, 1, 1, 0, 0, 0])
    D_full = D - lam[:, None, None] * np.outer(m, m) if kb.sri else D
    Ke = np.zeros((kb.conn.shape[0], 3 * kb.conn.shape[1], 3 * kb.conn.shape[1]))
    for q in range(kb.grad.shape[1]):
        B = _strain_matrix(kb.grad[:, q])
        Ke += kb.weight[:, q, None, None] * (np.transpose(B, (0, 2, 1)) @ (D_full @ B))
    if kb.sri:
        b = kb.grad_c.reshape(kb.grad_c.shape[0], -1)  # divergence row: d(u_k)/dx_k
        Ke += (kb.volume * lam)[:, None, None] * b[:, :, None] * b[:, None, :]
    return Ke


def linear_stiffness(kin: Kinematics, D: np.ndarray, lam: np.ndarray, pattern: SparsePattern) -> sp.csr_matrix:
    """Global small-strain stiffness, N/mm.

    Parameters
    ----------
    D : (n_cells, 6, 6) MPa, lam : (n_cells,) MPa — by global element index, see
        :meth:`MaterialAssignment.voigt`
    """
    Ke = []
    for kb in kin.blocks:
        rows = slice(kb.offset, kb.offset + kb.conn.shape[0])
        Ke.append(_block_stiffness(kb, D[rows], lam[rows]))
    return pattern.assemble(Ke)


def small_strain(kin: Kinematics, u: np.ndarray) -> np.ndarray:
    """Element-average small strain tensors ``(n_volume_elements, 3, 3)`` for ``u (n, 3)`` mm."""
    out = []
    for kb in kin.blocks:
        H = np.einsum("eai,eqaj->eqij", u[kb.conn], kb.grad)
        eps = 0.5 * (H + np.swapaxes(H, -1, -2))
        out.append(np.einsum("eqij,eq->eij", eps, kb.weight) / kb.volume[:, None, None])
    return np.concatenate(out)


def _block_groups(kb: BlockKinematics, groups) -> list[tuple[np.ndarray, object]]:
    """``(local element indices, material)`` of the groups that have elements in block ``kb``."""
    out = []
    for ids, mat in groups:
        local = kb.local(ids)
        if local.size:
            out.append((local, mat))
    return out


def neo_hookean_energy(kin: Kinematics, u: np.ndarray, groups) -> float:
    """Total strain energy (mJ) of the Neo-Hookean elements at displacement ``u (n, 3)`` mm.

    Returns ``inf`` if any element is inverted at a quadrature point.
    """
    total = 0.0
    for kb in kin.blocks:
        F_all = deformation_gradient(kb, u)
        Fc_all = deformation_gradient(kb, u, kb.grad_c[:, None])[:, 0]
        for ids, mat in _block_groups(kb, groups):
            F, Fc = F_all[ids], Fc_all[ids]
            J = np.linalg.det(F)
            Jc = np.linalg.det(Fc)
            if np.any(J <= 0) or np.any(Jc <= 0):
                return np.inf
            if kb.sri:
                I1 = np.einsum("eqij,eqij->eq", F, F)
                w_shear = 0.5 * mat.mu * (I1 - 3) - mat.mu * np.log(J)
                total += np.sum(kb.weight[ids] * w_shear) + np.sum(kb.volume[ids] * 0.5 * mat.lam * np.log(Jc) ** 2)
            else:
                total += np.sum(kb.weight[ids] * mat.energy(F))
    return float(total)


def _block_system(kb: BlockKinematics, u: np.ndarray, groups, tangent: bool):
    """Element forces ``(E, 3A)`` N and tangents ``(E, 3A, 3A)`` N/mm (or None) of one block."""
    E, A = kb.conn.shape
    fe = np.zeros((E, A, 3))
    Ke = np.zeros((E, 3 * A, 3 * A)) if tangent else None
    parts = [("shear", kb.grad, kb.weight), ("volumetric", kb.grad_c[:, None], kb.volume[:, None])] \
        if kb.sri else [("all", kb.grad, kb.weight)]
    for part, grad, weight in parts:
        F_all = deformation_gradient(kb, u, grad)
        for ids, mat in groups:
            g = grad[ids]
            P, Atan = mat.first_piola(F_all[ids], part)
            w = weight[ids]
            fe[ids] += element_forces(g, w, P)
            if tangent:
                Ke[ids] += element_tangent(g, w, Atan)
    return fe.reshape(E, -1), Ke


def neo_hookean_system(kin: Kinematics, u: np.ndarray, groups, pattern: SparsePattern,
                       tangent: bool = True) -> tuple[np.ndarray, sp.csr_matrix | None]:
    """Internal force ``(3n,)`` N and tangent stiffness (N/mm) at displacement ``u (n, 3)`` mm.

    Total Lagrangian on the configuration ``kin`` was computed for; ``groups`` are
    ``(global element indices, material)`` pairs (:meth:`MaterialAssignment.groups`).
    """
    for _, mat in groups:
        if not hasattr(mat, "energy") or getattr(mat, "linear", False):
            raise TypeError(f"neo_hookean_system got {type(mat).__name__}; every element needs a hyperelastic "
                            "material with energy(F) and the split first_piola(F, part), like NeoHookean")
    fes, Kes = [], []
    for kb in kin.blocks:
        fe, Ke = _block_system(kb, u, _block_groups(kb, groups), tangent)
        fes.append(fe)
        Kes.append(Ke)
    f = pattern.assemble_vector(fes)
    return f, (pattern.assemble(Kes) if tangent else None)
