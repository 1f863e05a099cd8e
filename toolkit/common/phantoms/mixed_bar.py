"""A small mixed-element mesh: a prismatic bar meshed with hexahedra, wedges and tetrahedra.

Real face meshes mix cell types; this bar is the smallest mesh that has all three
volume types and the two kinds of conforming interface between them:

- the cross-section is an L: a ``width x height`` rectangle (y, z) with a flange of
  ``width / 2 x flange`` on top of its right half; the bar runs along x over ``length``;
- the left half of the rectangle is ``hex8``, the right half ``wedge6`` (each hexahedron
  cut in two, prism axis along z): hexahedra and wedges meet on quadrilaterals;
- the flange is ``tet4`` (6 Kuhn tetrahedra per cube) standing on the wedges'
  triangles, which are the tetrahedra's own faces there.

Every lateral face has its normal in the y-z plane, so Saint-Venant's pure bending
field is an exact elasticity solution on the bar (see the static tests). Units mm.
"""

from __future__ import annotations

import numpy as np

from toolkit.common.meshes.mesh import Mesh
from toolkit.common.meshes.topology import kuhn_tets, wedges_from_hexes

__all__ = ["mixed_bar"]

_HEX_ORDER = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]


def mixed_bar(n: int = 1, length: float = 40.0, width: float = 10.0, height: float = 10.0, flange: float = 5.0,
              jitter: float = 0.0, seed: int | None = None) -> Mesh:
    """The L-section bar with ``hex8``, ``wedge6`` and ``tet4`` blocks (in that order).

    Parameters
    ----------
    n : cells across each half of the width; the cell size ``h = width / (2 n)`` mm is
        used along every axis (lengths are rounded to whole cells)
    length, width, height, flange : mm — bar length (x), section width (y) and height (z),
        height of the flange on the right half
    jitter : mm — move every node randomly by up to this much (distorted meshes for
        patch tests; keep it below ~0.25 h)
    seed : for ``jitter``

    Returns
    -------
    Mesh with node sets ``end0`` (x = 0) and ``end1`` (x = length), and the element set
    ``upper`` (centroid above mid-height), which spans all three blocks.
    """
    if int(n) != n or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    for name, value in (("length", length), ("width", width), ("height", height), ("flange", flange)):
        if not np.isfinite(value) or value <= 0:
            raise ValueError(f"{name} must be a positive length in mm, got {value!r}")
    h = width / (2 * n)
    nx, nzb, nzf = (max(1, int(round(v / h))) for v in (length, height, flange))
    axes = [np.linspace(0.0, length, nx + 1), np.linspace(0.0, width, 2 * n + 1),
            np.concatenate([np.linspace(0.0, height, nzb + 1), np.linspace(height, height + flange, nzf + 1)[1:]])]
    shape = tuple(a.size for a in axes)
    P = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    ids = np.arange(P.shape[0]).reshape(shape)
    cells = tuple(s - 1 for s in shape)
    corners = np.empty(cells + (2, 2, 2), dtype=np.int64)
    for a in (0, 1):
        for b in (0, 1):
            for d in (0, 1):
                corners[..., a, b, d] = ids[a:cells[0] + a, b:cells[1] + b, d:cells[2] + d]
    _, J, K = np.meshgrid(*[np.arange(c) for c in cells], indexing="ij")
    right, base = J >= n, K < nzb
    hex_c, wedge_c, tet_c = corners[~right & base], corners[right & base], corners[right & ~base]
    blocks = {
        "hex8": np.stack([hex_c[:, i, j, k] for i, j, k in _HEX_ORDER], axis=1),
        "wedge6": wedges_from_hexes(wedge_c, P),
        "tet4": kuhn_tets(tet_c, P),
    }
    used = np.unique(np.concatenate([c.ravel() for c in blocks.values()]))
    renumber = np.full(P.shape[0], -1, dtype=np.int64)
    renumber[used] = np.arange(used.size)
    P = P[used]
    blocks = {t: renumber[c] for t, c in blocks.items()}
    node_sets = {"end0": np.flatnonzero(P[:, 0] == 0.0), "end1": np.flatnonzero(P[:, 0] == length)}
    centroids = np.concatenate([P[c].mean(axis=1) for c in blocks.values()])
    if jitter:
        P = P + np.random.default_rng(seed).uniform(-jitter, jitter, size=P.shape)
    return Mesh(P, blocks, node_sets=node_sets, element_sets={"upper": np.flatnonzero(centroids[:, 2] > height / 2)})
