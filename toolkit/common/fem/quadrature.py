"""Quadrature rules on the reference cells, by polynomial order.

A rule of order ``p`` integrates every polynomial of total degree <= ``p`` exactly
(for the tensor-product cells: of degree <= ``p`` in each variable). Reference cells:

- ``line``: [-1, 1]; ``quad``: [-1, 1]^2; ``hex``: [-1, 1]^3 (Gauss-Legendre products);
- ``triangle``: {xi, eta >= 0, xi + eta <= 1}; ``tet``: the unit simplex in 3D;
- ``wedge``: triangle x [-1, 1] (a triangle rule times a Gauss line rule).

The low orders are the classical symmetric rules (centroid; the 3-point triangle rule
at (1/6, 1/6); the 4-point tetrahedron rule at a = (5 - sqrt 5) / 20); higher orders on
simplices are collapsed (Stroud conical) products of Gauss-Jacobi rules, whose weights
are all positive.

Every function returns ``points (Q, dim)`` and ``weights (Q,)`` float64; the weights sum
to the measure of the reference cell (2, 4, 8, 1/2, 1/6, 1).
"""

from __future__ import annotations

from functools import cache

import numpy as np

__all__ = ["gauss_line", "gauss_quad", "gauss_hex", "triangle_rule", "tet_rule", "wedge_rule"]


def _points_per_direction(order: int) -> int:
    """Gauss points that integrate degree ``order`` in one variable exactly."""
    if int(order) != order or order < 0:
        raise ValueError(f"quadrature order must be a non-negative integer, got {order!r}")
    return max(1, int(np.ceil((order + 1) / 2)))


def _frozen(*arrays):
    for a in arrays:
        a.flags.writeable = False
    return arrays


@cache
def gauss_line(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre rule on [-1, 1]: points ``(Q, 1)``, weights ``(Q,)`` (sum 2)."""
    x, w = np.polynomial.legendre.leggauss(_points_per_direction(order))
    return _frozen(x[:, None].copy(), w.copy())


def _tensor(rules) -> tuple[np.ndarray, np.ndarray]:
    """Product of rules (each ``(points (Q_i, d_i), weights (Q_i,))``), first rule slowest."""
    idx = [i.ravel() for i in np.meshgrid(*[np.arange(r[1].size) for r in rules], indexing="ij")]
    points = np.hstack([r[0][i] for r, i in zip(rules, idx)])
    weights = np.prod([r[1][i] for r, i in zip(rules, idx)], axis=0)
    return _frozen(np.ascontiguousarray(points), np.ascontiguousarray(weights))


@cache
def gauss_quad(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss product rule on [-1, 1]^2: points ``(Q, 2)``, weights (sum 4)."""
    return _tensor([gauss_line(order)] * 2)


@cache
def gauss_hex(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss product rule on [-1, 1]^3: points ``(Q, 3)``, weights (sum 8); order 2 is 2x2x2."""
    return _tensor([gauss_line(order)] * 3)


def _jacobi01(n: int, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Jacobi rule for ``int_0^1 (1 - t)^alpha f(t) dt`` with ``n`` points."""
    from scipy.special import roots_jacobi

    x, w = roots_jacobi(n, alpha, 0.0)
    return 0.5 * (1.0 + x), w * 0.5 ** (alpha + 1.0)


@cache
def triangle_rule(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Rule on the unit triangle: points ``(Q, 2)``, weights (sum 1/2).

    Order 1: the centroid; order 2: the 3 points (1/6, 1/6), (2/3, 1/6), (1/6, 2/3);
    higher: a collapsed Gauss-Jacobi product.
    """
    n = _points_per_direction(order)
    if order <= 1:
        return _frozen(np.array([[1.0 / 3.0, 1.0 / 3.0]]), np.array([0.5]))
    if order == 2:
        a, b = 1.0 / 6.0, 2.0 / 3.0
        return _frozen(np.array([[a, a], [b, a], [a, b]]), np.full(3, 1.0 / 6.0))
    u, wu = _jacobi01(n, 0.0)
    v, wv = _jacobi01(n, 1.0)
    U, V = np.meshgrid(u, v, indexing="ij")
    points = np.column_stack([(U * (1.0 - V)).ravel(), V.ravel()])
    return _frozen(points, np.outer(wu, wv).ravel())


@cache
def tet_rule(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Rule on the unit tetrahedron: points ``(Q, 3)``, weights (sum 1/6).

    Order 1: the centroid; order 2: the symmetric 4-point rule (barycentric coordinates
    a = (5 - sqrt 5) / 20 and b = 1 - 3 a); higher: a collapsed Gauss-Jacobi product.
    """
    n = _points_per_direction(order)
    if order <= 1:
        return _frozen(np.full((1, 3), 0.25), np.array([1.0 / 6.0]))
    if order == 2:
        a = (5.0 - np.sqrt(5.0)) / 20.0
        b = 1.0 - 3.0 * a
        points = np.vstack([np.full(3, a), [b, a, a], [a, b, a], [a, a, b]])
        return _frozen(points, np.full(4, 1.0 / 24.0))
    u, wu = _jacobi01(n, 0.0)
    v, wv = _jacobi01(n, 1.0)
    w, ww = _jacobi01(n, 2.0)
    U, V, W = (g.ravel() for g in np.meshgrid(u, v, w, indexing="ij"))
    points = np.column_stack([U * (1.0 - V) * (1.0 - W), V * (1.0 - W), W])
    weights = (wu[:, None, None] * wv[None, :, None] * ww[None, None, :]).ravel()
    return _frozen(points, weights)


@cache
def wedge_rule(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Rule on the reference wedge (triangle x [-1, 1]): points ``(Q, 3)``, weights (sum 1).

    Order 2 is the 3-point triangle rule times the 2-point Gauss rule (6 points).
    """
    return _tensor([triangle_rule(order), gauss_line(order)])
