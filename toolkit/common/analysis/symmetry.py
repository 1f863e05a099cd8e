"""Mirror symmetry of a node set about a coordinate plane (mm).

A scene that is symmetric about a plane (the phantom face and a ball moving in its
midsagittal plane x = 0) can still answer asymmetrically: a deformable ball pressed into
the face slides to one side or the other, a branch that round-off selects. Comparing two
runs then needs the mirror image of one of them, which :func:`mirror_index` provides.
"""

from __future__ import annotations

import numpy as np

__all__ = ["mirror_index", "mirrored"]


def mirror_index(points: np.ndarray, labels: np.ndarray | None = None, axis: int = 0,
                 tol: float = 1e-6) -> np.ndarray | None:
    """The index of each point's mirror image across the plane ``x[axis] = 0``.

    Parameters
    ----------
    points : (n, 3) mm
    labels : (n,) int, optional; a point's image must carry the same label. This tells
        coincident points apart (the two lips of the phantom's mouth slit share positions)
    axis : the plane's normal (0: x)
    tol : mm, largest distance between a mirrored point and its image

    Returns
    -------
    (n,) int permutation ``j`` with ``points[j[i]]`` the image of ``points[i]`` (an
    involution: ``j[j] = arange(n)``), or None when some point has no image within ``tol``
    or the images are not one-to-one.
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"mirror_index: points have shape {p.shape}; expected (n, 3)")
    labels = np.zeros(len(p)) if labels is None else np.asarray(labels, dtype=np.float64)
    if labels.shape != (len(p),):
        raise ValueError(f"mirror_index: labels have shape {labels.shape}; expected ({len(p)},)")
    # a label separates points by far more than any distance in the set
    spread = 1.0 + 4.0 * float(np.abs(p).max(initial=0.0))
    keyed = np.column_stack([p, labels * spread])
    flip = np.ones(4)
    flip[axis] = -1.0
    distance, index = cKDTree(keyed).query(keyed * flip)
    if distance.max(initial=0.0) > tol or not np.array_equal(index[index], np.arange(len(p))):
        return None
    return index


def mirrored(field: np.ndarray, index: np.ndarray, axis: int = 0) -> np.ndarray:
    """A vector field ``(..., n, 3)`` on the points, mirrored: the value at each point's image
    with its ``axis`` component negated."""
    out = np.asarray(field)[..., index, :].copy()
    out[..., axis] *= -1.0
    return out
