"""Tetrahedral elements for explicit dynamics: gradients, lumped mass, critical time step.

- ``tet4``: one Gauss point, row-sum lumped mass ``rho V / 4``.
- ``tet10`` (Abaqus C3D10 equivalent): 4 Gauss points; **HRZ** lumped mass (diagonal
  of the consistent mass scaled to the element mass): corners ``rho V / 36``, mid-edge
  nodes ``4 rho V / 27``, all positive — row-sum lumping would give the corners
  ``-rho V / 20``. The ratios follow from ``int N_a^2 dV`` = ``V / 70`` (corner) and
  ``8 V / 105`` (mid-edge) on a straight-sided tetrahedron.

The critical time step uses the element eigenvalue inequality: the largest natural
frequency of the assembled mesh is bounded by the largest element frequency, found
from the element's linear stiffness and lumped mass (``omega_max = max_e sqrt(eig(M_e^-1
K_e))``), so ``dt_crit = 2 / omega_max``. For a tet4 this is close to the textbook
``h / c_d`` with ``h`` the smallest altitude and ``c_d`` the dilatational wave speed.

Units: mm, s, tonne, N, MPa.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.common.mesh import InvertedElementError, Mesh
from toolkit.common.quality import tet10_shape_gradients
from toolkit.impact.jit import njit, use_jit

__all__ = ["TetKinematics", "tet_kinematics", "lumped_mass", "critical_time_step", "HRZ_TET10",
           "deformation_gradient", "internal_force"]

#: HRZ lumped-mass fractions of a straight tet10 (4 corners, 6 mid-edge nodes)
HRZ_TET10 = np.array([1 / 36] * 4 + [4 / 27] * 6)

_GAUSS4 = np.full((4, 3), 0.1381966011250105) + np.vstack([np.zeros(3), 0.4472135954999579 * np.eye(3)])


@dataclass(frozen=True, eq=False)
class TetKinematics:
    """Reference-configuration geometry of a tet block.

    Attributes
    ----------
    conn : (E, A) int64
    grad : (E, Q, A, 3) 1/mm — dN/dX at the Gauss points
    weight : (E, Q) mm^3 — reference volume per Gauss point
    volume : (E,) mm^3
    order : 1 or 2
    """

    conn: np.ndarray
    grad: np.ndarray
    weight: np.ndarray
    volume: np.ndarray
    order: int

    @property
    def n_points(self) -> int:
        """Gauss points in the block."""
        return self.weight.size


def _reference_gradients(order: int) -> tuple[np.ndarray, np.ndarray]:
    """dN/dxi ``(Q, A, 3)`` and reference weights ``(Q,)`` (sum 1/6)."""
    if order == 1:
        g = np.array([[-1.0, -1.0, -1.0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])[None]
        return g, np.array([1.0 / 6.0])
    return tet10_shape_gradients(_GAUSS4), np.full(4, 1.0 / 24.0)


def tet_kinematics(mesh: Mesh) -> TetKinematics:
    """Gradients and weights of the ``tet4``/``tet10`` block of ``mesh``; raises on inverted elements."""
    ctype = mesh.volume_type
    if ctype not in ("tet4", "tet10"):
        raise ValueError(f"explicit elements are tet4 or tet10, got {ctype!r}")
    order = 1 if ctype == "tet4" else 2
    conn = mesh.volume_cells
    dN, w = _reference_gradients(order)
    X = mesh.points[conn]  # (E, A, 3)
    J = np.einsum("eai,qak->eqik", X, dN)  # dX_i/dxi_k
    detJ = np.linalg.det(J)
    if np.any(detJ <= 0):
        bad = np.flatnonzero((detJ <= 0).any(axis=1))
        raise InvertedElementError(f"{bad.size} {ctype} elements have det J <= 0 at a Gauss point "
                                   f"(first: {bad[:5].tolist()})", bad, detJ.min(axis=1)[bad])
    Jinv = np.linalg.inv(J)
    grad = np.einsum("qak,eqkj->eqaj", dN, Jinv)
    weight = detJ * w
    return TetKinematics(conn, np.ascontiguousarray(grad), weight, weight.sum(axis=1), order)


def lumped_mass(kin: TetKinematics, density: np.ndarray | float, n_nodes: int) -> np.ndarray:
    """Nodal lumped mass ``(n_nodes,)`` tonne (HRZ for tet10), density tonne/mm^3 per element or scalar."""
    rho = np.broadcast_to(np.asarray(density, dtype=float), kin.volume.shape)
    m_e = rho * kin.volume
    frac = np.full(4, 0.25) if kin.order == 1 else HRZ_TET10
    return np.bincount(kin.conn.ravel(), weights=(m_e[:, None] * frac).ravel(), minlength=n_nodes)


def deformation_gradient(kin: TetKinematics, u: np.ndarray) -> np.ndarray:
    """``F (E, Q, 3, 3)`` at the Gauss points for nodal displacements ``u (n, 3)`` mm."""
    u = np.ascontiguousarray(u, dtype=np.float64)
    if use_jit():
        F = np.empty(kin.weight.shape + (3, 3))
        _deformation_gradient_loop(kin.conn, kin.grad, u, F)
        return F
    ue = u[kin.conn]  # (E, A, 3)
    F = np.matmul(np.swapaxes(ue, 1, 2)[:, None], kin.grad)  # (E,1,3,A) @ (E,Q,A,3) -> (E,Q,3,3)
    F[..., 0, 0] += 1.0
    F[..., 1, 1] += 1.0
    F[..., 2, 2] += 1.0
    return F


def internal_force(kin: TetKinematics, P: np.ndarray, n_nodes: int) -> np.ndarray:
    """Nodal internal forces ``(n_nodes, 3)`` N from first Piola-Kirchhoff stresses ``P (E, Q, 3, 3)`` MPa."""
    # f_a,i = sum_q w P_ij dN_a/dX_j
    if use_jit():
        f = np.zeros((n_nodes, 3))
        _internal_force_loop(kin.conn, kin.grad, kin.weight, np.ascontiguousarray(P, dtype=np.float64), f)
        return f
    fe = np.matmul(kin.grad, np.swapaxes(P, -1, -2) * kin.weight[..., None, None]).sum(axis=1)  # (E, A, 3)
    idx = kin.conn.ravel()
    fe = fe.reshape(-1, 3)
    return np.stack([np.bincount(idx, weights=fe[:, k], minlength=n_nodes) for k in range(3)], axis=1)


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


def _element_stiffness(kin: TetKinematics, lam: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """Small-strain element stiffness ``(E, 3A, 3A)`` N/mm (isotropic)."""
    E, Q, A, _ = kin.grad.shape
    K = np.zeros((E, 3 * A, 3 * A))
    for q in range(Q):
        g = kin.grad[:, q]  # (E, A, 3)
        w = kin.weight[:, q]
        # K_(a,i),(b,k) = w [lam g_ai g_bk + mu (g_ak g_bi + delta_ik g_a.g_b)]
        gg = np.einsum("eaj,ebj->eab", g, g)
        blk = (lam * w)[:, None, None, None, None] * np.einsum("eai,ebk->eaibk", g, g) \
            + (mu * w)[:, None, None, None, None] * (np.einsum("eak,ebi->eaibk", g, g)
                                                    + np.einsum("eab,ik->eaibk", gg, np.eye(3)))
        K += blk.reshape(E, 3 * A, 3 * A)
    return K


def critical_time_step(kin: TetKinematics, lam, mu, density, chunk: int = 4096) -> tuple[float, int, np.ndarray]:
    """Largest stable central-difference step by the element eigenvalue bound.

    Parameters
    ----------
    lam, mu : Lame parameters per element ``(E,)`` or scalars, MPa
    density : per element or scalar, tonne/mm^3

    Returns
    -------
    dt_crit : s — ``2 / omega_max``
    element : index of the element that sets it
    omega : (E,) rad/s — each element's largest frequency
    """
    E = kin.volume.size
    lam = np.broadcast_to(np.asarray(lam, float), (E,))
    mu = np.broadcast_to(np.asarray(mu, float), (E,))
    rho = np.broadcast_to(np.asarray(density, float), (E,))
    frac = np.full(4, 0.25) if kin.order == 1 else HRZ_TET10
    omega = np.empty(E)
    for s in range(0, E, chunk):
        sl = slice(s, min(E, s + chunk))
        sub = TetKinematics(kin.conn[sl], kin.grad[sl], kin.weight[sl], kin.volume[sl], kin.order)
        K = _element_stiffness(sub, lam[sl], mu[sl])
        m = np.repeat(rho[sl, None] * kin.volume[sl, None] * frac, 3, axis=1)  # (e, 3A)
        s_inv = 1.0 / np.sqrt(m)
        Ks = K * s_inv[:, :, None] * s_inv[:, None, :]
        omega[sl] = np.sqrt(np.maximum(np.linalg.eigvalsh(Ks)[:, -1], 0.0))
    worst = int(np.argmax(omega))
    return 2.0 / float(omega[worst]), worst, omega
