"""Split-conformal calibration of a surrogate's error estimate.

A surrogate gives, with each prediction, a *scale* ``s > 0`` (mm) that grows with its expected
error (a constant, the spread of an ensemble, a residual norm, ...). On ``n`` calibration cases,
kept apart from training by whole simulation, the ratios ``r_i = e_i / s_i`` of the true error
``e_i`` to the scale are sorted, and the factor ``q`` is the ``k``-th smallest with
``k = ceil((n + 1) c)``. For a new case exchangeable with the calibration ones, the bound
``q s`` covers its error with probability at least ``c``, and (ratios without ties) at most
``c + 1 / (n + 1)`` (Vovk et al. 2005; Angelopoulos and Bates 2021, section 1.1, appendix D):
:func:`coverage_interval`. The guarantee is marginal, over calibration sets and new cases; for
inputs unlike the calibration cases it does not hold, which is what the out-of-distribution
check beside it is for.

``k <= n`` needs ``n >= c / (1 - c)`` cases (9 for 90 %, 19 for 95 %); fewer is refused.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolkit.common.meshes.io import atomic_path
from toolkit.common.training.bundle import CALIBRATION_FILES, ModelBundle

__all__ = ["ConformalBound", "calibrate", "conformal_rank", "coverage_interval", "min_calibration_cases",
           "save_calibration", "load_calibration", "CALIBRATION_FILES"]


def min_calibration_cases(coverage: float) -> int:
    """Fewest calibration cases for which a finite bound at ``coverage`` exists."""
    _check_coverage(coverage)
    return math.ceil(coverage / (1.0 - coverage) - 1e-12)


def conformal_rank(n: int, coverage: float) -> int:
    """``k = ceil((n + 1) coverage)``: the rank (1-based) of the sorted calibration ratio used as
    the factor. Raises ValueError when ``k > n`` (too few cases for that coverage)."""
    _check_coverage(coverage)
    k = math.ceil((n + 1) * coverage - 1e-12)
    if k > n:
        raise ValueError(f"{n} calibration case(s) cannot give a bound at {coverage:.0%} coverage: it needs at least "
                         f"{min_calibration_cases(coverage)}; calibrate on more held-out simulations or ask a lower "
                         "coverage")
    return k


def coverage_interval(n: int, coverage: float) -> tuple[float, float]:
    """``(coverage, k / (n + 1))``: the guaranteed lower bound of the calibrated bound's marginal
    coverage with ``n`` cases, and its exact expectation when the ratios have no ties (which
    is below ``coverage + 1 / (n + 1)``)."""
    k = conformal_rank(n, coverage)
    return float(coverage), k / (n + 1)


def _check_coverage(coverage: float) -> None:
    if not (isinstance(coverage, (int, float)) and 0.0 < coverage < 1.0):
        raise ValueError(f"coverage = {coverage!r}; expected a probability in (0, 1), e.g. 0.9")


@dataclass(frozen=True)
class ConformalBound:
    """A calibrated error bound ``factor * scale``.

    coverage : the probability the bound holds for a new exchangeable case
    factor : ``q``, dimensionless (the ``k``-th smallest calibration ratio)
    ratios : (n,) sorted calibration ratios ``error / scale`` (kept, so another coverage can be
        asked of the same calibration with :meth:`at`)
    """

    coverage: float
    factor: float
    ratios: tuple[float, ...]

    @property
    def n(self) -> int:
        return len(self.ratios)

    def at(self, coverage: float) -> ConformalBound:
        """The same calibration at another coverage."""
        k = conformal_rank(self.n, coverage)
        return ConformalBound(float(coverage), float(self.ratios[k - 1]), self.ratios)

    def bound(self, scale):
        """``factor * scale`` (same shape and unit as ``scale``)."""
        return self.factor * np.asarray(scale, dtype=np.float64)

    def expected_coverage(self) -> float:
        """``k / (n + 1)``, the coverage expected of this bound (at least :attr:`coverage`)."""
        return coverage_interval(self.n, self.coverage)[1]

    def to_dict(self) -> dict:
        return {"coverage": self.coverage, "factor": self.factor, "ratios": list(self.ratios)}

    @classmethod
    def from_dict(cls, d: dict) -> ConformalBound:
        return cls(float(d["coverage"]), float(d["factor"]), tuple(float(r) for r in d["ratios"]))


def calibrate(errors, scales, coverage: float = 0.9) -> ConformalBound:
    """Calibrate ``factor * scale`` to bound ``error`` with probability ``coverage``.

    Parameters
    ----------
    errors : (n,) true errors of the calibration cases (mm, >= 0)
    scales : (n,) the estimate's scale for the same cases (mm, > 0)
    coverage : in (0, 1)

    Raises ValueError for mismatched or non-finite input, a non-positive scale, or fewer cases
    than :func:`min_calibration_cases`.
    """
    e = np.asarray(errors, dtype=np.float64).ravel()
    s = np.asarray(scales, dtype=np.float64).ravel()
    if e.shape != s.shape:
        raise ValueError(f"errors {e.shape} and scales {s.shape} must have one value per calibration case")
    if not (np.isfinite(e).all() and np.isfinite(s).all()):
        raise ValueError("errors and scales must be finite")
    if (e < 0).any():
        raise ValueError("errors must be >= 0 (a norm of the prediction's error)")
    if (s <= 0).any():
        raise ValueError(f"scales must be > 0; {int((s <= 0).sum())} of {s.size} are not")
    ratios = np.sort(e / s)
    k = conformal_rank(ratios.size, coverage)
    return ConformalBound(float(coverage), float(ratios[k - 1]), tuple(ratios.tolist()))


def save_calibration(directory, meta: dict, arrays: dict):
    """Write ``arrays`` (name -> ndarray) to ``calibration.npz`` and ``meta`` (JSON-ready) to
    ``calibration.json`` in the model directory ``directory``, each atomically, the JSON last, with
    the fingerprint of the model's weights (``model_sha1``, read back by :func:`load_calibration`);
    returns the directory."""

    directory = Path(directory)
    meta = {**meta, "model_sha1": ModelBundle.weights_sha1(directory)}
    with atomic_path(directory / CALIBRATION_FILES[1]) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    with atomic_path(directory / CALIBRATION_FILES[0]) as tmp:
        tmp.write_text(json.dumps(meta, indent=2))
    return directory


def load_calibration(directory, command: str) -> tuple[dict, dict]:
    """``(meta, arrays)`` of the calibration saved in the model directory ``directory``;
    FileNotFoundError naming ``command`` (the one that makes a calibration, e.g. ``toolkit static
    calibrate``) when absent, ValueError naming it when the calibration was made for other weights
    (a calibration copied from another model, or one that training replaced)."""
    directory = Path(directory)
    if not all((directory / name).is_file() for name in CALIBRATION_FILES):
        raise FileNotFoundError(f"{directory} holds no calibration ({', '.join(CALIBRATION_FILES)}): make one with "
                                f"`{command} --model {directory} --data DB.h5`")
    meta = json.loads((directory / CALIBRATION_FILES[0]).read_text())
    made_for, weights = meta.get("model_sha1"), ModelBundle.weights_sha1(directory)
    if made_for != weights:
        raise ValueError(f"{directory / CALIBRATION_FILES[0]} was made for another model (weights {made_for}, this "
                         f"directory's model.pt is {weights}): calibrate this model again: "
                         f"`{command} --model {directory} --data DB.h5`")
    with np.load(directory / CALIBRATION_FILES[1]) as z:
        arrays = {k: z[k] for k in z.files}
    return meta, arrays
