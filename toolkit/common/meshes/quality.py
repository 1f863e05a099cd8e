"""Element quality: the scaled Jacobian, and the check that refuses bad elements.

Definitions (Verdict-style, 1 for the ideal element, <= 0 for inverted ones):

- ``hex8``: the minimum over the 8 corners of the determinant of the three unit
  edge vectors leaving the corner (right-handed in VTK order).
- ``wedge6``: the minimum over the 6 corners of the determinant of the three unit
  edge vectors leaving the corner (two along its triangle, one along the prism edge,
  right-handed in the Abaqus C3D6 order), times ``2 / sqrt(3)`` so that the right
  prism on an equilateral triangle scores 1 (its corner value is sin 60 degrees).
- ``tet4``: ``sqrt(2) * det[e1, e2, e3] / max over corners of the product of the
  three edge lengths at that corner`` (1 for a regular tetrahedron).
- ``tet10``: the corner tetrahedron's scaled Jacobian times the smallest ratio of
  the quadratic map's Jacobian determinant (sampled at the 10 nodes and the 4
  Gauss points) to that of the straight-sided tetrahedron; equal to the ``tet4``
  value for straight edges, <= 0 once curved edges fold the element.

The corner edge tables are the reference records' ``corner_frames``
(:mod:`toolkit.common.fem.reference`).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from toolkit.common.errors import DegenerateElementError, InvertedElementError, MeshError
from toolkit.common.fem.reference import REFERENCE_ELEMENTS

__all__ = ["scaled_jacobian", "check_elements", "check_blocks", "tet10_shape_gradients", "TET10_SAMPLE_GRADIENTS"]

_HEX_CORNER_EDGES = REFERENCE_ELEMENTS["hex8"].corner_frames
_WEDGE_CORNER_EDGES = REFERENCE_ELEMENTS["wedge6"].corner_frames
_TET_CORNER_EDGES = REFERENCE_ELEMENTS["tet4"].corner_frames
#: corner value of the ideal wedge (right prism on an equilateral triangle): sin 60 degrees
_WEDGE_IDEAL = np.sqrt(3.0) / 2.0


def _det3(a: np.ndarray) -> np.ndarray:
    """Determinant of ``(..., 3, 3)`` arrays whose rows are vectors."""
    return np.einsum("...i,...i->...", np.cross(a[..., 0, :], a[..., 1, :]), a[..., 2, :])


def _corner_sj(x: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Minimum over corners of det of the unit edge vectors, ``(n,)``; 0 for zero-length edges."""
    e = x[:, frames, :] - x[:, :frames.shape[0], None, :]  # (n, corners, 3, 3)
    norm = np.linalg.norm(e, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = _det3(e / norm)
    return np.nan_to_num(d, nan=0.0).min(axis=1)


def _hex_sj(x: np.ndarray) -> np.ndarray:
    return _corner_sj(x, _HEX_CORNER_EDGES)


def _wedge_sj(x: np.ndarray) -> np.ndarray:
    return _corner_sj(x, _WEDGE_CORNER_EDGES) / _WEDGE_IDEAL


def _tet_sj(x: np.ndarray) -> np.ndarray:
    e = x[:, _TET_CORNER_EDGES, :] - x[:, :4, None, :]  # (n, 4, 3, 3)
    lengths = np.linalg.norm(e, axis=-1).prod(axis=-1).max(axis=-1)
    det = _det3(x[:, None, 1:4, :] - x[:, None, :1, :])[:, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        sj = np.sqrt(2.0) * det / lengths
    return np.nan_to_num(sj, nan=0.0)


def tet10_shape_gradients(xi: np.ndarray) -> np.ndarray:
    """Gradients of the 10 quadratic tetrahedron shape functions.

    The ``tet10`` reference record's :meth:`~toolkit.common.fem.ReferenceElement.gradient`.

    Parameters
    ----------
    xi : (n_samples, 3) reference coordinates

    Returns
    -------
    (n_samples, 10, 3) ``dN_a / dxi_k``
    """
    return REFERENCE_ELEMENTS["tet10"].gradient(xi)


_TET10_SAMPLES = np.vstack(
    [
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
        [[0.5, 0, 0], [0.5, 0.5, 0], [0, 0.5, 0], [0, 0, 0.5], [0.5, 0, 0.5], [0, 0.5, 0.5]],
        np.full((4, 3), 0.1381966011250105) + np.vstack([np.zeros(3), 0.4472135954999579 * np.eye(3)]),
    ]
)


#: (14, 3, 10) transposed shape gradients of tet10 at the points where its quality samples the
#: Jacobian (the 10 nodes and the 4 Gauss points): ``dN_a / dxi_k`` at ``[s, k, a]``
TET10_SAMPLE_GRADIENTS = np.ascontiguousarray(tet10_shape_gradients(_TET10_SAMPLES).transpose(0, 2, 1))


def _tet10_sj(x: np.ndarray) -> np.ndarray:
    jac_t = np.matmul(TET10_SAMPLE_GRADIENTS[None], x[:, None])  # (n, s, 3, 3): row k is dx/dxi_k
    det = _det3(jac_t)
    det_lin = _det3(x[:, 1:4, :] - x[:, :1, :])
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = det.min(axis=1) / det_lin
    sj = _tet_sj(x[:, :4])
    # for an inverted corner tet the ratio is positive but the element is bad
    return np.where(sj > 0, sj * np.minimum(1.0, np.nan_to_num(ratio, nan=0.0)), sj)


_SCALED_JACOBIAN = {"hex8": _hex_sj, "wedge6": _wedge_sj, "tet4": _tet_sj, "tet10": _tet10_sj}


def scaled_jacobian(ctype: str, x: np.ndarray) -> np.ndarray:
    """Scaled Jacobian per element.

    Parameters
    ----------
    ctype : ``hex8``, ``wedge6``, ``tet4`` or ``tet10``
    x : (n_elements, nodes_per_cell, 3) float, mm — element node coordinates

    Returns
    -------
    (n_elements,) float, dimensionless in [-1, 1]
    """
    fn = _SCALED_JACOBIAN.get(ctype)
    if fn is None:
        raise MeshError(f"scaled Jacobian of cell type {ctype!r} is not defined;"
                        f" expected one of {list(_SCALED_JACOBIAN)}")
    x = np.asarray(x, dtype=float)
    n = REFERENCE_ELEMENTS[ctype].n_nodes
    if x.ndim != 3 or x.shape[1:] != (n, 3):
        raise MeshError(f"{ctype} node coordinates have shape {x.shape}, expected (n_elements, {n}, 3)")
    return fn(x)


def check_elements(ctype: str, x: np.ndarray, min_scaled_jacobian: float = 1e-3, offset: int = 0) -> np.ndarray:
    """Raise if an element of one block is inverted or degenerate, else return the scaled Jacobians.

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
    _raise_if_bad(sj, offset + np.arange(sj.size), x.mean(axis=1) if sj.size else np.zeros((0, 3)), ctype,
                  min_scaled_jacobian)
    return sj


def check_blocks(points: np.ndarray, blocks: Iterable, min_scaled_jacobian: float = 1e-3) -> np.ndarray:
    """:func:`check_elements` over several cell blocks at once (a mixed mesh).

    Parameters
    ----------
    points : (n_points, 3) float, mm
    blocks : :class:`~toolkit.common.meshes.mesh.CellBlock` s (``ctype``, ``cells``, ``offset``)
    min_scaled_jacobian : elements below this (but > 0) are degenerate

    Returns
    -------
    (n_elements,) scaled Jacobians of the blocks, concatenated in block order

    Raises
    ------
    InvertedElementError, DegenerateElementError — naming the worst elements of all
    blocks by global index, with their types
    """
    blocks = list(blocks)
    sj, ids, centres, types = [], [], [], []
    for b in blocks:
        x = points[b.cells]
        sj.append(scaled_jacobian(b.ctype, x))
        ids.append(b.offset + np.arange(b.cells.shape[0]))
        centres.append(x.mean(axis=1))
        types.append(np.full(b.cells.shape[0], b.ctype, dtype=object))
    if not blocks:
        return np.zeros(0)
    sj_all = np.concatenate(sj)
    _raise_if_bad(sj_all, np.concatenate(ids), np.concatenate(centres), np.concatenate(types), min_scaled_jacobian)
    return sj_all


def _raise_if_bad(sj, ids, centres, types, min_scaled_jacobian) -> None:
    """Raise for elements with ``sj <= 0`` (inverted) or ``< min_scaled_jacobian`` (degenerate)."""
    distinct = [types] if isinstance(types, str) else list(dict.fromkeys(types.tolist()))
    label = "/".join(distinct)
    for bad, kind, exc, hint in (
        (sj <= 0.0, "inverted (scaled Jacobian <= 0)", InvertedElementError,
         "check the node ordering (VTK/Abaqus convention) or the geometry that folded"),
        (sj < min_scaled_jacobian, f"degenerate (scaled Jacobian < {min_scaled_jacobian:g})", DegenerateElementError,
         "the elements are nearly flat: remesh or relax the shape parameters"),
    ):
        if bad.any():
            k = np.flatnonzero(bad)
            k = k[np.argsort(sj[k], kind="stable")]
            worst = k[0]
            what = f"{types[worst]} " if len(distinct) > 1 else ""
            raise exc(
                f"{k.size} of {sj.size} {label} elements are {kind}; worst: {what}element {ids[worst]}"
                f" (scaled Jacobian {sj[worst]:.3g}, centroid {np.round(centres[worst], 2).tolist()} mm);"
                f" first: {ids[k[:5]].tolist()}. Suggestion: {hint}.",
                ids[k],
                sj[k],
            )
