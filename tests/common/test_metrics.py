"""Tests for toolkit.common.analysis.metrics: closed forms, hand-computed values and scipy references."""

import numpy as np
import pandas as pd
import pytest
from scipy import stats
from scipy.spatial.transform import Rotation

from toolkit.common.analysis.metrics import (
    BOTH_LIPS_THRESHOLD_MM,
    SINGLE_LIP_THRESHOLD_MM,
    convex_part,
    fit_circle,
    lip_shape_analysis,
    lip_shape_difference,
    mean_euclidean_error,
    midline_profile,
    nodal_errors,
    nrmse,
    pearson,
    procrustes_displacement,
    region_errors,
    rmse,
    surface_deviation,
    vertex_normals,
    wilcoxon_paired,
)


# ----------------------------------------------------------------------------------------------
# geometry helpers
# ----------------------------------------------------------------------------------------------
def grid_plane(nx, ny, x_range, y_range):
    """Triangulated rectangle in z = 0: (nx*ny, 3) points and (2(nx-1)(ny-1), 3) triangles."""
    x, y = np.meshgrid(np.linspace(*x_range, nx), np.linspace(*y_range, ny), indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="ij")
    a = (i * ny + j).ravel()
    b, c, d = a + ny, a + ny + 1, a + 1
    tris = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return pts, tris.astype(np.int64)


def icosphere(radius, n_subdivisions):
    """Icosahedron subdivided n times, vertices projected onto the sphere (outward winding)."""
    t = (1.0 + np.sqrt(5.0)) / 2.0
    v = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
         [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], np.int64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(n_subdivisions):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        mid = v[uniq].mean(axis=1)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1) + len(v)
        v = np.vstack([v, mid])
        a, b, c = f.T
        f = np.concatenate([np.column_stack(x) for x in
                            ([a, m[0], m[2]], [b, m[1], m[0]], [c, m[2], m[1]],
                             [m[0], m[1], m[2]])])
    return radius * v, f


def arc(centre, radius, theta0, theta1, n):
    """n points of a circular arc in the (y, z) plane at equal angle (= arc-length) steps."""
    th = np.linspace(theta0, theta1, n)
    return np.column_stack([centre[0] + radius * np.cos(th), centre[1] + radius * np.sin(th)])


# ----------------------------------------------------------------------------------------------
# nodal errors
# ----------------------------------------------------------------------------------------------
def test_nodal_errors_are_euclidean_lengths():
    """Error vectors (3, 4, 0) and (0, 0, -2) mm have lengths 5 and 2 mm (Pythagoras)."""
    true = np.array([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
    pred = true + np.array([[3.0, 4.0, 0.0], [0.0, 0.0, -2.0]])
    np.testing.assert_allclose(nodal_errors(pred, true), [5.0, 2.0], rtol=1e-15)


def test_mean_euclidean_error_single_and_batched():
    """The PointNet++ paper: e = (1/N) sum ||v_n - u_n||; a batch averages over samples and nodes."""
    true = np.zeros((2, 2, 3))
    pred = np.array([[[3, 4, 0], [0, 0, 2]], [[1, 0, 0], [0, 6, 8]]], float)  # 5, 2, 1, 10
    assert mean_euclidean_error(pred[0], true[0]) == pytest.approx(3.5, rel=1e-15)
    assert mean_euclidean_error(pred, true) == pytest.approx(18.0 / 4.0, rel=1e-15)


def test_rmse_hand_value_any_shape():
    """sqrt(mean((p - t)^2)): one entry off by 2 among 3 -> sqrt(4/3); shape (2, 3) likewise."""
    assert rmse([1.0, 2.0, 3.0], [1.0, 2.0, 5.0]) == pytest.approx(np.sqrt(4.0 / 3.0))
    p = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 3.0]])
    assert rmse(p, np.zeros((2, 3))) == pytest.approx(np.sqrt(11.0 / 6.0))


