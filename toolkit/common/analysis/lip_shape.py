"""Lip-shape analysis of the lip-sliding paper (Fig. 6): midline lip profiles, Procrustes
displacement, best-fitting circles, and the clinical acceptability thresholds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.common.analysis._validate import _as_points

__all__ = [
    "SINGLE_LIP_THRESHOLD_MM",
    "BOTH_LIPS_THRESHOLD_MM",
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

#: Lip-shape value (mm) below which a single-lip prediction is clinically acceptable (the lip-sliding paper).
SINGLE_LIP_THRESHOLD_MM = 0.55
#: Lip-shape value (mm) below which both lips as a whole are clinically acceptable (the lip-sliding paper).
BOTH_LIPS_THRESHOLD_MM = 0.7


def midline_profile(points, half_width: float = 1.0) -> np.ndarray:
    """Facial profile along the midline: (y, z) of points near the midsagittal plane.

    Parameters
    ----------
    points : (n_points, 3) float, mm
        E.g. skin-node coordinates of the face (anterior surface only: posterior points in the
        band would interleave with the face when sorted by z).
    half_width : float, mm
        Points with ``|x| <= half_width`` are kept.

    Returns
    -------
    (m, 2) float, mm
        ``(y, z)`` sorted by z (ties by y), m >= 5.
    """
    p = _as_points(points, "points")
    if not half_width >= 0.0:
        raise ValueError(f"half_width is {half_width}, expected a non-negative value in mm")
    sel = p[np.abs(p[:, 0]) <= half_width]
    if sel.shape[0] < 5:
        raise ValueError(
            f"{sel.shape[0]} points lie within |x| <= {half_width} mm of the midline, expected "
            "at least 5; widen half_width"
        )
    order = np.lexsort((sel[:, 1], sel[:, 2]))
    return sel[order][:, 1:3].copy()


def _as_profile(x, name: str, min_points: int = 3) -> np.ndarray:
    a = _as_points(x, name, dim=2)
    if a.shape[0] < min_points:
        raise ValueError(f"{name} has {a.shape[0]} points, expected at least {min_points}")
    return a


def convex_part(profile, z_range, window: int = 1) -> np.ndarray:
    """Convex (anteriorly bulging) part of a lip profile, the lip-sliding paper's "lip profile".

    Within ``zmin <= z <= zmax`` the profile (sorted by z) is walked upwards. The turning
    direction at point i is the 2-D cross product ``s1_y s2_z - s1_z s2_y`` of the segments
    ``s1 = p_i - p_{i-w}`` and ``s2 = p_{i+w} - p_i``: positive (a left, counter-clockwise turn
    in the (y, z) plane) where the profile bulges anteriorly (+y), negative at concavities
    such as the labiomental fold. The result is the contiguous run of points with positive
    turning around the most anterior point (max y), which always belongs to it. A larger
    ``window`` w compares longer chords and so ignores noise on the scale of the point spacing;
    the w end points of the range inherit the turning of their nearest evaluated neighbour.

    Parameters
    ----------
    profile : (m, 2) float, mm
        ``(y, z)`` points, e.g. from :func:`midline_profile`.
    z_range : (float, float), mm
        ``(zmin, zmax)`` bracketing one lip.
    window : int
        Chord length w in points (>= 1).

    Returns
    -------
    (k, 2) float, mm
        ``(y, z)`` points of the convex part sorted by z, k >= 3.
    """
    p = _as_profile(profile, "profile", min_points=3)
    zmin, zmax = (float(v) for v in z_range)
    if not zmin < zmax:
        raise ValueError(f"z_range is {tuple(z_range)}, expected (zmin, zmax) with zmin < zmax")
    w = int(window)
    if w < 1:
        raise ValueError(f"window is {window}, expected an integer >= 1")
    p = p[np.lexsort((p[:, 0], p[:, 1]))]
    p = p[(p[:, 1] >= zmin) & (p[:, 1] <= zmax)]
    if p.shape[0] < 2 * w + 1:
        raise ValueError(
            f"{p.shape[0]} profile points lie in z_range {(zmin, zmax)}, expected at least "
            f"{2 * w + 1} for window {w}"
        )
    s1 = p[w:-w] - p[: -2 * w]
    s2 = p[2 * w :] - p[w:-w]
    inner = s1[:, 0] * s2[:, 1] - s1[:, 1] * s2[:, 0]
    turn = np.concatenate([np.full(w, inner[0]), inner, np.full(w, inner[-1])])
    apex = int(np.argmax(p[:, 0]))
    convex = turn > 0.0
    convex[apex] = True
    # contiguous run of True around apex: nearest non-convex index on each side
    left_bad = np.flatnonzero(~convex[:apex])
    right_bad = np.flatnonzero(~convex[apex + 1 :])
    lo = left_bad[-1] + 1 if left_bad.size else 0
    hi = apex + 1 + right_bad[0] if right_bad.size else p.shape[0]
    if hi - lo < 3:
        raise ValueError(
            f"the convex part around the most anterior point (y={p[apex, 0]:.3f}, "
            f"z={p[apex, 1]:.3f} mm) has {hi - lo} points, expected at least 3; check z_range "
            "or increase window for noisy profiles"
        )
    return p[lo:hi].copy()


@dataclass(frozen=True, eq=False)
class Circle:
    """Circle in the (y, z) plane.

    Attributes
    ----------
    centre : (2,) float, mm
    radius : float, mm
    rms_residual : float, mm
        Root-mean-square of ``||p_i - centre|| - radius`` over the fitted points.
    """

    centre: np.ndarray
    radius: float
    rms_residual: float = 0.0


def fit_circle(points2d, n_iter: int = 20) -> Circle:
    """Best-fitting circle: algebraic (Kasa) fit refined by Gauss-Newton on the geometric fit.

    The Kasa fit solves the linear least squares ``2 c . p + (r^2 - |c|^2) = |p|^2``; it is
    exact for points on a circle and a good start otherwise. Gauss-Newton then minimises
    ``sum (||p_i - c|| - r)^2`` (the geometric, orthogonal-distance fit), which is unbiased for
    short arcs where the Kasa fit shrinks the radius.

    Parameters
    ----------
    points2d : (k, 2) float, mm, k >= 3, not collinear
    n_iter : int
        Maximum Gauss-Newton steps (stops when the step is below 1e-12 of the radius).

    Returns
    -------
    Circle
    """
    p = _as_profile(points2d, "points2d", min_points=3)
    shift = p.mean(axis=0)
    q = p - shift
    scale = np.sqrt(np.mean(np.sum(q**2, axis=1)))
    if scale == 0.0:
        raise ValueError("points2d are all identical; expected at least 3 distinct points")
    q = q / scale
    A = np.column_stack([2.0 * q, np.ones(q.shape[0])])
    rhs = np.sum(q**2, axis=1)
    sol, _, rank, sv = np.linalg.lstsq(A, rhs, rcond=None)
    if rank < 3 or sv[-1] < 1e-10 * sv[0]:
        raise ValueError(
            f"the {p.shape[0]} points are (nearly) collinear; a best-fitting circle needs "
            "curved points"
        )
    c = sol[:2]
    r = np.sqrt(sol[2] + c @ c)
    for _ in range(int(n_iter)):
        diff = q - c
        dist = np.linalg.norm(diff, axis=1)
        if np.any(dist == 0.0):
            break
        res = dist - r
        J = np.column_stack([-diff / dist[:, None], -np.ones(q.shape[0])])
        step = np.linalg.lstsq(J, -res, rcond=None)[0]
        c = c + step[:2]
        r = r + step[2]
        if np.linalg.norm(step) <= 1e-12 * abs(r):
            break
    r = abs(r)
    resid = np.linalg.norm(q - c, axis=1) - r
    return Circle(
        centre=c * scale + shift,
        radius=float(r * scale),
        rms_residual=float(np.sqrt(np.mean(resid**2)) * scale),
    )


def _resample(profile: np.ndarray, n: int) -> np.ndarray:
    """``n`` points at equal arc-length fractions along a polyline, both ends included."""
    seg = np.linalg.norm(np.diff(profile, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] == 0.0:
        raise ValueError("profile has zero length; expected distinct points")
    keep = np.concatenate([[True], seg > 0])  # np.interp needs increasing abscissae
    s, pts = s[keep], profile[keep]
    target = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(target, s, pts[:, 0]), np.interp(target, s, pts[:, 1])])


def _rigid_displacement(p: np.ndarray, q: np.ndarray) -> float:
    """Mean distance the points ``p`` move under the best rigid 2-D map onto ``q`` (Kabsch)."""
    cp, cq = p.mean(axis=0), q.mean(axis=0)
    h = (p - cp).T @ (q - cq)
    u, _, vt = np.linalg.svd(h)
    dsign = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, dsign]) @ u.T
    moved = (p - cp) @ rot.T + cq
    return float(np.mean(np.linalg.norm(moved - p, axis=1)))


def procrustes_displacement(pred, ref, n_samples: int = 50) -> float:
    """Displacement required to match a predicted profile to a reference one (Procrustes).

    Both profiles (ordered consistently, e.g. by z) are resampled to ``n_samples`` points at
    equal fractions of their own arc length, which gives the point correspondence. The
    rigid map (rotation + translation, no scaling, no reflection) minimising the summed
    squared distances of the mapped ``pred`` points to ``ref`` is found by the Kabsch SVD; the
    result is the mean distance the ``pred`` points move under that map. A pure translation
    ``t`` gives ``|t|``; identical profiles give 0.

    Parameters
    ----------
    pred, ref : (k, 2) float, mm, k >= 2 (point counts may differ)
    n_samples : int, >= 3

    Returns
    -------
    float, mm
    """
    p = _as_profile(pred, "pred", min_points=2)
    q = _as_profile(ref, "ref", min_points=2)
    if int(n_samples) < 3:
        raise ValueError(f"n_samples is {n_samples}, expected at least 3")
    return _rigid_displacement(_resample(p, int(n_samples)), _resample(q, int(n_samples)))


@dataclass(frozen=True, eq=False)
class LipShapeDifference:
    """Lip-shape difference between a predicted and a reference profile (the lip-sliding paper).

    Attributes
    ----------
    procrustes_mm : float, mm
        Procrustes displacement required to match the profiles.
    centre_distance_mm : float, mm
        Distance between the best-fitting circles' centres (lip position).
    radius_difference_mm : float, mm
        ``|r_pred - r_ref|`` of the best-fitting circles (lip size and curvature).
    value : float, mm
        Mean of the three terms above.
    threshold_mm : float, mm
        Clinical acceptability threshold applied.
    acceptable : bool
        ``value < threshold_mm``.
    pred_circle, ref_circle : Circle or None
        The fitted circles (None for the combined both-lips result).
    """

    procrustes_mm: float
    centre_distance_mm: float
    radius_difference_mm: float
    value: float
    threshold_mm: float
    acceptable: bool
    pred_circle: Circle | None = None
    ref_circle: Circle | None = None


@dataclass(frozen=True, eq=False)
class LipShapeAnalysis:
    """Lip-shape analysis of the upper lip, the lower lip and both lips as a whole.

    Attributes
    ----------
    upper, lower : LipShapeDifference
        Judged against :data:`SINGLE_LIP_THRESHOLD_MM`.
    both : LipShapeDifference
        Judged against :data:`BOTH_LIPS_THRESHOLD_MM`; see :func:`lip_shape_analysis`.
    """

    upper: LipShapeDifference
    lower: LipShapeDifference
    both: LipShapeDifference


def lip_shape_difference(
    pred_profile, ref_profile, n_samples: int = 50, threshold_mm: float = SINGLE_LIP_THRESHOLD_MM
) -> LipShapeDifference:
    """The lip-sliding paper's lip-shape value for one lip.

    The paper quantifies the difference "by the combination of 1) the required displacement to
    match two lip profiles [Procrustes] and 2) the difference in the size and center of the best
    fitting circle", with acceptability below 0.55 for a single lip, but does not print how the
    terms combine. Our reading: ``value = (procrustes + |c_pred - c_ref| + |r_pred - r_ref|) / 3``,
    the mean of three millimetre terms, so that the value is itself in mm and comparable to
    the paper's thresholds.

    Parameters
    ----------
    pred_profile, ref_profile : (k, 2) float, mm
        ``(y, z)`` convex lip profiles (see :func:`convex_part`), ordered by z, k >= 3.
    n_samples : int
        Resampling for the Procrustes term.
    threshold_mm : float, mm

    Returns
    -------
    LipShapeDifference
    """
    p = _as_profile(pred_profile, "pred_profile")
    q = _as_profile(ref_profile, "ref_profile")
    proc = procrustes_displacement(p, q, n_samples)
    cp, cq = fit_circle(p), fit_circle(q)
    centre = float(np.linalg.norm(cp.centre - cq.centre))
    radius = abs(cp.radius - cq.radius)
    value = (proc + centre + radius) / 3.0
    return LipShapeDifference(
        procrustes_mm=proc,
        centre_distance_mm=centre,
        radius_difference_mm=radius,
        value=value,
        threshold_mm=float(threshold_mm),
        acceptable=bool(value < threshold_mm),
        pred_circle=cp,
        ref_circle=cq,
    )


def lip_shape_analysis(
    pred_upper, ref_upper, pred_lower, ref_lower, n_samples: int = 50
) -> LipShapeAnalysis:
    """The lip-sliding paper's lip-shape analysis: upper lip, lower lip, and both lips as a whole.

    Single lips use :func:`lip_shape_difference` with the 0.55 mm threshold. For both lips as a
    whole (0.7 mm threshold) each of the three terms is the mean of the upper- and lower-lip
    terms, so ``both.value = (upper.value + lower.value) / 2``. We chose this over one
    Procrustes fit of the concatenated profiles because the displacement of a joint rigid map
    can cancel opposite lip movements: an upper lip moved up by 1 mm and a lower lip moved
    down by 1 mm need almost no joint rigid displacement, while each lip needs 1 mm.

    Parameters
    ----------
    pred_upper, ref_upper, pred_lower, ref_lower : (k, 2) float, mm
        ``(y, z)`` convex lip profiles ordered by z.
    n_samples : int
        Resampling for the Procrustes terms.

    Returns
    -------
    LipShapeAnalysis
    """
    up = lip_shape_difference(pred_upper, ref_upper, n_samples, SINGLE_LIP_THRESHOLD_MM)
    lo = lip_shape_difference(pred_lower, ref_lower, n_samples, SINGLE_LIP_THRESHOLD_MM)
    proc = 0.5 * (up.procrustes_mm + lo.procrustes_mm)
    centre = 0.5 * (up.centre_distance_mm + lo.centre_distance_mm)
    radius = 0.5 * (up.radius_difference_mm + lo.radius_difference_mm)
    value = (proc + centre + radius) / 3.0
    both = LipShapeDifference(
        procrustes_mm=proc,
        centre_distance_mm=centre,
        radius_difference_mm=radius,
        value=value,
        threshold_mm=BOTH_LIPS_THRESHOLD_MM,
        acceptable=bool(value < BOTH_LIPS_THRESHOLD_MM),
    )
    return LipShapeAnalysis(upper=up, lower=lo, both=both)
