"""Vectorized finite-element assembly for solid elements (hex8, tet4, tet10).

Shape-function gradients and quadrature weights come from scikit-fem (the only
place where its ``(3, n)`` layout is read); element matrices are built with batched
``numpy.matmul`` over elements and scattered into a CSR matrix through a
precomputed pattern (``numpy.bincount``), with no Python loop over elements.

Volumetric locking (nu -> 0.5) is avoided on hexahedra by the **mean-dilatation
(B-bar) split**: the ``lam (tr eps)^2`` part of the energy (the ``lam (ln J)^2`` part for
Neo-Hookean) is evaluated once per element with the volume-averaged shape-function
gradients, the rest with 2x2x2 Gauss points. Averaging the gradients over the element
(rather than taking them at the centre, i.e. plain selective reduced integration)
keeps the patch test exact on distorted hexahedra.

Degrees of freedom are node-major: dof ``3 * node + component``. Units: mm, MPa,
N (forces), mJ (energies).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
import scipy.sparse as sp

from toolkit.common.materials import LinearElastic, NeoHookean, TransverselyIsotropic
from toolkit.common.mesh import Mesh

__all__ = ["Kinematics", "kinematics", "SparsePattern", "MaterialAssignment", "linear_stiffness",
           "neo_hookean_system", "neo_hookean_energy", "small_strain"]

_SRI_TYPES = ("hex8",)


@dataclass(frozen=True, eq=False)
class Kinematics:
    """Geometry of every element at its quadrature points.

    Attributes
    ----------
    conn : (E, A) int64 — element nodes in the local order of the gradients
    grad : (E, Q, A, 3) float, 1/mm — shape-function gradients
    weight : (E, Q) float, mm^3 — quadrature weights times det J
    grad_c : (E, A, 3) float, 1/mm — volume-averaged gradients (mean dilatation)
    volume : (E,) float, mm^3
    sri : bool — whether the volumetric part uses the averaged gradients
    """

    conn: np.ndarray
    grad: np.ndarray
    weight: np.ndarray
    grad_c: np.ndarray
    volume: np.ndarray
    sri: bool


def kinematics(mesh: Mesh, points: np.ndarray | None = None) -> Kinematics:
    """Gradients and weights of the volume block of ``mesh`` (optionally at other ``points``)."""
    import skfem

    m = mesh if points is None else mesh.with_points(points)
    ctype = m.volume_type
    sk = m.to_skfem()
    elem = {"hex8": skfem.ElementHex1, "tet4": skfem.ElementTetP1, "tet10": skfem.ElementTetP2}[ctype]()
    order = {"hex8": 2, "tet4": 1, "tet10": 2}[ctype]
    basis = skfem.Basis(sk, elem, intorder=order)
    n_local = elem.doflocs.shape[0]
    grad = np.stack([basis.basis[i][0].grad for i in range(n_local)]).transpose(2, 3, 0, 1)  # (E,Q,A,3)
    conn = np.asarray(sk.dofs.element_dofs if ctype == "tet10" else sk.t).T.astype(np.int64)
    weight = np.asarray(basis.dx)
    volume = weight.sum(axis=1)
    grad_bar = np.einsum("eqaj,eq->eaj", grad, weight) / volume[:, None, None]
    return Kinematics(conn, np.ascontiguousarray(grad), weight, grad_bar, volume, ctype in _SRI_TYPES)


class SparsePattern:
    """CSR sparsity pattern of a mesh's vector stiffness, built once per topology.

    ``assemble(Ke)`` sums element matrices ``(E, 3A, 3A)`` into CSR with one
    ``bincount``; the pattern is reused for every increment and Newton iteration.
    """

    def __init__(self, conn: np.ndarray, n_nodes: int):
        E, A = conn.shape
        self.n_dofs = 3 * n_nodes
        self.dofs = (3 * conn[:, :, None] + np.arange(3)).reshape(E, 3 * A)
        rows = np.repeat(self.dofs, 3 * A, axis=1).ravel()
        cols = np.tile(self.dofs, (1, 3 * A)).ravel()
        key = rows * self.n_dofs + cols
        uniq, self.slot = np.unique(key, return_inverse=True)
        self.slot = self.slot.ravel()
        self.indices = (uniq % self.n_dofs).astype(np.int32)
        counts = np.bincount(uniq // self.n_dofs, minlength=self.n_dofs)
        self.indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
        self.nnz = uniq.size

    def assemble(self, Ke: np.ndarray) -> sp.csr_matrix:
        data = np.bincount(self.slot, weights=Ke.reshape(-1), minlength=self.nnz)
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n_dofs, self.n_dofs))

    def assemble_vector(self, fe: np.ndarray) -> np.ndarray:
        """Sum element vectors ``(E, 3A)`` into a global ``(3 n_nodes,)`` vector."""
        return np.bincount(self.dofs.ravel(), weights=fe.ravel(), minlength=self.n_dofs)


@dataclass(frozen=True)
class MaterialAssignment:
    """Material of every element: a default plus overrides by element set.

    ``MaterialAssignment(LinearElastic(), {"lip_muscle": TransverselyIsotropic()})`` is seed
    001's face; a transversely isotropic material reads the cell field
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
        return all(isinstance(m, (LinearElastic, TransverselyIsotropic))
                   for m in [self.default, *(self.regions or {}).values()])

    def voigt(self, mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
        """Per-element Voigt stiffness ``(E, 6, 6)`` MPa and volumetric lambda ``(E,)`` MPa."""
        D = np.empty((mesh.n_cells, 6, 6))
        lam = np.empty(mesh.n_cells)
        for ids, mat in self.groups(mesh):
            if isinstance(mat, TransverselyIsotropic):
                if "fibre_direction" not in mesh.cell_data:
                    raise KeyError("a transversely isotropic material needs the cell field 'fibre_direction'")
                D[ids] = mat.stiffness(mesh.cell_data["fibre_direction"][ids])
            elif isinstance(mat, LinearElastic):
                D[ids] = mat.stiffness()
            else:
                raise TypeError(f"{type(mat).__name__} is not a linear material; use neo_hookean_system")
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


def linear_stiffness(kin: Kinematics, D: np.ndarray, lam: np.ndarray, pattern: SparsePattern) -> sp.csr_matrix:
    """Global small-strain stiffness, N/mm.

    Parameters
    ----------
    D : (E, 6, 6) MPa, lam : (E,) MPa — see :meth:`MaterialAssignment.voigt`
    """
    m = np.array([1.0, 1, 1, 0, 0, 0])
    if kin.sri:
        D_full = D - lam[:, None, None] * np.outer(m, m)
    else:
        D_full = D
    Ke = np.zeros((kin.conn.shape[0], 3 * kin.conn.shape[1], 3 * kin.conn.shape[1]))
    for q in range(kin.grad.shape[1]):
        B = _strain_matrix(kin.grad[:, q])
        Ke += kin.weight[:, q, None, None] * (np.transpose(B, (0, 2, 1)) @ (D_full @ B))
    if kin.sri:
        b = kin.grad_c.reshape(kin.grad_c.shape[0], -1)  # divergence row: d(u_k)/dx_k
        Ke += (kin.volume * lam)[:, None, None] * b[:, :, None] * b[:, None, :]
    return pattern.assemble(Ke)


def small_strain(kin: Kinematics, u: np.ndarray) -> np.ndarray:
    """Element-average small strain tensors ``(E, 3, 3)`` for displacements ``u (n, 3)`` mm."""
    H = np.einsum("eai,eqaj->eqij", u[kin.conn], kin.grad)
    eps = 0.5 * (H + np.swapaxes(H, -1, -2))
    return np.einsum("eqij,eq->eij", eps, kin.weight) / kin.volume[:, None, None]


def _deformation_gradient(kin: Kinematics, u: np.ndarray, grad: np.ndarray) -> np.ndarray:
    return np.eye(3) + np.einsum("eai,e...aj->e...ij", u[kin.conn], grad)


def neo_hookean_energy(kin: Kinematics, u: np.ndarray, groups) -> float:
    """Total strain energy (mJ) of the Neo-Hookean elements at displacement ``u (n, 3)`` mm.

    Returns ``inf`` if any element is inverted at a quadrature point.
    """
    total = 0.0
    for ids, mat in groups:
        F = _deformation_gradient(kin, u, kin.grad)[ids]
        J = np.linalg.det(F)
        Fc = _deformation_gradient(kin, u, kin.grad_c[:, None])[ids, 0]
        Jc = np.linalg.det(Fc)
        if np.any(J <= 0) or np.any(Jc <= 0):
            return np.inf
        I1 = np.einsum("eqij,eqij->eq", F, F)
        lnJ = np.log(J)
        if kin.sri:
            w_shear = 0.5 * mat.mu * (I1 - 3) - mat.mu * lnJ
            total += np.sum(kin.weight[ids] * w_shear) + np.sum(kin.volume[ids] * 0.5 * mat.lam * np.log(Jc) ** 2)
        else:
            total += np.sum(kin.weight[ids] * mat.energy(F))
    return float(total)


def neo_hookean_system(kin: Kinematics, u: np.ndarray, groups, pattern: SparsePattern,
                       tangent: bool = True) -> tuple[np.ndarray, sp.csr_matrix | None]:
    """Internal force ``(3n,)`` N and tangent stiffness (N/mm) at displacement ``u (n, 3)`` mm.

    Total Lagrangian on the configuration ``kin`` was computed for.
    """
    E, A = kin.conn.shape
    fe = np.zeros((E, A, 3))
    Ke = np.zeros((E, 3 * A, 3 * A)) if tangent else None
    parts = [("shear", kin.grad, kin.weight), ("volumetric", kin.grad_c[:, None], kin.volume[:, None])] \
        if kin.sri else [("all", kin.grad, kin.weight)]
    for ids, mat in groups:
        if not isinstance(mat, NeoHookean):
            raise TypeError(f"neo_hookean_system got {type(mat).__name__}; every element must be NeoHookean")
        for part, grad, weight in parts:
            g = grad[ids]
            F = _deformation_gradient(kin, u, grad)[ids]
            P, Atan = mat.first_piola(F, part)
            w = weight[ids]
            fe[ids] += np.einsum("eqij,eqaj,eq->eai", P, g, w)
            if tangent:
                # G[(i,j),(a,k)] = delta_ik g_aj  -> Ke = sum_q w G^T A9 G
                for q in range(g.shape[1]):
                    G = np.zeros((ids.size, 9, 3 * A))
                    for i in range(3):
                        for j in range(3):
                            G[:, 3 * i + j, i::3] = g[:, q, :, j]
                    A9 = Atan[:, q].reshape(ids.size, 9, 9)
                    Ke[ids] += w[:, q, None, None] * (np.transpose(G, (0, 2, 1)) @ (A9 @ G))
    f = pattern.assemble_vector(fe.reshape(E, -1))
    return f, (pattern.assemble(Ke) if tangent else None)