def test_nrmse_is_rmse_over_the_peak_and_matches_numpy():
    """NRMSE = sqrt(mean((p - t)^2)) / max|t| by default (numpy on random arrays), or over a given
    peak (e.g. the largest displacement magnitude); an all-zero truth has no peak and raises."""
    rng = np.random.default_rng(1)
    t = rng.normal(size=(50, 3))
    p = t + 0.1 * rng.normal(size=t.shape)
    expected = np.sqrt(np.mean((p - t) ** 2)) / np.abs(t).max()
    assert nrmse(p, t) == pytest.approx(expected, rel=1e-14)
    peak = np.linalg.norm(t, axis=1).max()
    assert nrmse(p, t, peak=peak) == pytest.approx(rmse(p, t) / peak, rel=1e-14)
    assert nrmse([1.0, 2.0, 3.0], [1.0, 2.0, 5.0]) == pytest.approx(np.sqrt(4.0 / 3.0) / 5.0)
    with pytest.raises(ValueError, match="peak is 0.0"):
        nrmse(np.ones(3), np.zeros(3))


def test_pearson_matches_scipy_and_linear_limits():
    """r = +1 for an increasing affine map, -1 for a decreasing one, scipy's r otherwise."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(40, 3))
    assert pearson(2.0 * x + 1.0, x) == pytest.approx(1.0, abs=1e-15)
    assert pearson(-x, x) == pytest.approx(-1.0, abs=1e-15)
    y = x + rng.normal(size=x.shape)
    assert pearson(y, x) == pytest.approx(stats.pearsonr(y.ravel(), x.ravel())[0], rel=1e-12)


def test_pearson_constant_input_raises():
    with pytest.raises(ValueError, match="pred is constant"):
        pearson(np.full(5, 2.0), np.arange(5.0))
    with pytest.raises(ValueError, match="true is constant"):
        pearson(np.arange(5.0), np.zeros(5))


def test_nodal_metrics_validate_shapes_and_nan():
    a = np.zeros((4, 3))
    with pytest.raises(ValueError, match=r"pred has shape \(3, 3\), expected"):
        nodal_errors(np.zeros((3, 3)), a)
    with pytest.raises(ValueError, match=r"pred has shape \(4, 2\), expected \(n, 3\)"):
        nodal_errors(np.zeros((4, 2)), np.zeros((4, 2)))
    bad = a.copy()
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"true has 1 non-finite entries.*\(2, 1\)"):
        mean_euclidean_error(a, bad)
    with pytest.raises(ValueError, match="pred has 1 non-finite"):
        rmse(bad, a)


# ----------------------------------------------------------------------------------------------
# region errors
# ----------------------------------------------------------------------------------------------
def test_region_errors_hand_computed_table():
    """Errors 1, 2, 3, 4 mm along x. 'lips' = nodes 0, 1: mean = median 1.5, p95 (linear)
    1 + 0.95 = 1.95, max 2, rmse sqrt((1+4)/2). 'all': p95 at position 0.95*3 = 2.85 -> 3.85,
    rmse sqrt(30/4)."""
    true = np.zeros((4, 3))
    pred = np.zeros((4, 3))
    pred[:, 0] = [1.0, 2.0, 3.0, 4.0]
    table = region_errors(pred, true, {"lips": np.array([0, 1]), "chin": np.array([3, 2])})
    assert isinstance(table, pd.DataFrame)
    assert list(table.index) == ["lips", "chin", "all"]
    lips = table.loc["lips"]
    assert lips["n_nodes"] == 2
    np.testing.assert_allclose(
        lips[["mean", "median", "p95", "max", "rmse"]].to_numpy(float),
        [1.5, 1.5, 1.95, 2.0, np.sqrt(2.5)], rtol=1e-14)
    np.testing.assert_allclose(
        table.loc["all", ["mean", "median", "p95", "max", "rmse"]].to_numpy(float),
        [2.5, 2.5, 3.85, 4.0, np.sqrt(7.5)], rtol=1e-14)
    mask = np.array([False, False, True, True])
    pd.testing.assert_frame_equal(region_errors(pred, true, {"chin": mask}).loc[["chin"]],
                                  table.loc[["chin"]])


def test_region_errors_rejects_bad_indices():
    z = np.zeros((4, 3))
    with pytest.raises(ValueError, match=r"region 'lips' holds indices in \[0, 7\], expected \[0, 3\]"):
        region_errors(z, z, {"lips": np.array([0, 7])})
    with pytest.raises(ValueError, match="region 'lips'"):
        region_errors(z, z, {"lips": np.array([-1, 2])})
    with pytest.raises(ValueError, match="reserved"):
        region_errors(z, z, {"all": np.array([0])})
    with pytest.raises(ValueError, match="int64"):
        region_errors(z, z, {"lips": np.array([0.0, 1.0])})


# ----------------------------------------------------------------------------------------------
# surface deviation
# ----------------------------------------------------------------------------------------------
def test_vertex_normals_of_a_plane_and_a_sphere():
    """Plane z = 0 (counter-clockwise triangles): every normal is +z. Icosphere: normals
    point outward, within a few degrees of radial."""
    pts, tris = grid_plane(5, 4, (0, 4), (0, 3))
    np.testing.assert_allclose(vertex_normals(pts, tris), np.tile([0, 0, 1.0], (20, 1)),
                               atol=1e-15)
    v, f = icosphere(10.0, 2)
    cos = np.sum(vertex_normals(v, f) * v / 10.0, axis=1)
    assert cos.min() > np.cos(np.radians(3.0))


def test_surface_deviation_parallel_planes_exact():
    """Two parallel planes 2.5 mm apart, differently triangulated and both rotated by the same
    rotation: the normal line of every reference vertex hits the other plane at |t| = 2.5 mm."""
    rot = Rotation.from_euler("xyz", [0.3, -0.7, 1.1]).as_matrix()
    ref, ref_t = grid_plane(21, 21, (0, 20), (0, 20))
    oth, oth_t = grid_plane(13, 17, (-5, 25), (-5, 25))
    oth[:, 2] = 2.5
    shift = np.array([4.0, -3.0, 7.0])
    res = surface_deviation(oth @ rot.T + shift, oth_t, ref @ rot.T + shift, ref_t,
                            regions={"corner": np.array([0, 1, 21])})
    np.testing.assert_allclose(res.distance, 2.5, atol=1e-9)
    assert res.hit.all() and res.n_fallback == 0
    assert res.summary.loc["all", "n_vertices"] == 441
    np.testing.assert_allclose(res.summary.loc["corner", ["mean", "max", "rmse"]].to_numpy(float),
                               2.5, atol=1e-9)


def test_surface_deviation_falls_back_to_closest_point_past_the_edge():
    """Other plane z = 2.5 covers only x <= 10 of the reference square [0, 20]^2: vertices with
    x > 10 miss it along their normal and get the closest-point distance to the edge,
    sqrt((x - 10)^2 + 2.5^2) mm; they are exactly the fallbacks."""
    ref, ref_t = grid_plane(21, 11, (0, 20), (0, 10))
    oth, oth_t = grid_plane(11, 11, (0, 10), (0, 10))
    oth[:, 2] = 2.5
    res = surface_deviation(oth, oth_t, ref, ref_t)
    x = ref[:, 0]
    expected = np.where(x <= 10, 2.5, np.hypot(x - 10, 2.5))
    np.testing.assert_allclose(res.distance, expected, atol=1e-9)
    np.testing.assert_array_equal(res.hit, x <= 10)
    assert res.n_fallback == np.count_nonzero(x > 10) == 110


def test_surface_deviation_concentric_spheres():
    """Concentric spheres r = 10 mm and R = 11 mm (icospheres, 2562 vertices, the inner one
    rotated so that vertices do not line up): the exact deviation is R - r = 1 mm.

    Tolerance from the geometry, not from a previous run. A faceted sphere of radius rho lies
    in the shell [rho - s, rho], s = rho - min(face-plane distance to the centre) (sagitta). A
    line from a point at radius R_0 at angle alpha to the radial direction meets the sphere of
    radius rho at t = R_0 cos(alpha) -/+ sqrt(rho^2 - R_0^2 sin^2(alpha)), monotone in alpha and
    rho; the bounds below use the largest alpha of the computed normals. Both are within 0.015 mm
    of 1 mm here (s = 0.0114 mm, alpha < 0.34 deg), so any larger error would fail the test."""
    r, R = 10.0, 11.0
    rot = Rotation.from_euler("zyx", [0.4, 0.25, -0.6]).as_matrix()
    inner_v, inner_f = icosphere(r, 4)
    inner_v = inner_v @ rot.T
    outer_v, outer_f = icosphere(R, 4)

    def sagitta(v, f, rho):
        n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return rho - np.min(np.abs(np.sum(n * v[f[:, 0]], axis=1)))

    def max_angle(v, f):
        rad = v / np.linalg.norm(v, axis=1, keepdims=True)
        return np.arccos(np.clip(np.sum(vertex_normals(v, f) * rad, axis=1), -1, 1)).max()

    # reference = outer sphere, inward lines to the faceted inner sphere
    res = surface_deviation(inner_v, inner_f, outer_v, outer_f)
    a, s = max_angle(outer_v, outer_f), sagitta(inner_v, inner_f, r)
    upper = R * np.cos(a) - np.sqrt((r - s) ** 2 - R**2 * np.sin(a) ** 2)
    assert res.hit.all() and res.n_fallback == 0
    assert res.distance.min() >= R - r - 1e-9
    assert res.distance.max() <= upper + 1e-9
    assert upper - 1.0 < 0.015

    # reference = inner sphere, outward lines to the faceted outer sphere
    res = surface_deviation(outer_v, outer_f, inner_v, inner_f)
    a, s = max_angle(inner_v, inner_f), sagitta(outer_v, outer_f, R)
    upper = np.sqrt(R**2 - r**2 * np.sin(a) ** 2) - r * np.cos(a)
    assert res.hit.all()
    assert res.distance.min() >= R - s - r - 1e-9
    assert res.distance.max() <= upper + 1e-9
    assert (1.0 - (R - s - r)) < 0.015 and upper - 1.0 < 0.015
    assert res.summary.loc["all", "mean"] == pytest.approx(1.0, abs=0.01)


def test_surface_deviation_unreferenced_points_and_validation():
    """Reference points used by no triangle get NaN, are not fallbacks, are left out of the
    summary; out-of-range triangle indices are rejected."""
    ref, ref_t = grid_plane(3, 3, (0, 2), (0, 2))
    ref = np.vstack([ref, [[50.0, 50.0, 50.0]]])
    oth, oth_t = grid_plane(5, 5, (-1, 3), (-1, 3))
    oth[:, 2] = -1.0
    res = surface_deviation(oth, oth_t, ref, ref_t)
    assert np.isnan(res.distance[-1]) and not res.hit[-1] and res.n_fallback == 0
    np.testing.assert_allclose(res.distance[:-1], 1.0, atol=1e-12)
    assert res.summary.loc["all", "n_vertices"] == 9
    with pytest.raises(ValueError, match=r"reference_triangles holds indices in \[2, 10\], expected \[0, 9\]"):
        surface_deviation(oth, oth_t, ref, ref_t + 2)
    with pytest.raises(ValueError, match="region 'lips'"):
        surface_deviation(oth, oth_t, ref, ref_t, regions={"lips": np.array([10])})


# ----------------------------------------------------------------------------------------------
# Wilcoxon signed-rank
# ----------------------------------------------------------------------------------------------
def test_wilcoxon_paired_hand_computed_ranks():
    """d = a - b = [-0.3, 1.1, 0.7, -2.0, 1.6, 0.2, 2.4]. Ranks of |d|: 0.2->1, 0.3->2,
    0.7->3, 1.1->4, 1.6->5, 2.0->6, 2.4->7, so W- = 2 + 6 = 8, W+ = 28 - 8 = 20 and the
    two-sided statistic is min = 8. Exact null: of the 2^7 = 128 sign patterns, 24 have a rank
    sum <= 8 (counts 1,1,1,2,2,3,4,5,5 for sums 0..8), so p = 2 * 24/128 = 0.375."""
    d = np.array([-0.3, 1.1, 0.7, -2.0, 1.6, 0.2, 2.4])
    b = np.array([1.0, 0.5, 2.0, 3.0, 0.25, 0.75, 1.5])
    a = b + d
    res = wilcoxon_paired(a, b, names=("explicit", "implicit"))
    assert res.statistic == 8.0
    assert res.rank_sum_negative == 8.0 and res.rank_sum_positive == 20.0
    assert res.p_value == pytest.approx(0.375, rel=1e-12)
    assert res.p_value == pytest.approx(stats.wilcoxon(a, b).pvalue, rel=1e-14)
    assert res.n == 7
    assert res.median_difference == pytest.approx(0.7)
    assert res.mean_difference == pytest.approx(3.7 / 7.0)
    assert res.better == "implicit"
    greater = wilcoxon_paired(a, b, alternative="greater")
    assert greater.statistic == 20.0  # scipy reports W+ for one-sided tests
    assert greater.p_value == pytest.approx(
        stats.wilcoxon(a, b, alternative="greater").pvalue, rel=1e-14)
    assert wilcoxon_paired(b, a).better == "a"


def test_wilcoxon_paired_validation():
    with pytest.raises(ValueError, match=r"a has shape \(3,\), expected \(n,\) like b \(4,\)"):
        wilcoxon_paired(np.ones(3), np.ones(4))
    with pytest.raises(ValueError, match="all 3 paired differences"):
        wilcoxon_paired(np.ones(3), np.ones(3))
    with pytest.raises(ValueError, match="alternative"):
        wilcoxon_paired(np.arange(3.0), np.ones(3), alternative="bigger")


# ----------------------------------------------------------------------------------------------
# lip-shape analysis
# ----------------------------------------------------------------------------------------------
def test_thresholds_are_the_papers():
    assert SINGLE_LIP_THRESHOLD_MM == 0.55 and BOTH_LIPS_THRESHOLD_MM == 0.7


def test_midline_profile_selects_band_and_sorts_by_z():
    pts = np.array([[0.5, 3.0, 2.0], [-1.0, 4.0, -1.0], [2.0, 9.0, 0.0], [0.0, 5.0, 1.0],
                    [0.9, 6.0, 3.0], [-0.2, 7.0, 0.5]])
    np.testing.assert_array_equal(
        midline_profile(pts, half_width=1.0),
        [[4.0, -1.0], [7.0, 0.5], [5.0, 1.0], [3.0, 2.0], [6.0, 3.0]])
    with pytest.raises(ValueError, match=r"3 points lie within \|x\| <= 0.6 mm"):
        midline_profile(pts, half_width=0.6)


def bump_profile(z_step=0.5, n_bump=31):
    """Line y = 0 for 3 <= |z| <= 10 with a circular bump y = sqrt(25 - z^2) - 4 for |z| < 3
    (radius 5 mm, 1 mm high). The line-bump junctions at z = +-3 are concave corners."""
    line_lo = np.arange(-10.0, -3.0 + 1e-12, z_step)
    z_bump = np.linspace(-3.0, 3.0, n_bump + 2)[1:-1]
    line = np.concatenate([line_lo, -line_lo[::-1]])
    bump = np.column_stack([np.sqrt(25.0 - z_bump**2) - 4.0, z_bump])
    prof = np.vstack([np.column_stack([np.zeros_like(line), line]), bump])
    return prof[np.argsort(prof[:, 1])], bump


def test_convex_part_returns_just_the_bump():
    """Walking up in z, the bump turns counter-clockwise (anterior bulge) at each interior
    point, the junctions turn clockwise and the line does not turn: the convex part is exactly
    the bump points, also when the z range starts inside the flat part."""
    prof, bump = bump_profile()
    np.testing.assert_array_equal(convex_part(prof, (-10.0, 10.0)), bump)
    np.testing.assert_array_equal(convex_part(prof[::-1], (-6.0, 8.0)), bump)
    inside = convex_part(prof, (-1.0, 10.0))
    np.testing.assert_array_equal(inside, bump[bump[:, 1] >= -1.0])


def test_convex_part_with_noise_and_window():
    """With 0.003 mm noise on densely sampled points (0.1 mm apart) the single-segment turning
    flips sign by chance; chords of 5 points (0.5 mm) are robust and the result stays within
    one window (0.5 mm) of the bump, |z| < 3."""
    rng = np.random.default_rng(1)
    prof, _ = bump_profile(z_step=0.1, n_bump=59)
    noisy = prof + rng.normal(scale=0.003, size=prof.shape) * [1.0, 0.0]
    with pytest.raises(ValueError, match="increase window"):
        convex_part(noisy, (-10.0, 10.0), window=1)  # noise breaks the run at the apex
    part = convex_part(noisy, (-10.0, 10.0), window=5)
    assert part[:, 1].min() > -3.5 and part[:, 1].max() < 3.5
    assert part[:, 1].min() < -2.5 and part[:, 1].max() > 2.5


def test_fit_circle_exact_on_arc():
    """Points of a 60-degree arc, centre (3, -1.5) mm, radius 7.2 mm, are fitted exactly."""
    c = fit_circle(arc((3.0, -1.5), 7.2, -0.4, -0.4 + np.pi / 3, 12))
    np.testing.assert_allclose(c.centre, [3.0, -1.5], atol=1e-8)
    assert c.radius == pytest.approx(7.2, abs=1e-8)
    assert c.rms_residual < 1e-10


def test_fit_circle_with_noise_within_five_standard_deviations():
    """Radial noise sigma = 0.01 mm on 200 points of a 120-degree arc. The geometric fit's
    linearised covariance is sigma^2 (J^T J)^-1 with J the Jacobian of ||p - c|| - r; each
    parameter must lie within 5 standard deviations (a failure chance ~ 1e-6 per parameter)."""
    rng = np.random.default_rng(7)
    centre, radius, sigma = np.array([1.0, 2.0]), 6.0, 0.01
    th = np.linspace(-np.pi / 3, np.pi / 3, 200)
    u = np.column_stack([np.cos(th), np.sin(th)])
    pts = centre + (radius + rng.normal(scale=sigma, size=th.size))[:, None] * u
    J = np.column_stack([-u, -np.ones(th.size)])
    std = sigma * np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
    c = fit_circle(pts)
    err = np.abs(np.append(c.centre - centre, c.radius - radius))
    assert np.all(err < 5.0 * std), (err, std)
    with pytest.raises(ValueError, match="collinear"):
        fit_circle(np.column_stack([np.linspace(0, 1, 6), np.linspace(0, 2, 6)]))


def test_lip_shape_difference_on_offset_arcs():
    """Reference arc: centre c, radius r; prediction: centre c + (0.3, -0.2), radius r + 0.4,
    same angles (so the arc-length resampling keeps corresponding angles). Circle terms:
    |(0.3, -0.2)| = sqrt(0.13) and 0.4 mm. Procrustes: pred is a scaled, translated copy, so the
    optimal rotation is the identity and every point moves by the centroid difference,
    |delta + 0.4 mean(u_j)| with u_j the unit directions."""
    th0, th1, n = -0.6, 0.7, 50
    c, r, delta, dr = np.array([-8.0, 20.0]), 9.0, np.array([0.3, -0.2]), 0.4
    ref = arc(c, r, th0, th1, n)
    pred = arc(c + delta, r + dr, th0, th1, n)
    th = np.linspace(th0, th1, n)
    mean_u = np.array([np.cos(th).mean(), np.sin(th).mean()])
    res = lip_shape_difference(pred, ref, n_samples=n)
    assert res.centre_distance_mm == pytest.approx(np.sqrt(0.13), abs=1e-8)
    assert res.radius_difference_mm == pytest.approx(0.4, abs=1e-8)
    proc = np.linalg.norm(delta + dr * mean_u)
    assert res.procrustes_mm == pytest.approx(proc, abs=1e-10)
    assert res.value == pytest.approx((proc + np.sqrt(0.13) + 0.4) / 3.0, abs=1e-8)
    assert res.acceptable == (res.value < 0.55)


def test_procrustes_translation_and_rotation_closed_forms():
    """Translation t: every point moves |t| = 0.5 mm. Rotation by phi about the centroid g:
    point p moves 2 sin(phi/2) |p - g|, so the mean displacement is 2 sin(phi/2) mean|p - g|."""
    ref = arc((-5.0, 1.0), 8.0, -0.5, 0.6, 40)
    shifted = ref + [0.3, 0.4]
    assert procrustes_displacement(shifted, ref, n_samples=40) == pytest.approx(0.5, abs=1e-12)
    d = lip_shape_difference(shifted, ref, n_samples=40)
    assert d.radius_difference_mm == pytest.approx(0.0, abs=1e-9)
    assert d.centre_distance_mm == pytest.approx(0.5, abs=1e-9)

    phi = 0.1
    g = ref.mean(axis=0)
    rot = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
    rotated = (ref - g) @ rot.T + g
    expected = 2.0 * np.sin(phi / 2.0) * np.linalg.norm(ref - g, axis=1).mean()
    assert procrustes_displacement(rotated, ref, n_samples=40) == pytest.approx(expected,
                                                                                 rel=1e-10)


def test_lip_shape_identical_and_big_offset():
    """Identical profiles: every term and the value are 0, acceptable. A 5 mm shift: Procrustes
    5, centre 5, radius 0 -> value 10/3 mm, unacceptable."""
    ref = arc((-5.0, 1.0), 8.0, -0.5, 0.6, 30)
    same = lip_shape_difference(ref.copy(), ref)
    assert same.value == pytest.approx(0.0, abs=1e-9) and same.acceptable
    far = lip_shape_difference(ref + [0.0, 5.0], ref)
    assert far.value == pytest.approx(10.0 / 3.0, abs=1e-8) and not far.acceptable


def test_lip_shape_analysis_thresholds_and_both_lips():
    """Upper lip shifted by 0.9 mm: value (0.9 + 0.9 + 0)/3 = 0.6 >= 0.55, unacceptable.
    Lower lip unchanged: 0. Both lips: mean of the terms, value 0.3 < 0.7, acceptable."""
    upper = arc((-6.0, 12.0), 7.0, -0.6, 0.6, 30)
    lower = arc((-7.0, -12.0), 6.0, -0.5, 0.5, 30)
    res = lip_shape_analysis(upper + [0.0, 0.9], upper, lower.copy(), lower)
    assert res.upper.value == pytest.approx(0.6, abs=1e-8) and not res.upper.acceptable
    assert res.lower.value == pytest.approx(0.0, abs=1e-8) and res.lower.acceptable
    assert res.both.value == pytest.approx(0.3, abs=1e-8) and res.both.acceptable
    assert res.both.threshold_mm == BOTH_LIPS_THRESHOLD_MM
    assert res.upper.threshold_mm == SINGLE_LIP_THRESHOLD_MM
    assert res.both.procrustes_mm == pytest.approx(0.45, abs=1e-10)


def test_lip_profile_validation():
    with pytest.raises(ValueError, match=r"pred_profile has shape \(4, 3\), expected \(n, 2\)"):
        lip_shape_difference(np.zeros((4, 3)), np.zeros((4, 2)))
    bad = arc((0.0, 0.0), 5.0, 0.0, 1.0, 10)
    bad[3, 0] = np.nan
    with pytest.raises(ValueError, match="points2d has 1 non-finite"):
        fit_circle(bad)
