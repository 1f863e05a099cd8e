"""The isoparametric map of a block of cells: physical gradients and integration weights.

For cells with node coordinates ``x (E, A, 3)`` and the reference element's gradients
``dN/dxi (Q, A, 3)`` at the quadrature points, the Jacobian is
``J = dx/dxi = sum_a x_a (dN_a/dxi)``, the physical gradients ``dN/dx = dN/dxi J^-1``
and the integration weights ``w_q det J``. The inverse is the adjugate over the
determinant, so a flat cell gives non-finite gradients and a zero weight rather than
an exception; inverted cells get negative weights (callers decide what to do).
"""

from __future__ import annotations

import numpy as np

from toolkit.common.fem.reference import reference_element

__all__ = ["shape_gradients"]


def shape_gradients(ctype: str, x: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Physical shape-function gradients and weights of a block of volume cells.

    Parameters
    ----------
    ctype : volume cell type (``hex8``, ``wedge6``, ``tet4``, ``tet10``)
    x : (E, A, 3) float, mm — node coordinates of the cells, in the reference node order
    order : quadrature order (see :meth:`~toolkit.common.fem.ReferenceElement.quadrature`)

    Returns
    -------
    grad : (E, Q, A, 3) float, 1/mm — ``dN_a/dx_j`` at the quadrature points
    weight : (E, Q) float, mm^3 — quadrature weight times ``det J`` (negative if inverted)
    """
    ref = reference_element(ctype)
    if ref.dim != 3:
        raise ValueError(f"shape_gradients maps volume cells; {ctype!r} has a {ref.dim}-D reference cell")
    x = np.asarray(x, dtype=float)
    if x.ndim != 3 or x.shape[1:] != (ref.n_nodes, 3):
        raise ValueError(f"{ctype} node coordinates have shape {x.shape}, expected (E, {ref.n_nodes}, 3)")
    xi, w = ref.quadrature(order)
    dN = ref.gradient(xi)  # (Q, A, 3)
    J = np.einsum("eai,qak->eqik", x, dN)  # dx_i / dxi_k
    a, b, c = J[..., 0], J[..., 1], J[..., 2]  # the columns dx/dxi_k
    det = np.einsum("...i,...i->...", a, np.cross(b, c))
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.stack([np.cross(b, c), np.cross(c, a), np.cross(a, b)], axis=-2) / det[..., None, None]
    grad = np.einsum("qak,eqkj->eqaj", dN, inv)
    return np.ascontiguousarray(grad), det * w
