"""Surgical plans: rigid-motion algebra against closed forms, slerp increments, proximal
following about the condyles, range checks and file round trips."""

import json
import math
import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from toolkit.common.phantoms.phantom import face_hex
from toolkit.static.plan import (
    PHYSIOLOGICAL_RANGES,
    SEGMENTS,
    PlanRangeWarning,
    RigidMotion,
    SurgicalPlan,
    default_plan,
    proximal_reference_points,
)

RNG = np.random.default_rng(1)


@pytest.fixture(scope="module")
def phantom():
    return face_hex("coarse")


def _rodrigues(axis, angle_rad):
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * K + (1 - math.cos(angle_rad)) * K @ K


def _assert_same_motion(a: RigidMotion, b: RigidMotion, atol=1e-12):
    pts = RNG.uniform(-60, 60, size=(20, 3))
    np.testing.assert_allclose(a.apply(pts), b.apply(pts), rtol=0, atol=atol)


# ------------------------------------------------------------------ RigidMotion
def test_rotation_vector_matches_scipy_and_rodrigues():
    """A rotation vector (axis * angle in degrees) gives the Rodrigues matrix and scipy's
    matrix, the unit quaternion (cos a/2, sin a/2 * axis) and its angle back."""
    for _ in range(5):
        rotvec = RNG.normal(size=3) * 30.0
        m = RigidMotion.from_rotation_vector(rotvec)
        angle = np.linalg.norm(rotvec)
        np.testing.assert_allclose(m.matrix, Rotation.from_rotvec(rotvec, degrees=True).as_matrix(), atol=1e-14)
        np.testing.assert_allclose(m.matrix, _rodrigues(rotvec, math.radians(angle)), atol=1e-14)
        assert np.linalg.norm(m.rotation) == pytest.approx(1.0, abs=1e-15)
        assert m.rotation[0] == pytest.approx(math.cos(math.radians(angle) / 2), abs=1e-15)
        assert m.angle_deg == pytest.approx(angle, rel=1e-12)
        np.testing.assert_allclose(m.rotation_vector_deg, rotvec, rtol=1e-12)


def test_euler_is_x_then_y_then_z_and_matrix_round_trip():
    """euler_deg (a, b, c) rotates about the fixed x, then y, then z axis: R = Rz(c) Ry(b) Rx(a);
    from_matrix recovers the same rotation."""
    a, b, c = 10.0, -20.0, 35.0
    m = RigidMotion.from_euler_deg([a, b, c])
    rx, ry, rz = (_rodrigues(axis, math.radians(v)) for axis, v in (([1, 0, 0], a), ([0, 1, 0], b), ([0, 0, 1], c)))
    expected = rz @ ry @ rx
    np.testing.assert_allclose(m.matrix, expected, atol=1e-14)
    np.testing.assert_allclose(RigidMotion.from_matrix(expected).matrix, expected, atol=1e-14)
    with pytest.raises(ValueError, match="proper rotation"):
        RigidMotion.from_matrix(np.diag([1.0, 1.0, -1.0]))


def test_apply_about_pivot_keeps_pivot_and_distances():
    """A pure rotation about a pivot leaves the pivot fixed and preserves all distances
    (to the pivot and between points); the translation is the pivot's displacement."""
    pivot = np.array([3.0, -18.0, 21.6])
    m = RigidMotion.from_rotation_vector([7.0, -3.0, 12.0], pivot=pivot)
    pts = RNG.uniform(-50, 50, size=(30, 3))
    moved = m.apply(pts)
    np.testing.assert_allclose(m.apply(pivot), pivot, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(moved - pivot, axis=1), np.linalg.norm(pts - pivot, axis=1), rtol=1e-13)
    d0 = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    d1 = np.linalg.norm(moved[:, None] - moved[None], axis=-1)
    np.testing.assert_allclose(d1, d0, atol=1e-11)
    t = np.array([1.0, 2.0, -2.0])
    mt = RigidMotion(m.rotation, t, pivot)
    np.testing.assert_allclose(mt.displacement(pivot), t, atol=1e-12)
    assert mt.translation_mm == pytest.approx(3.0, rel=1e-15)


