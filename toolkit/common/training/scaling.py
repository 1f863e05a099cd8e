"""Min-max scaling of features to [0, 1] (the PointNet++ paper scales its inputs so), saved with a model.

A :class:`MinMaxScaler` holds one ``(lo, hi)`` pair per feature (the last axis); a
constant feature (``hi == lo``) maps to 0 and back to its value. It round-trips
through JSON exactly (Python writes floats with ``repr``), so a saved model rescales
bit-for-bit as it did in training. Works on numpy arrays and torch tensors alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MinMaxScaler"]


@dataclass(frozen=True, eq=False)
class MinMaxScaler:
    """Per-feature affine map ``(x - lo) / (hi - lo)`` onto [0, 1].

    Attributes
    ----------
    lo, hi : (n_features,) float64, in the unit of each feature; ``hi >= lo``
    names : optional feature names (say units in them, e.g. ``"velocity_mm_s"``)
    """

    lo: np.ndarray
    hi: np.ndarray
    names: tuple[str, ...] | None = None

    def __post_init__(self):
        lo = np.array(self.lo, dtype=np.float64, ndmin=1)
        hi = np.array(self.hi, dtype=np.float64, ndmin=1)
        if lo.ndim != 1 or lo.shape != hi.shape:
            raise ValueError(f"MinMaxScaler: lo {lo.shape} and hi {hi.shape} must be equal-length 1-D arrays")
        bad = np.flatnonzero(~(np.isfinite(lo) & np.isfinite(hi)) | (hi < lo))
        if bad.size:
            i = bad[0]
            raise ValueError(f"MinMaxScaler: feature {i} has lo={lo[i]!r}, hi={hi[i]!r}; expected finite lo <= hi")
        names = None if self.names is None else tuple(str(n) for n in self.names)
        if names is not None and len(names) != lo.size:
            raise ValueError(f"MinMaxScaler: {len(names)} names for {lo.size} features")
        lo.flags.writeable = hi.flags.writeable = False
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)
        object.__setattr__(self, "names", names)

    @property
    def n_features(self) -> int:
        return int(self.lo.size)

    @property
    def span(self) -> np.ndarray:
        """``hi - lo``, with 1 for constant features (they map to 0)."""
        s = self.hi - self.lo
        return np.where(s > 0, s, 1.0)

    @classmethod
    def fit(cls, x, names=None) -> MinMaxScaler:
        """Fit on ``x`` of shape ``(..., n_features)``: the minimum and maximum over all other axes."""
        a = np.asarray(x, dtype=np.float64)
        if a.ndim == 0 or a.size == 0:
            raise ValueError(f"MinMaxScaler.fit needs a non-empty (..., n_features) array, got shape {a.shape}")
        flat = a.reshape(-1, a.shape[-1])
        if not np.isfinite(flat).all():
            col = int(np.flatnonzero(~np.isfinite(flat).all(axis=0))[0])
            raise ValueError(f"MinMaxScaler.fit: feature {col} has non-finite values")
        return cls(flat.min(axis=0), flat.max(axis=0), names)

    def _params(self, x):
        if self._is_torch(x):
            import torch

            return (torch.tensor(self.lo, dtype=x.dtype, device=x.device),
                    torch.tensor(self.span, dtype=x.dtype, device=x.device))
        return self.lo, self.span

    @staticmethod
    def _is_torch(x) -> bool:
        return type(x).__module__.startswith("torch")

    def _check(self, x):
        if x.shape[-1] != self.n_features:
            raise ValueError(f"scaler was fitted on {self.n_features} features"
                             f"{' ' + str(list(self.names)) if self.names else ''}, got an array with "
                             f"{x.shape[-1]} on its last axis (shape {tuple(x.shape)})")

    def transform(self, x):
        """``(x - lo) / span``; same shape and (for tensors) dtype/device as ``x``."""
        x = x if self._is_torch(x) else np.asarray(x, dtype=np.float64)
        self._check(x)
        lo, span = self._params(x)
        return (x - lo) / span

    def inverse(self, y):
        """Back to the original units: ``y * span + lo``."""
        y = y if self._is_torch(y) else np.asarray(y, dtype=np.float64)
        self._check(y)
        lo, span = self._params(y)
        return y * span + lo

    def to_dict(self) -> dict:
        """JSON-ready: ``{"lo": [...], "hi": [...], "names": [...] or None}``."""
        return {"lo": self.lo.tolist(), "hi": self.hi.tolist(),
                "names": None if self.names is None else list(self.names)}

    @classmethod
    def from_dict(cls, d: dict) -> MinMaxScaler:
        missing = {"lo", "hi"} - set(d)
        if missing:
            raise ValueError(f"scaler record lacks {sorted(missing)}; expected keys lo, hi (and names)")
        return cls(d["lo"], d["hi"], d.get("names"))

    def __eq__(self, other) -> bool:
        if not isinstance(other, MinMaxScaler):
            return NotImplemented
        return np.array_equal(self.lo, other.lo) and np.array_equal(self.hi, other.hi) and self.names == other.names

    __hash__ = None
