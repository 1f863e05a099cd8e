"""Tetrahedral elements for explicit dynamics: the face and ball blocks and their critical time step.

The gradients, weights and HRZ lumped mass come from the shared core
(:mod:`toolkit.common.fem.kinematics`):

- ``tet4``: one Gauss point, lumped mass ``rho V / 4``.
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

from dataclasses import replace

import numpy as np

from toolkit.common.fem.assembly import element_tangent
from toolkit.common.fem.kinematics import BlockKinematics, kinematics
from toolkit.common.fem.materials import isotropic_tangent
from toolkit.common.fem.reference import reference_element
from toolkit.common.meshes.mesh import InvertedElementError, Mesh

__all__ = ["tet_kinematics", "critical_time_step"]


def tet_kinematics(mesh: Mesh) -> BlockKinematics:
    """Reference-configuration gradients and weights of the ``tet4``/``tet10`` block of
    ``mesh`` (the shared :func:`~toolkit.common.fem.kinematics.kinematics`: one point for
    tet4, the 4-point rule for tet10, no mean dilatation); raises on inverted elements."""
    ctype = mesh.volume_type
    if ctype not in ("tet4", "tet10"):
        raise ValueError(f"explicit elements are tet4 or tet10, got {ctype!r}")
    kin = kinematics(mesh, mean_dilatation=False).blocks[0]
    bad = np.flatnonzero((kin.weight <= 0).any(axis=1))
    if bad.size:
        raise InvertedElementError(f"{bad.size} {ctype} elements have det J <= 0 at a Gauss point "
                                   f"(first: {bad[:5].tolist()})", bad, kin.weight.min(axis=1)[bad])
    return kin


def _element_stiffness(kin: BlockKinematics, lam, mu) -> np.ndarray:
    """Small-strain element stiffness ``(E, 3A, 3A)`` N/mm of an isotropic material: the shared
    :func:`~toolkit.common.fem.assembly.element_tangent` of the isotropic tensor; ``lam``,
    ``mu`` MPa, scalars or ``(E,)``."""
    E, Q = kin.weight.shape
    lam = np.broadcast_to(np.asarray(lam, float), (E,))
    mu = np.broadcast_to(np.asarray(mu, float), (E,))
    C = np.broadcast_to(isotropic_tangent(lam, mu)[:, None], (E, Q, 3, 3, 3, 3))
    return element_tangent(kin.grad, kin.weight, C)


def critical_time_step(kin: BlockKinematics, lam, mu, density, chunk: int = 4096) -> tuple[float, int, np.ndarray]:
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
    frac = reference_element(kin.ctype).hrz_fractions
    omega = np.empty(E)
    for s in range(0, E, chunk):
        sl = slice(s, min(E, s + chunk))
        sub = replace(kin, conn=kin.conn[sl], grad=kin.grad[sl], weight=kin.weight[sl], volume=kin.volume[sl])
        K = _element_stiffness(sub, lam[sl], mu[sl])
        m = np.repeat(rho[sl, None] * kin.volume[sl, None] * frac, 3, axis=1)  # (e, 3A)
        s_inv = 1.0 / np.sqrt(m)
        Ks = K * s_inv[:, :, None] * s_inv[:, None, :]
        omega[sl] = np.sqrt(np.maximum(np.linalg.eigvalsh(Ks)[:, -1], 0.0))
    worst = int(np.argmax(omega))
    return 2.0 / float(omega[worst]), worst, omega
