"""Material tangents ``dP/dF`` of any material with the update contract.

The contract: ``material.update(F (m, 3, 3), state) -> result`` with ``result.first_piola
(m, 3, 3)`` MPa, the state being that of the last converged step (the update never changes
it). :func:`algorithmic_tangent` differentiates that update, return mapping included, with
respect to ``F``: the tangent that is consistent with the discrete update (what Newton's
method needs for quadratic convergence), for any material, at the cost of nine more updates.
"""

from __future__ import annotations

import numpy as np

__all__ = ["algorithmic_tangent"]


def algorithmic_tangent(material, F: np.ndarray, state, step: float = 1e-7, central: bool = False):
    """The update at ``F`` and its derivative ``dP/dF``.

    Forward differences (``central=False``) have a truncation error of ``step`` times the
    curvature of ``P`` (relative ~1e-7 for a unit-order ``F``) and a round-off error of
    ``eps / step`` (~1e-9); central differences cost nine more updates and are second order.

    Parameters
    ----------
    material : object with ``update(F, state)``
    F : (m, 3, 3) deformation gradients (dimensionless)
    state : the material state the update starts from (unchanged)
    step : perturbation of each component of ``F``

    Returns
    -------
    update : the material's result at ``F`` (stresses, new state)
    A : (m, 3, 3, 3, 3) MPa, ``A[p, i, J, k, L] = dP_iJ / dF_kL`` at point ``p``
    """
    F = np.asarray(F, dtype=np.float64)
    base = material.update(F, state)
    A = np.empty(F.shape[:1] + (3, 3, 3, 3))
    for k in range(3):
        for L in range(3):
            plus = F.copy()
            plus[:, k, L] += step
            P_plus = material.update(plus, state).first_piola
            if central:
                minus = F.copy()
                minus[:, k, L] -= step
                A[:, :, :, k, L] = (P_plus - material.update(minus, state).first_piola) / (2.0 * step)
            else:
                A[:, :, :, k, L] = (P_plus - base.first_piola) / step
    return base, A