def test_slerp_half_of_40_degrees():
    """Slerp from the identity at 1/2 of a 40 degree rotation is 20 degrees about the same
    axis (quaternion (cos 10, sin 10 * axis)), and the translation is halved."""
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    m = RigidMotion.from_rotation_vector(40.0 * axis, translation=[4.0, -6.0, 2.0], pivot=[1.0, 2.0, 3.0])
    half = m.interpolated(0.5)
    assert half.angle_deg == pytest.approx(20.0, rel=1e-13)
    expected = np.r_[math.cos(math.radians(10)), math.sin(math.radians(10)) * axis]
    np.testing.assert_allclose(half.rotation, expected, atol=1e-15)
    np.testing.assert_allclose(half.translation, [2.0, -3.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(half.pivot, m.pivot)
    np.testing.assert_allclose(half.after(half).matrix, m.matrix, atol=1e-14)  # two half rotations make the whole


def test_short_arc_sign_invariance():
    """q and -q are the same rotation, so they interpolate identically along the short arc
    (angle at fraction f is f times the angle, never the 360 - angle long way)."""
    q = RigidMotion.from_rotation_vector([0.0, 150.0, 0.0]).rotation
    a, b = RigidMotion(q), RigidMotion(-q)
    for f in (0.25, 0.5, 0.75):
        np.testing.assert_allclose(a.interpolated(f).matrix, b.interpolated(f).matrix, atol=1e-15)
        assert b.interpolated(f).angle_deg == pytest.approx(150.0 * f, rel=1e-12)


def test_composition_and_inverse():
    """m.after(n) applies n then m; m.inverted() undoes m (their composition is the identity)."""
    m = RigidMotion.from_rotation_vector([10.0, 0.0, 5.0], [1.0, 2.0, 3.0], pivot=[0.0, 30.0, 10.0])
    n = RigidMotion.from_euler_deg([-4.0, 8.0, 2.0], [-3.0, 0.5, 1.0], pivot=[50.0, -18.0, 21.6])
    pts = RNG.uniform(-60, 60, size=(10, 3))
    np.testing.assert_allclose(m.after(n).apply(pts), m.apply(n.apply(pts)), atol=1e-12)
    np.testing.assert_allclose(m.inverted().apply(m.apply(pts)), pts, atol=1e-12)
    assert m.inverted().after(m).angle_deg == pytest.approx(0.0, abs=1e-6)


def test_nan_and_zero_quaternion_errors():
    """NaN and zero-norm quaternions are refused at construction, naming the field and,
    through a plan, the segment."""
    with pytest.raises(ValueError, match="zero norm"):
        RigidMotion((0.0, 0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="rotation quaternion.*NaN"):
        RigidMotion((1.0, float("nan"), 0.0, 0.0))
    with pytest.raises(ValueError, match="translation.*NaN"):
        RigidMotion(translation=(0.0, float("nan"), 0.0))
    with pytest.raises(ValueError, match="segment 'distal': translation_mm.*NaN"):
        SurgicalPlan.from_dict({"distal": {"translation_mm": [0.0, float("nan"), 0.0]}})
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        RigidMotion(pivot=(1.0, 2.0))


# ------------------------------------------------------------------ SurgicalPlan
def test_unknown_segment_and_defaults():
    """Unknown segment names are refused with the known ones listed; missing segments are the identity."""
    with pytest.raises(ValueError, match="unknown segments \\['maxila'\\].*lefort"):
        SurgicalPlan({"maxila": RigidMotion()})
    plan = SurgicalPlan({"lefort": RigidMotion(translation=(0, 2, 0))})
    assert list(plan.motions) == list(SEGMENTS)
    assert all(plan.motions[k].is_identity for k in SEGMENTS[1:])


def test_increments_fractions_and_last_equals_plan():
    """increments(3) are the cumulative plans at 1/3, 2/3 and 1: translations scale
    linearly, angles by the same fraction, and the last equals the plan to 1e-12."""
    plan = SurgicalPlan(
        {
            "lefort": RigidMotion.from_rotation_vector([3.0, 0.0, 1.0], [0.0, 4.0, -2.0], [0.0, 32.0, 18.0]),
            "distal": RigidMotion.from_rotation_vector([5.0, 0.0, 0.0], [0.0, -6.0, 0.0], [0.0, -18.0, 21.6]),
        }
    )
    steps = plan.increments(3)
    assert len(steps) == 3
    for k, step in enumerate(steps, start=1):
        for name in SEGMENTS:
            m, s = plan.motions[name], step.motions[name]
            np.testing.assert_allclose(s.translation, k / 3 * m.translation, atol=1e-15)
            assert s.angle_deg == pytest.approx(k / 3 * m.angle_deg, abs=1e-12)
    for name in SEGMENTS:
        np.testing.assert_allclose(steps[-1].motions[name].rotation, plan.motions[name].rotation, atol=1e-12)
        np.testing.assert_allclose(steps[-1].motions[name].translation, plan.motions[name].translation, atol=1e-12)
    with pytest.raises(ValueError, match="n = 0"):
        plan.increments(0)
    with pytest.raises(ValueError, match="fraction"):
        plan.interpolated(1.5)


@pytest.mark.parametrize("condyles", ["phantom", "tilted"])
def test_proximal_following_recovers_condylar_rotation(phantom, condyles):
    """If the distal mandible rotates purely about the axis through both condyles, each
    proximal segment's best rotation about its condyle is that same rotation (to 1e-9),
    and the condyles do not move."""
    if condyles == "phantom":
        c = phantom.condyles
    else:
        c = np.array([[50.0, -15.0, 25.0], [-52.0, -21.0, 18.0]])
    axis = (c[0] - c[1]) / np.linalg.norm(c[0] - c[1])
    distal = RigidMotion.from_rotation_vector(8.0 * axis, pivot=c.mean(axis=0))
    plan = SurgicalPlan({"distal": distal}).with_proximal_following(
        c, phantom.segments["proximal_left"].surface.points, phantom.segments["proximal_right"].surface.points
    )
    for side, name in enumerate(("proximal_left", "proximal_right")):
        m = plan.motions[name]
        np.testing.assert_allclose(m.matrix, distal.matrix, atol=1e-9)
        np.testing.assert_allclose(m.translation, 0.0)
        np.testing.assert_allclose(m.pivot, c[side])
        np.testing.assert_allclose(m.apply(c), c, atol=1e-9)  # both condyles lie on the axis


def test_proximal_following_of_default_plan(phantom):
    """For a general distal motion (setback + rotation) the proximal segments keep their
    condyles fixed, are mirror images of each other on the symmetric phantom, and their
    rotation is a least-squares optimum: no small rotation about the condyle (0.05 deg
    about random axes) lowers the mismatch with the distal motion at the reference points."""
    plan = default_plan(phantom)
    reference = proximal_reference_points(phantom)
    for side, name in enumerate(("proximal_left", "proximal_right")):
        m, pts, c = plan.motions[name], reference[side], phantom.condyles[side]
        np.testing.assert_allclose(m.apply(c), c, atol=1e-12)
        target = plan.motions["distal"].apply(pts)
        best = np.sum((m.apply(pts) - target) ** 2)
        assert best < np.sum((pts - target) ** 2)
        for axis in RNG.normal(size=(10, 3)):
            nudge = RigidMotion.from_rotation_vector(0.05 * axis / np.linalg.norm(axis), pivot=c)
            assert np.sum((nudge.after(m).apply(pts) - target) ** 2) > best
    mirror = np.diag([-1.0, 1.0, 1.0])
    left, right = plan.motions["proximal_left"].matrix, plan.motions["proximal_right"].matrix
    np.testing.assert_allclose(mirror @ left @ mirror, right, atol=1e-12)


def test_default_plan_within_ranges(phantom):
    """The packaged plan is the documented bimaxillary plan, pivots from the phantom, and
    stays within the physiological ranges (no warning)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", PlanRangeWarning)
        plan = default_plan(phantom)
    lf, d = plan.motions["lefort"], plan.motions["distal"]
    np.testing.assert_allclose(lf.translation, [0.0, 4.0, -2.0])
    np.testing.assert_allclose(lf.rotation_vector_deg, [3.0, 0.0, 0.0], atol=1e-13)
    np.testing.assert_allclose(d.translation, [0.0, -6.0, 0.0])
    np.testing.assert_allclose(d.rotation_vector_deg, [5.0, 0.0, 0.0], atol=1e-13)
    np.testing.assert_allclose(lf.pivot, phantom.segments["lefort"].pivot)
    np.testing.assert_allclose(d.pivot, phantom.segments["distal"].pivot)
    table = plan.summary()
    assert list(table.columns) == ["segment", "translation_mm", "rotation_deg"]
    assert table.set_index("segment").loc["lefort", "translation_mm"] == pytest.approx(math.sqrt(20.0))
    for name, rg in PHYSIOLOGICAL_RANGES.items():
        mm, deg = rg.translation_mm[1], rg.rotation_deg[1]
        assert plan.motions[name].translation_mm <= mm and plan.motions[name].angle_deg <= deg


def test_range_warning_error_and_force():
    """1.5x the Le Fort range warns; 2.5x raises unless forced, and a forced plan warns
    naming the segment, the value and the range."""
    max_mm, max_deg = PHYSIOLOGICAL_RANGES["lefort"].translation_mm[1], PHYSIOLOGICAL_RANGES["lefort"].rotation_deg[1]
    with pytest.warns(PlanRangeWarning, match=r"'lefort': translation 9.45 mm .*0-6.3 mm"):
        SurgicalPlan({"lefort": RigidMotion(translation=(0.0, 1.5 * max_mm, 0.0))})
    big = RigidMotion.from_rotation_vector([2.5 * max_deg, 0.0, 0.0], pivot=(0.0, 30.0, 10.0))
    with pytest.raises(ValueError, match=r"'lefort': rotation 24.5 degrees .*0-9.8 degrees.*force=True"):
        SurgicalPlan({"lefort": big})
    with pytest.warns(PlanRangeWarning, match="force=True"):
        plan = SurgicalPlan({"lefort": big}, force=True)
    with pytest.warns(PlanRangeWarning):
        assert plan.increments(3)[0].motions["lefort"].angle_deg == pytest.approx(2.5 * max_deg / 3)
    with pytest.raises(ValueError, match="'distal'"):
        SurgicalPlan({"distal": RigidMotion(translation=(0.0, -30.0, 0.0))})


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_file_round_trip(tmp_path, suffix, phantom):
    """write then read gives the same plan to 1e-12 (quaternions, translations, pivots,
    force flag), and the atomic write leaves no temporary file behind."""
    with pytest.warns(PlanRangeWarning):
        plan = SurgicalPlan.for_phantom(
            phantom,
            lefort=RigidMotion.from_euler_deg([3.3, -1.1, 0.7], [0.1, 4.2, -2.3], [0.3, 32.1, 17.9]),
            distal={"translation_mm": [0.0, -6.0, 1.0], "rotation_vector_deg": [30.0, 1.0, -2.0]},
            force=True,
        )
    path = tmp_path / f"plan{suffix}"
    plan.write(path)
    with pytest.warns(PlanRangeWarning, match="accepted because force=True"):
        back = SurgicalPlan.read(path)
    assert back.force is True
    for name in SEGMENTS:
        a, b = plan.motions[name], back.motions[name]
        np.testing.assert_allclose(b.rotation, a.rotation, rtol=0, atol=1e-12)
        np.testing.assert_allclose(b.translation, a.translation, rtol=0, atol=1e-12)
        np.testing.assert_allclose(b.pivot, a.pivot, rtol=0, atol=1e-12)
    assert [p.name for p in tmp_path.iterdir()] == [path.name]
    if suffix == ".json":
        assert json.loads(path.read_text())["distal"]["translation_mm"] == [0.0, -6.0, 1.0]


def test_hand_written_toml(tmp_path, phantom):
    """A hand-written TOML with rotation_vector_deg / euler_deg and no pivots reads with a
    phantom (pivots from its segments, proximal following); without one a rotating
    segment needs pivot_mm; inconsistent quaternion and rotation vector are refused."""
    path = tmp_path / "hand.toml"
    path.write_text(
        '[lefort]\ntranslation_mm = [0, 3, -1]\nrotation_vector_deg = [2, 0, 0]\n'
        '[distal]\ntranslation_mm = [0, -4, 0]\neuler_deg = [4, 0, 0]\n'
    )
    plan = SurgicalPlan.read(path, phantom=phantom)
    np.testing.assert_allclose(plan.motions["lefort"].matrix, _rodrigues([1, 0, 0], math.radians(2)), atol=1e-15)
    np.testing.assert_allclose(plan.motions["distal"].pivot, phantom.segments["distal"].pivot)
    assert plan.motions["proximal_left"].angle_deg > 0
    with pytest.raises(ValueError, match="hand.toml: segment 'lefort': pivot_mm is missing"):
        SurgicalPlan.read(path)
    path.write_text("[distal]\ntranslation_mm = [0, -4, 0]\n")  # no rotation: no pivot needed
    np.testing.assert_allclose(SurgicalPlan.read(path).motions["distal"].translation, [0, -4, 0])
    path.write_text("[distal]\nrotation_quaternion = [1, 0, 0, 0]\nrotation_vector_deg = [5, 0, 0]\n"
                    "pivot_mm = [0, 0, 0]")
    with pytest.raises(ValueError, match="differ by 5 degrees"):
        SurgicalPlan.read(path)
    path.write_text("[distal]\ntranslation = [0, -4, 0]\n")
    with pytest.raises(ValueError, match="unknown keys \\['translation'\\]"):
        SurgicalPlan.read(path)


def test_unknown_suffix(tmp_path):
    """Only .toml and .json are plan formats; the error names the suffix received."""
    plan = SurgicalPlan({})
    with pytest.raises(ValueError, match="'.yaml'.*\\.toml"):
        plan.write(tmp_path / "plan.yaml")
    with pytest.raises(ValueError, match="'.txt'"):
        SurgicalPlan.read(tmp_path / "plan.txt")


# ------------------------------------------------------------------ sampler
@pytest.mark.parametrize("mode", ["sagittal", "full"])
def test_sample_plans_are_uniform_in_the_ranges(phantom, mode):
    """sample_plans draws both segments in every plan, with the pivot's translation and the
    rotation angle inside the lip-sliding paper's ranges (Le Fort 0-6.3 mm / 0-9.8 deg, distal
    2.1-11.5 mm / 0.5-13.3 deg) and spread over them: 300 draws reach within 10% of both
    ends of each range. Sagittal plans translate in the y-z plane and rotate about x;
    full plans have a lateral component too. No plan warns (all within range), and every
    plan closes the jaws by at most MAX_JAW_CLOSING_MM."""
    from toolkit.static.plan import MAX_JAW_CLOSING_MM, dental_arch, jaw_closing, sample_plans

    with warnings.catch_warnings():
        warnings.simplefilter("error", PlanRangeWarning)
        plans = sample_plans(300, 7, mode, phantom=phantom)
    arch = dental_arch(phantom)
    for name in ("lefort", "distal"):
        rg = PHYSIOLOGICAL_RANGES[name]
        t = np.array([p.motions[name].translation_mm for p in plans])
        a = np.array([p.motions[name].angle_deg for p in plans])
        for values, (lo, hi) in ((t, rg.translation_mm), (a, rg.rotation_deg)):
            assert lo - 1e-9 <= values.min() and values.max() <= hi + 1e-9
            assert values.min() < lo + 0.1 * (hi - lo) and values.max() > hi - 0.1 * (hi - lo)
        tr = np.array([p.motions[name].translation for p in plans])
        axis = np.array([p.motions[name].rotation_vector_deg for p in plans])
        if mode == "sagittal":
            assert np.abs(tr[:, 0]).max() < 1e-12 and np.abs(axis[:, 1:]).max() < 1e-12
        else:
            assert np.abs(tr[:, 0]).max() > 1.0 and np.abs(axis[:, 1:]).max() > 1.0
        np.testing.assert_allclose([p.motions[name].pivot for p in plans],
                                   np.tile(phantom.segments[name].pivot, (len(plans), 1)))
    assert max(jaw_closing(p, arch) for p in plans) <= MAX_JAW_CLOSING_MM


@pytest.mark.parametrize("mode", ["sagittal", "full"])
def test_sampling_hull_holds_every_draw_and_no_more(phantom, mode):
    """Every plan sample_plans draws lies in sampling_hull (read back by sampled_parameters),
    and 300 draws reach within 10 % of the top of each of its ranges: the hull is no wider than
    what the sampler spans; a plan one step beyond a range is outside."""
    from toolkit.common.training import extrapolation
    from toolkit.static.plan import dental_arch, sample_plans, sampled_parameters, sampling_hull

    hull = sampling_hull(mode)
    assert hull["lefort.lateral_translation_mm"] == [0.0, 0.0 if mode == "sagittal" else 6.3]
    assert hull["distal.translation_mm"] == [0.0, 11.5] and hull["distal.rotation_deg"] == [0.0, 13.3]
    arch = dental_arch(phantom)
    values = [sampled_parameters(p, arch) for p in sample_plans(300, 11, mode, phantom=phantom)]
    for v in values:
        assert extrapolation(v, hull)["outside"] is False
    for name, (lo, hi) in hull.items():
        if hi > lo:
            assert max(v[name] for v in values) > hi - 0.1 * (hi - lo), name
    beyond = SurgicalPlan.from_dict({"lefort": {"translation_mm": [0.0, 6.4, 0.0]},
                                     "distal": {"translation_mm": [0.0, -5.0, 0.0],
                                                "rotation_vector_deg": [5.0, 0.0, 0.0]}}, phantom=phantom)
    ex = extrapolation(sampled_parameters(beyond, arch), hull)
    assert list(ex["parameters"]) == ["lefort.translation_mm"]
    assert ex["parameters"]["lefort.translation_mm"]["outside_by"] == pytest.approx(0.1)
    with pytest.raises(ValueError, match="unknown sampling mode 'axial'"):
        sampling_hull("axial")


def test_sample_plans_are_reproducible_and_extend(phantom):
    """Plan i depends only on the seed and i: the first 5 of 8 equal 5 drawn alone, another
    seed differs, and the proximal segments follow the distal one about the condyles."""
    from toolkit.static.plan import sample_plans

    a, b = sample_plans(8, 3, phantom=phantom), sample_plans(5, 3, phantom=phantom)
    for p, q in zip(a, b):
        for name in SEGMENTS:
            np.testing.assert_array_equal(p.motions[name].rotation, q.motions[name].rotation)
            np.testing.assert_array_equal(p.motions[name].translation, q.motions[name].translation)
    c = sample_plans(1, 4, phantom=phantom)[0]
    assert not np.allclose(c.motions["distal"].translation, a[0].motions["distal"].translation)
    for side, name in enumerate(("proximal_left", "proximal_right")):
        np.testing.assert_allclose(a[0].motions[name].pivot, phantom.condyles[side])
        assert a[0].motions[name].translation_mm == 0.0


def test_jaw_closing_rejection_and_bad_arguments(phantom):
    """Without the closing bound some uniform draws drive the mandibular teeth through the
    maxillary ones by more than 10 mm (a closed-form check: a pure 12 mm upward distal
    translation closes by exactly 11 mm); the bound rejects them, and bad arguments are
    refused naming the value."""
    from toolkit.static.plan import dental_arch, jaw_closing, sample_plans

    arch = dental_arch(phantom)
    up = SurgicalPlan({"distal": RigidMotion(translation=(0.0, 0.0, 11.0))})
    assert jaw_closing(up, arch) == pytest.approx(11.0)
    assert jaw_closing(up.scaled(-1.0), arch) == 0.0  # separating jaws do not close
    raw = sample_plans(100, 0, phantom=phantom, max_jaw_closing_mm=None)
    assert max(jaw_closing(p, arch) for p in raw) > 10.0
    with pytest.raises(ValueError, match="mode 'lateral'"):
        sample_plans(1, 0, "lateral", phantom=phantom)
    with pytest.raises(ValueError, match="n = -1"):
        sample_plans(-1, 0, phantom=phantom)
    with pytest.raises(ValueError, match="max_jaw_closing_mm = -1"):
        sample_plans(1, 0, phantom=phantom, max_jaw_closing_mm=-1.0)
    with pytest.raises(ValueError, match="MotionRange.translation_mm"):
        from toolkit.static.plan import MotionRange

        MotionRange((3.0, 1.0), (0.0, 1.0))
