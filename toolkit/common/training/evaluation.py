"""What scoring a surrogate returns, in both workflows (``evaluate_surrogate`` of
:mod:`toolkit.static.surrogate` and :mod:`toolkit.impact.evaluation`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Evaluation"]


@dataclass(frozen=True, eq=False)
class Evaluation:
    """A surrogate scored against the FE on samples it did not train on.

    Attributes
    ----------
    metrics : dict of the ``metrics.json`` keys (mm, MPa, s, ms; each workflow's documents them)
    items : (I,) int, what was scored: static, the database's sample rows (one per simulation
        increment); impact, item indices (simulation-major: ``item = sim * N + node``)
    predicted, truth : float64, same shape: static ``(I, n, 3)`` nodal displacements, mm;
        impact ``(I, F, 4)`` per frame ux, uy, uz (mm) and von Mises stress (MPa)
    per_sample : static, a DataFrame with one row per scored sample (key, subject, increment,
        errors in mm); impact, None
    """

    metrics: dict
    items: np.ndarray
    predicted: np.ndarray
    truth: np.ndarray
    per_sample: Any = None
