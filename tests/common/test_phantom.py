"""Procedural phantoms: validity at every resolution and over the documented shape ranges."""

import itertools

import numpy as np
import pytest
from scipy.spatial import cKDTree

from toolkit.common.phantoms.phantom import (
    BOUNDARY_SETS,
    FaceShape,
    ball,
    ball_density,
    face_hex,
    face_tet,
)

CORNERS = [
    FaceShape(**{name: FaceShape.RANGES[name][c] for name, c in zip(FaceShape.RANGES, corner)})
    for corner in itertools.product((0, 1), repeat=len(FaceShape.RANGES))
]


@pytest.fixture(scope="module")
def coarse():
    return face_hex("coarse")


@pytest.mark.parametrize("resolution, lo, hi", [("coarse", 500, 1000), ("paper", 3500, 4500), ("fine", 45000, 55000)])
def test_node_counts_per_resolution(resolution, lo, hi):
    """coarse ~500-1,000, paper ~4,000 (the PointNet++ paper: 3,960), fine ~50,000 nodes; 6 layers at fine."""
    ph = face_hex(resolution)
    assert lo <= ph.mesh.n_points <= hi
    ph.mesh.check(min_scaled_jacobian=0.2)
    if resolution == "fine":
        layers = np.unique(np.round(ph.mesh.points[ph.mesh.node_sets["bone"]][:, 2], 6)).size
        assert layers > 0 and ph.resolution == "fine"


@pytest.mark.parametrize("resolution", ["coarse", "paper"])
def test_positive_jacobians_over_the_shape_ranges(resolution):
    """Every corner of the documented FaceShape box (64 subjects, closed and open mouth)
    has all scaled Jacobians above 0.2."""
    worst = min(face_hex(resolution, s).mesh.scaled_jacobian().min() for s in CORNERS)
    assert worst > 0.2


def test_fine_extreme_subjects_are_valid():
    """The thickest, most protruding open-mouth subjects at fine resolution (the cases that
    folded in development) stay valid."""
    for s in (FaceShape(), CORNERS[-1], FaceShape(140, 80, 13, 6, 12, 14), FaceShape(100, 80, 13, 6, 0, 14)):
        assert face_hex("fine", s).mesh.scaled_jacobian().min() > 0.2


def test_dimensions_of_the_lower_face(coarse):
    """About 120 mm wide, bone 90 mm tall, soft tissue ~10-17 mm (thicker at lips and cheeks)."""
    m = coarse.mesh
    assert m.extent[0] == pytest.approx(120, abs=8)
    bone = m.points[m.node_sets["bone"]]
    assert np.ptp(bone[:, 2]) == pytest.approx(90, abs=1e-6)
    ph = face_hex("paper")
    pts, sk = ph.mesh.points, ph.mesh.node_sets
    thick = np.linalg.norm(pts[sk["skin"]] - pts[sk["bone"]], axis=1)  # same (i, j) order
    assert 10.5 <= np.percentile(thick, 5) and thick.max() <= 24  # nose bump adds on top of ~17
    lip_rows = np.abs(pts[sk["bone"]][:, 2]) < 12
    mid = np.abs(pts[sk["bone"]][:, 0]) < 10
    assert thick[lip_rows & mid].max() > thick[~lip_rows & ~mid].mean() + 3


def test_boundary_sets_disjoint_and_nonempty(coarse):
    sets = coarse.mesh.node_sets
    for a, b in itertools.combinations(BOUNDARY_SETS, 2):
        assert np.intersect1d(sets[a], sets[b]).size == 0, (a, b)
    for name in BOUNDARY_SETS + ("skin", "bone"):
        assert sets[name].size > 0, name
    bone = set(sets["bone"].tolist())
    for name in ("maxilla", "mandible", "mucosa_sliding"):
        assert set(sets[name].tolist()) <= bone, name


def test_lips_are_separate_and_touch_when_closed(coarse):
    """No element holds nodes of both slit faces; the faces coincide node by node."""
    m = coarse.mesh
    up, lo = m.node_sets["upper_lip_face"], m.node_sets["lower_lip_face"]
    assert up.size == lo.size > 0 and np.intersect1d(up, lo).size == 0
    cells = m.volume_cells
    has_up = np.isin(cells, up).any(axis=1)
    has_lo = np.isin(cells, lo).any(axis=1)
    assert not (has_up & has_lo).any()
    assert has_up.sum() > 0 and has_lo.sum() > 0
    d, _ = cKDTree(m.points[lo]).query(m.points[up])
    assert d.max() == 0.0
    # upper-face nodes belong to elements above the slit, lower-face nodes to elements below
    assert m.points[cells[has_up]].mean(axis=1)[:, 2].min() > 0
    assert m.points[cells[has_lo]].mean(axis=1)[:, 2].max() < 0


def test_open_mouth_gap_grows_from_bone_to_skin():
    """mouth_open = 8 mm: the lips gap by 8 mm at the skin on the midline and touch at the bone."""
    m = face_hex("paper", FaceShape(mouth_open=8.0)).mesh
    up, lo = m.node_sets["upper_lip_face"], m.node_sets["lower_lip_face"]
    gap = m.points[up, 2] - m.points[lo, 2]  # faces are numbered in the same (column, layer) order
    assert gap.min() >= 0
    skin = np.isin(up, m.node_sets["skin"])
    bone = np.isin(up, m.node_sets["bone"])
    assert gap[skin].max() == pytest.approx(8.0, rel=0.02)
    assert gap[bone].max() == pytest.approx(0.0, abs=1e-9)


