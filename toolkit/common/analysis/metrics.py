"""Accuracy metrics for facial soft-tissue predictions.

Everything is in millimetres. Points are ``(n_points, 3)`` float64 arrays with axes
x lateral (midline plane x = 0), y anterior, z superior; node and vertex index arrays
are int64.

Contents
--------
Nodal errors (the PointNet++ and impact papers)
    :func:`nodal_errors`, :func:`mean_euclidean_error`, :func:`rmse`, :func:`nrmse`,
    :func:`pearson`, :func:`region_errors`.
Paired comparison of error distributions (the PointNet++ paper's explicit vs implicit ablation)
    :func:`wilcoxon_paired` -> :class:`PairedComparison`.
Surface deviation along normals (the lip-sliding paper), in :mod:`toolkit.common.analysis.surface_distance`
    :func:`vertex_normals`, :func:`surface_deviation` -> :class:`SurfaceDeviation`.
Lip-shape analysis (the lip-sliding paper, Fig. 6), in :mod:`toolkit.common.analysis.lip_shape`
    :func:`midline_profile`, :func:`convex_part`, :func:`fit_circle` -> :class:`Circle`,
    :func:`procrustes_displacement`, :func:`lip_shape_difference`,
    :func:`lip_shape_analysis`, thresholds :data:`SINGLE_LIP_THRESHOLD_MM` and
    :data:`BOTH_LIPS_THRESHOLD_MM`.

All of them are importable from here.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from toolkit.common.analysis._validate import _as_float, _as_pair, _region_indices
from toolkit.common.analysis.lip_shape import (
    BOTH_LIPS_THRESHOLD_MM,
    SINGLE_LIP_THRESHOLD_MM,
    Circle,
    LipShapeAnalysis,
    LipShapeDifference,
    convex_part,
    fit_circle,
    lip_shape_analysis,
    lip_shape_difference,
    midline_profile,
    procrustes_displacement,
)
from toolkit.common.analysis.surface_distance import SurfaceDeviation, surface_deviation, vertex_normals

__all__ = [
    "SINGLE_LIP_THRESHOLD_MM",
    "BOTH_LIPS_THRESHOLD_MM",
    "nodal_errors",
    "mean_euclidean_error",
    "rmse",
    "nrmse",
    "pearson",
    "region_errors",
    "vertex_normals",
    "SurfaceDeviation",
    "surface_deviation",
    "PairedComparison",
    "wilcoxon_paired",
    "midline_profile",
    "convex_part",
    "Circle",
    "fit_circle",
    "procrustes_displacement",
    "LipShapeDifference",
    "LipShapeAnalysis",
    "lip_shape_difference",
    "lip_shape_analysis",
]


# ----------------------------------------------------------------------------------------------
# nodal errors
# ----------------------------------------------------------------------------------------------
def nodal_errors(pred, true) -> np.ndarray:
    """Euclidean distance between predicted and true position (or displacement) per node.

    Parameters
    ----------
    pred, true : (n_nodes, 3) float, mm

    Returns
    -------
    (n_nodes,) float, mm
        ``||pred_i - true_i||``.
    """
    a, b = _as_pair(pred, true, allowed_ndim=(2,), last=3)
    return np.linalg.norm(a - b, axis=-1)


def mean_euclidean_error(pred, true) -> float:
    """Mean Euclidean nodal error, the PointNet++ paper's metric ``e = (1/N) sum_n ||v_n - u_n||``.

    Parameters
    ----------
    pred, true : (n_nodes, 3) or (n_samples, n_nodes, 3) float, mm
        A batch is averaged over samples and nodes alike.

    Returns
    -------
    float, mm
    """
    a, b = _as_pair(pred, true, allowed_ndim=(2, 3), last=3)
    return float(np.mean(np.linalg.norm(a - b, axis=-1)))


def rmse(pred, true) -> float:
    """Root-mean-square error over all entries, ``sqrt(mean((pred - true)**2))``.

    Parameters
    ----------
    pred, true : array of any (matching, non-empty) shape, in the unit of the data
        (mm for displacements, MPa for stresses). Per-component for vectors, so for
        ``(n, 3)`` displacements this is ``sqrt(mean ||e_i||^2 / 3)``.

    Returns
    -------
    float, unit of the data
    """
    a, b = _as_pair(pred, true)
    return float(np.sqrt(np.mean((a - b) ** 2)))


def nrmse(pred, true, peak: float | None = None) -> float:
    """RMSE normalised by the peak of the ground truth, ``rmse(pred, true) / peak``.

    Parameters
    ----------
    pred, true : array of any (matching, non-empty) shape, in the unit of the data
    peak : the normalising peak in that unit; default ``max |true|`` over all entries (pass
        the largest displacement magnitude for ``(n, 3)`` displacements)

    Returns
    -------
    float, dimensionless (0.01 = 1 % of the peak)
    """
    a, b = _as_pair(pred, true)
    p = float(np.max(np.abs(b))) if peak is None else float(peak)
    if not np.isfinite(p) or p <= 0.0:
        raise ValueError(f"peak is {p!r}; expected a positive finite value (is the ground truth all zero?)")
    return float(np.sqrt(np.mean((a - b) ** 2))) / p


def pearson(pred, true) -> float:
    """Pearson correlation coefficient over all (flattened) entries.

    ``r = sum(dp * dt) / sqrt(sum(dp**2) * sum(dt**2))`` with ``dp = pred - mean(pred)``.

    Parameters
    ----------
    pred, true : array of any (matching) shape with at least 2 entries, any unit

    Returns
    -------
    float, dimensionless, in [-1, 1]

    Raises
    ------
    ValueError
        If either input is constant (r is undefined).
    """
    a, b = _as_pair(pred, true)
    x, y = a.ravel(), b.ravel()
    if x.size < 2:
        raise ValueError(f"pred has {x.size} entry, expected at least 2 for a correlation")
    for name, v in (("pred", x), ("true", y)):
        if np.ptp(v) == 0.0:
            raise ValueError(
                f"{name} is constant (all {v.size} entries equal {v[0]!r}); Pearson r is "
                "undefined for a constant input"
            )
    dx, dy = x - x.mean(), y - y.mean()
    r = np.dot(dx, dy) / np.sqrt(np.dot(dx, dx) * np.dot(dy, dy))
    return float(np.clip(r, -1.0, 1.0))


def region_errors(pred, true, regions: Mapping[str, np.ndarray] | None = None) -> pd.DataFrame:
    """Euclidean nodal-error statistics per region of nodes.

    Parameters
    ----------
    pred, true : (n_nodes, 3) float, mm
    regions : mapping name -> (k,) int64 node indices (or (n_nodes,) bool mask), optional
        Regions may overlap. The name ``'all'`` is reserved.

    Returns
    -------
    pandas.DataFrame
        Indexed by region name (the given regions in order, then ``'all'``), columns
        ``n_nodes``, ``mean``, ``median``, ``p95`` (linear-interpolated 95th percentile),
        ``max`` and ``rmse``, all in mm; here ``rmse = sqrt(mean ||e_i||^2)`` over the
        region's nodes (the root-mean-square Euclidean error).
    """
    e = nodal_errors(pred, true)
    idx = _region_indices(regions, e.shape[0], "node")
    idx["all"] = np.arange(e.shape[0], dtype=np.int64)
    return _error_table(e, idx, "n_nodes", with_quantiles=True)


def _error_table(e: np.ndarray, idx: dict[str, np.ndarray], count: str, with_quantiles: bool):
    rows = {}
    for name, i in idx.items():
        v = e[i]
        row = {count: int(v.size), "mean": float(v.mean())}
        if with_quantiles:
            row["median"] = float(np.median(v))
            row["p95"] = float(np.percentile(v, 95.0))
        row["max"] = float(v.max())
        row["rmse"] = float(np.sqrt(np.mean(v**2)))
        rows[name] = row
    table = pd.DataFrame.from_dict(rows, orient="index")
    table.index.name = "region"
    return table


# ----------------------------------------------------------------------------------------------
# paired comparison
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PairedComparison:
    """Wilcoxon signed-rank comparison of paired error samples ``a`` and ``b``.

    Attributes
    ----------
    statistic : float
        scipy's statistic: ``min(W+, W-)`` for ``'two-sided'``, ``W+`` otherwise.
    p_value : float
    n : int
        Number of pairs (including zero differences, which the test discards).
    median_difference, mean_difference : float, unit of the data (mm)
        Of ``a - b``.
    rank_sum_positive, rank_sum_negative : float
        ``W+`` / ``W-``: sums of the ranks of ``|a - b|`` (zeros discarded, ties averaged) over
        pairs with ``a > b`` / ``a < b``.
    better : str
        Name of the sample with smaller errors: ``names[0]`` if ``W- > W+`` (``a`` tends to be
        smaller), ``names[1]`` if ``W+ > W-``, ``'neither'`` if equal.
    """

    statistic: float
    p_value: float
    n: int
    median_difference: float
    mean_difference: float
    rank_sum_positive: float
    rank_sum_negative: float
    better: str


def wilcoxon_paired(
    a, b, alternative: str = "two-sided", names: tuple[str, str] = ("a", "b")
) -> PairedComparison:
    """Wilcoxon signed-rank test of paired error distributions (the PointNet++ paper's ablation).

    Wraps :func:`scipy.stats.wilcoxon` (zero differences discarded, exact null distribution for
    small samples without ties, normal approximation otherwise).

    Parameters
    ----------
    a, b : (n_samples,) float, e.g. mm
        Per-sample errors of two methods on the same samples (e.g. explicit and implicit
        boundary types).
    alternative : {'two-sided', 'less', 'greater'}
        ``'less'``: the differences ``a - b`` are stochastically smaller than zero.
    names : (str, str)
        Labels of ``a`` and ``b`` used in ``better``.

    Returns
    -------
    PairedComparison
    """
    x = _as_float(a, "a")
    y = _as_float(b, "b")
    if x.ndim != 1 or x.shape != y.shape:
        raise ValueError(f"a has shape {x.shape}, expected (n,) like b {y.shape}")
    if alternative not in ("two-sided", "less", "greater"):
        raise ValueError(
            f"alternative is {alternative!r}, expected 'two-sided', 'less' or 'greater'"
        )
    d = x - y
    nz = d[d != 0.0]
    if nz.size == 0:
        raise ValueError(
            f"all {d.size} paired differences a - b are zero; the signed-rank test is undefined"
        )
    ranks = stats.rankdata(np.abs(nz))
    w_plus = float(ranks[nz > 0].sum())
    w_minus = float(ranks[nz < 0].sum())
    res = stats.wilcoxon(x, y, alternative=alternative)
    better = names[0] if w_minus > w_plus else names[1] if w_plus > w_minus else "neither"
    return PairedComparison(
        statistic=float(res.statistic),
        p_value=float(res.pvalue),
        n=int(d.size),
        median_difference=float(np.median(d)),
        mean_difference=float(np.mean(d)),
        rank_sum_positive=w_plus,
        rank_sum_negative=w_minus,
        better=better,
    )
