"""Input validation shared by the metric modules (shapes, NaN, index ranges)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np


def _as_float(x, name: str) -> np.ndarray:
    """Return ``x`` as a float64 array, raising if it holds NaN or inf."""
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} could not be converted to a float array: {exc}") from exc
    if not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a))
        raise ValueError(
            f"{name} has {len(bad)} non-finite entries (NaN or inf), first at index "
            f"{tuple(int(i) for i in bad[0])}; expected finite values"
        )
    return a


def _as_points(x, name: str, dim: int = 3) -> np.ndarray:
    """Return ``x`` as a finite ``(n, dim)`` float64 array with n >= 1."""
    a = _as_float(x, name)
    if a.ndim != 2 or a.shape[1] != dim or a.shape[0] == 0:
        raise ValueError(f"{name} has shape {a.shape}, expected (n, {dim}) with n >= 1")
    return a


def _as_pair(pred, true, *, allowed_ndim: tuple[int, ...] | None = None, last: int = 3):
    """Validate a (pred, true) pair of equal, non-empty shape; optionally (n, last) or
    (b, n, last)."""
    a = _as_float(pred, "pred")
    b = _as_float(true, "true")
    if a.shape != b.shape:
        raise ValueError(f"pred has shape {a.shape}, expected the shape of true {b.shape}")
    if a.size == 0:
        raise ValueError(f"pred and true are empty (shape {a.shape}); expected at least one entry")
    if allowed_ndim is not None and (a.ndim not in allowed_ndim or a.shape[-1] != last):
        want = " or ".join({2: f"(n, {last})", 3: f"(b, n, {last})"}[d] for d in allowed_ndim)
        raise ValueError(f"pred has shape {a.shape}, expected {want}")
    return a, b


def _as_triangles(t, n_points: int, name: str) -> np.ndarray:
    """Return ``t`` as an int64 ``(m, 3)`` array of indices in ``[0, n_points)``."""
    a = np.asarray(t)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
        raise ValueError(f"{name} has shape {a.shape}, expected (m, 3) with m >= 1")
    if not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{name} has dtype {a.dtype}, expected an integer dtype (int64 indices)")
    a = a.astype(np.int64)
    if a.min() < 0 or a.max() >= n_points:
        raise ValueError(
            f"{name} holds indices in [{a.min()}, {a.max()}], expected [0, {n_points - 1}] "
            f"for {n_points} points"
        )
    return a


def _region_indices(regions: Mapping | None, n: int, what: str) -> dict[str, np.ndarray]:
    """Validate a name -> index-array (or boolean mask) mapping against ``n`` items."""
    out: dict[str, np.ndarray] = {}
    if regions is None:
        return out
    for name, idx in regions.items():
        if name == "all":
            raise ValueError("region name 'all' is reserved for the whole set; rename the region")
        a = np.asarray(idx)
        if a.dtype == bool:
            if a.shape != (n,):
                raise ValueError(
                    f"region {name!r} is a boolean mask of shape {a.shape}, expected ({n},)"
                )
            a = np.flatnonzero(a)
        else:
            if a.ndim != 1 or not np.issubdtype(a.dtype, np.integer):
                raise ValueError(
                    f"region {name!r} has shape {a.shape} and dtype {a.dtype}, expected a 1-D "
                    f"int64 array of {what} indices"
                )
            a = a.astype(np.int64)
        if a.size == 0:
            raise ValueError(f"region {name!r} is empty; expected at least one {what} index")
        if a.min() < 0 or a.max() >= n:
            raise ValueError(
                f"region {name!r} holds indices in [{a.min()}, {a.max()}], expected "
                f"[0, {n - 1}] for {n} {what}s"
            )
        out[str(name)] = a
    return out