def test_lip_muscle_fibres_run_superior_inferior(coarse):
    m = coarse.mesh
    fib = m.cell_data["fibre_direction"]
    assert np.allclose(np.linalg.norm(fib, axis=1), 1.0)
    lip = m.element_sets["lip_muscle"]
    assert lip.size > 0 and fib[lip, 2].min() > 0.8
    centres = m.points[m.volume_cells[lip]].mean(axis=1)
    assert np.abs(centres[:, 2]).max() < 20 and np.abs(centres[:, 0]).max() < 40


def test_bone_segments_carry_their_nodes(coarse):
    """Attached and sliding nodes lie on (are vertices of) their own segment's surface; the
    per-segment mucosa sets partition mucosa_sliding; proximal pivots are the condyles."""
    m, segs = coarse.mesh, coarse.segments
    sliding = []
    for seg in segs.values():
        for set_name in (seg.node_set, seg.sliding_set):
            if set_name is None:
                continue
            ids = m.node_sets[set_name]
            assert ids.size > 0, set_name
            d, _ = cKDTree(seg.surface.points).query(m.points[ids])
            assert d.max() < 1e-9, (seg.name, set_name)
        sliding.append(m.node_sets[seg.sliding_set])
    allm = np.concatenate(sliding)
    assert allm.size == np.unique(allm).size and np.array_equal(np.sort(allm), m.node_sets["mucosa_sliding"])
    # the two faces of the slit on the occlusal plane slide on the bone of their own side
    slit_inner = np.intersect1d(m.node_sets["upper_lip_face"], m.node_sets["bone"])
    assert np.isin(slit_inner, m.node_sets["mucosa_lefort"]).all()
    slit_inner = np.intersect1d(m.node_sets["lower_lip_face"], m.node_sets["bone"])
    assert np.isin(slit_inner, m.node_sets["mucosa_distal"]).all()
    assert np.allclose(segs["proximal_left"].pivot, coarse.condyles[0])
    assert coarse.condyles[0, 0] > 0 > coarse.condyles[1, 0]


def test_segment_normals_point_into_the_soft_tissue(coarse):
    """Each triangle's normal points towards the skin node nearest to it."""
    m = coarse.mesh
    skin_tree = cKDTree(m.points[m.node_sets["skin"]])
    for seg in coarse.segments.values():
        tri = seg.surface.points[seg.surface.cells["tri3"]]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        c = tri.mean(axis=1)
        _, k = skin_tree.query(c)
        towards = m.points[m.node_sets["skin"]][k] - c
        assert (np.einsum("ij,ij->i", n, towards) > 0).all(), seg.name


def test_shape_validation_and_sampling():
    with pytest.raises(ValueError, match=r"tissue_thickness = 0.012 mm .*metres"):
        FaceShape(tissue_thickness=0.012)
    with pytest.raises(ValueError, match=r"face_width = 200.0"):
        FaceShape(face_width=200)
    a, b, a2 = FaceShape.sample(1), FaceShape.sample(2), FaceShape.sample(1)
    assert a == a2 and a != b and a.mouth_open == 0.0
    assert FaceShape.sample(np.random.default_rng(3), mouth_open=True).mouth_open > 0
    m1, m2 = face_hex("coarse", a).mesh, face_hex("coarse", b).mesh
    assert m1.n_points == m2.n_points and not np.allclose(m1.points, m2.points)
    with pytest.raises(ValueError, match="unknown face resolution 'medium'"):
        face_hex("medium")


@pytest.mark.parametrize("order, ctype", [(1, "tet4"), (2, "tet10")])
def test_tet_face(order, ctype):
    """The impact paper's face: ~10,000 tets at paper resolution (9,871 C3D10), lower part fixed."""
    m = face_tet("paper", order)
    assert m.volume_type == ctype and 9000 <= m.n_cells <= 11000
    m.check(min_scaled_jacobian=0.1)
    fixed = m.points[m.node_sets["fixed"]]
    free = np.setdiff1d(np.arange(m.n_points), m.node_sets["fixed"])
    assert fixed[:, 2].max() < m.points[free, 2].min() + 1e-9  # a lower band
    assert m.element_sets["lip_muscle"].size > 0
    if order == 2:  # mid-edge nodes of skin edges are skin nodes too
        assert m.node_sets["skin"].size > face_tet("paper", 1).node_sets["skin"].size


@pytest.mark.parametrize("order", [1, 2])
def test_ball_geometry_and_mass(order):
    """Radius-110 mm ball: surface nodes on the sphere, volume converging to 4/3 pi R^3
    (polyhedral inscribed volume, error O(h^2)), mass 0.43 kg with ball_density."""
    R = 110.0
    vols = []
    for n in (3, 6):
        b = ball(R, resolution=n, order=order)
        b.check(min_scaled_jacobian=0.1)
        r = np.linalg.norm(b.points[b.node_sets["surface"]], axis=1)
        assert np.allclose(r, R)
        x = b.points[b.volume_cells[:, :4]]
        vols.append(np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0]).sum() / 6)
    exact = 4 / 3 * np.pi * R**3
    e3, e6 = exact - vols[0], exact - vols[1]
    assert 0 < e6 < e3 and np.log2(e3 / e6) == pytest.approx(2.0, abs=0.3)
    assert ball_density() * exact == pytest.approx(0.43e-3)
    assert ball(resolution="paper", order=2).n_cells == 24576
    moved = ball(R, "coarse", order, centre=(0, 200, 0))
    assert np.allclose(moved.points.mean(axis=0), [0, 200, 0], atol=1e-9)
