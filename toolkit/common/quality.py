"""Element quality: the scaled Jacobian, and the check that refuses bad elements.

Definitions (Verdict-style, 1 for the ideal element, <= 0 for inverted ones):

- ``hex8``: the minimum over the 8 corners of the determinant of the three unit
  edge vectors leaving the corner (right-handed in VTK order).
- ``tet4``: ``sqrt(2) * det[e1, e2, e3] / max over corners of the product of the
  three edge lengths at that corner`` (1 for a regular tetrahedron).
- ``tet10``: the corner tetrahedron's scaled Jacobian times the smallest ratio of
  the quadratic map's Jacobian determinant (sampled at the 10 nodes and the 4
  Gauss points) to that of the straight-sided tetrahedron; equal to the ``tet4``
  value for straight edges, <= 0 once curved edges fold the element.
"""

from __future__ import annotations

import numpy as np

from toolkit.common.mesh import DegenerateElementError, InvertedElementError, MeshError

__all__ = ["scaled_jacobian", "check_elements", "tet10_shape_gradients"]

_HEX_CORNER_EDGES = np.array(
    [[1, 3, 4], [2, 0, 5], [3, 1, 6], [0, 2, 7], [7, 5, 0], [4, 6, 1], [5, 7, 2], [6, 4, 3]]
)
_TET_CORNER_EDGES = np.array([[1, 2, 3], [2, 0, 3], [0, 1, 3], [1, 0, 2]])


def _det3(a: np.ndarray) -> np.ndarray:
    """Determinant of ``(..., 3, 3)`` arrays whose rows are vectors."""
    return np.einsum("...i,...i->...", np.cross(a[..., 0, :], a[..., 1, :]), a[..., 2, :])


def _hex_sj(x: np.ndarray) -> np.ndarray:
    e = x[:, _HEX_CORNER_EDGES, :] - x[:, :, None, :]  # (n, 8, 3, 3)
    norm = np.linalg.norm(e, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = _det3(e / norm)
    return np.nan_to_num(d, nan=0.0).min(axis=1)


def _tet_sj(x: np.ndarray) -> np.ndarray:
    e = x[:, _TET_CORNER_EDGES, :] - x[:, :4, None, :]  # (n, 4, 3, 3)
    lengths = np.linalg.norm(e, axis=-1).prod(axis=-1).max(axis=-1)
    det = _det3(x[:, None, 1:4, :] - x[:, None, :1, :])[:, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        sj = np.sqrt(2.0) * det / lengths
    return np.nan_to_num(sj, nan=0.0)


def tet10_shape_gradients(xi: np.ndarray) -> np.ndarray:
    """Gradients of the 10 quadratic tetrahedron shape functions.

    Parameters
    ----------
    xi : (n_samples, 3) reference coordinates

    Returns
    -------
    (n_samples, 10, 3) ``dN_a / dxi_k``
    """
    xi = np.atleast_2d(xi)
    L = np.column_stack([1.0 - xi.sum(axis=1), xi])  # barycentric (n, 4)
    dL = np.array([[-1.0, -1.0, -1.0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])  # (4, 3)
    g = np.empty((xi.shape[0], 10, 3))
    g[:, :4, :] = (4.0 * L - 1.0)[:, :, None] * dL[None]
    from toolkit.common.topology import TET_EDGES

    i, j = TET_EDGES[:, 0], TET_EDGES[:, 1]
    g[:, 4:, :] = 4.0 * (L[:, i, None] * dL[None, j] + L[:, j, None] * dL[None, i])
    return g


_TET10_SAMPLES = np.vstack(
    [
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
        [[0.5, 0, 0], [0.5, 0.5, 0], [0, 0.5, 0], [0, 0, 0.5], [0.5, 0, 0.5], [0, 0.5, 0.5]],
        np.full((4, 3), 0.1381966011250105) + np.vstack([np.zeros(3), 0.4472135954999579 * np.eye(3)]),
    ]
)


def _tet10_sj(x: np.ndarray) -> np.ndarray:
    g = tet10_shape_gradients(_TET10_SAMPLES)  # (s, 10, 3)
    jac = np.einsum("nai,sak->nsik", x, g)  # dx_i/dxi_k
    det = np.linalg.det(jac)
    det_lin = _det3(x[:, 1:4, :] - x[:, :1, :])
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = det.min(axis=1) / det_lin
    sj = _tet_sj(x[:, :4])
    # for an inverted corner tet the ratio is positive but the element is bad
    return np.where(sj > 0, sj * np.minimum(1.0, np.nan_to_num(ratio, nan=0.0)), sj)


def scaled_jacobian(ctype: str, x: np.ndarray) -> np.ndarray:
    """Scaled Jacobian per element.

    Parameters
    ----------
    ctype : ``hex8``, ``tet4`` or ``tet10``
    x : (n_elements, nodes_per_cell, 3) float, mm — element node coordinates

    Returns
    -------
    (n_elements,) float, dimensionless in [-1, 1]
    """
    fn = {"hex8": _hex_sj, "tet4": _tet_sj, "tet10": _tet10_sj}.get(ctype)
    if fn is None:
        raise MeshError(f"scaled Jacobian of cell type {ctype!r} is not defined; expected hex8, tet4 or tet10")
    return fn(np.asarray(x, dtype=float))


def check_elements(ctype: str, x: np.ndarray, min_scaled_jacobian: float = 1e-3, offset: int = 0) -> np.ndarray:
    """Raise if an element is inverted or degenerate, else return the scaled Jacobians.

    Parameters
    ----------
    ctype : cell type
    x : (n_elements, nodes_per_cell, 3) float, mm
    min_scaled_jacobian : elements below this (but > 0) are degenerate
    offset : added to element indices in messages (global numbering)

    Raises
    ------
    InvertedElementError, DegenerateElementError
    """
    sj = scaled_jacobian(ctype, x)
    for bad, kind, exc, hint in (
        (sj <= 0.0, "inverted (scaled Jacobian <= 0)", InvertedElementError,
         "check the node ordering (VTK/Abaqus convention) or the geometry that folded"),
        (sj < min_scaled_jacobian, f"degenerate (scaled Jacobian < {min_scaled_jacobian:g})", DegenerateElementError,
         "the elements are nearly flat: remesh or relax the shape parameters"),
    ):
        if bad.any():
            ids = np.flatnonzero(bad)
            ids = ids[np.argsort(sj[ids])]
            worst = ids[0]
            centre = x[worst].mean(axis=0)
            raise exc(
                f"{ids.size} of {sj.size} {ctype} elements are {kind}; worst: element {worst + offset}"
                f" (scaled Jacobian {sj[worst]:.3g}, centroid {np.round(centre, 2).tolist()} mm);"
                f" first: {(ids[:5] + offset).tolist()}. Suggestion: {hint}.",
                ids + offset,
                sj[ids],
            )
    return sj
