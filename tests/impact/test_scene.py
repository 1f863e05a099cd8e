"""Impact scenes: TOML round trip, validation that names the bad key or value, the impact paper's
defaults (typed from the paper, not from the code), what build_model builds (no ball mesh for a
rigid ball; the ball outside the face at t = 0; a 0.43 kg ball), and an end-to-end smoke run."""

import numpy as np
import pytest

from toolkit.impact import (
    BallSpec,
    ContactSpec,
    FaceSpec,
    Fidelity,
    MaterialSpec,
    Scene,
    SceneGeometryWarning,
    build_model,
    default_scene,
    simulate,
)
from toolkit.impact.simulate import sweep_travel

#: the impact paper's yield tables (MPa, plastic strain)
FACE_YIELD = [(0.015, 0.0), (0.020, 0.03), (0.025, 0.032), (0.028, 0.05), (0.030, 0.06), (0.031, 0.07)]
BALL_YIELD = [(0.034, 0.0), (0.035, 0.03), (0.036, 0.032), (0.037, 0.05), (0.038, 0.06), (0.039, 0.07)]


def _coarse(rigid, order=1, **fidelity):
    return Scene(face=FaceSpec(resolution="coarse"), ball=BallSpec(rigid=rigid),
                 fidelity=Fidelity(order=order, **{"integrator": "explicit", **fidelity}),
                 duration=0.3, n_frames=6)


def test_toml_round_trip(tmp_path):
    """A scene with every section changed from its default is written to TOML and read back equal
    (floats, tuples, booleans, a nested yield table, an explicit target and dt)."""
    scene = Scene(
        face=FaceSpec(resolution="coarse", material=MaterialSpec(0.02, 0.45, 1.1e-9, ((0.01, 0.0), (0.02, 0.1))),
                      lower_fixed_fraction=0.2),
        ball=BallSpec(rigid=True, velocity=45.0, direction=(0.0, -3.0, 4.0), target=(1.0, 2.0, 3.0), gap=1.5,
                      target_offset=(0.0, 1.0, -2.0)),
        contact=ContactSpec(friction=0.3, dt_fraction=0.8),
        fidelity=Fidelity(order=1, integrator="explicit", mass_scaling=25.0, safety=0.7, dt=1e-4,
                          allow_unstable_dt=True),
        duration=0.25,
        n_frames=7,
    )
    path = scene.write(tmp_path / "scene.toml")
    assert Scene.read(path) == scene
    assert Scene.read(default_scene().write(tmp_path / "default.toml")) == default_scene()


@pytest.mark.parametrize(
    "text, match",
    [
        ("colour = 1", "colour"),
        ("[ball]\nspeed = 3.0", "speed"),
        ("[face]\nresolution = 'coarse'\nstiffness = 1.0", "stiffness"),
        ("[face.material]\nE = 0.015\nnu = 0.49\ndensity = 1000.0", r"density 1000.0 looks like kg/m\^3"),
        ("[ball]\nvelocity = 30000.0", r"velocity 30000.0 mm/s looks like it is not in mm/s"),
        ("[fidelity]\norder = 3", "order must be 1 or 2, got 3"),
        ("[fidelity]\nmass_scaling = 0.5", "mass_scaling must be >= 1, got 0.5"),
    ],
)
def test_bad_scene_files_name_the_problem(tmp_path, text, match):
    """Unknown keys (top level or inside a table) and values in the wrong units or range raise
    ValueError naming the key or the value received (and the file)."""
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=match) as info:
        Scene.read(path)
    assert str(path) in str(info.value)


def test_default_scene_is_the_impact_papers():
    """The impact paper's scene: face E = 0.015 MPa, nu = 0.49, 1000 kg/m^3 with its yield table; ball
    E = 0.38 MPa, nu = 0.39, radius 110 mm, 0.43 kg (solid-sphere density 0.43e-3 t / (4/3 pi
    110^3 mm^3)), its yield table; 30 mm/s for 1.8 s; friction 0.2; 10-node tetrahedra."""
    s = default_scene()
    assert (s.face.material.E, s.face.material.nu) == (0.015, 0.49)
    assert s.face.material.density == pytest.approx(1e-9, rel=1e-12)
    np.testing.assert_allclose(s.face.material.yield_table, FACE_YIELD, rtol=1e-12)
    assert (s.ball.material.E, s.ball.material.nu, s.ball.radius) == (0.38, 0.39, 110.0)
    assert s.ball.material.density == pytest.approx(0.43e-3 / (4 / 3 * np.pi * 110.0**3), rel=1e-12)
    np.testing.assert_allclose(s.ball.material.yield_table, BALL_YIELD, rtol=1e-12)
    assert (s.ball.velocity, s.duration, s.contact.friction, s.fidelity.order) == (30.0, 1.8, 0.2, 2)
    assert not s.ball.rigid
    assert default_scene(velocity=45.0).ball.velocity == 45.0


@pytest.mark.parametrize("rigid", [True, False], ids=["rigid", "deformable"])
def test_built_ball_starts_outside_the_face(rigid):
    """A rigid ball is an analytic sphere (no mesh); a deformable one is a tet mesh inside the
    sphere of radius R about the start centre. The centre is advanced along the motion until the
    closest skin node is exactly gap = 0.5 mm from the sphere (1e-9 mm), so no skin node is
    inside it at t = 0."""
    scene = _coarse(rigid, order=2)
    built = build_model(scene)
    assert (built.ball is None) == rigid
    skin = built.face.points[built.face.node_set("skin")]
    clearance = np.linalg.norm(skin - built.ball_centre, axis=1) - scene.ball.radius
    assert clearance.min() == pytest.approx(scene.ball.gap, abs=1e-9)
    if not rigid:
        assert built.ball.volume_type == "tet10"
        assert np.linalg.norm(built.ball.points - built.ball_centre, axis=1).max() <= scene.ball.radius * (1 + 1e-12)
        assert built.model.points.shape[0] == built.face.n_points + built.ball.n_points


def test_deformable_ball_weighs_043_kg():
    """Without mass scaling the ball body's lumped masses sum to rho V_mesh; the coarse tet10 ball
    (mid-edge surface nodes on the sphere) has nearly the sphere's volume, so the ball weighs
    0.43 kg (0.43e-3 tonne) within 1 %."""
    built = build_model(_coarse(rigid=False, order=2))
    assert built.model.mass[built.face.n_points:].sum() == pytest.approx(0.43e-3, rel=1e-2)


def test_coarse_rigid_impact_smoke():
    """End to end: coarse tet4 face, rigid ball at 30 mm/s, mass scaling 100, 0.3 s. The summary
    has every documented key, added_mass_fraction = 100 - 1 = 99, the final energy balance error
    is below 2 %, and the skin in contact is pushed along by the ball: the largest displacement
    is the ball's travel after touching, 30 * 0.3 - 0.5 = 8.5 mm, within 30 % (penalty
    penetration and the skin sliding sideways make it differ)."""
    scene = _coarse(rigid=True, order=1, mass_scaling=100.0)
    summary = simulate(scene, preview=False).summary()
    keys = {"face_nodes", "face_elements", "steps", "dt_s", "wall_time_s", "max_displacement_mm",
            "max_von_mises_mpa", "energy_error", "added_mass_fraction"}
    assert keys <= set(summary)
    assert summary["added_mass_fraction"] == pytest.approx(99.0, rel=1e-12)
    assert summary["energy_error"] < 0.02
    travel = scene.ball.velocity * scene.duration - scene.ball.gap
    assert summary["max_displacement_mm"] == pytest.approx(travel, rel=0.3)
    assert summary["steps"] * summary["dt_s"] == pytest.approx(scene.duration, rel=1e-9)


def test_sweep_travel_is_the_first_touch_of_a_moving_sphere():
    """A sphere of radius 10 mm starting at the origin and moving along +x touches the point
    (20, 6, 0) after 20 - sqrt(100 - 36) = 12 mm, the point (5, 0, 0) (already inside) at -5 mm,
    and never the point (0, 11, 0) off its path; an oblique direction gives the same travel as
    the rotated problem."""
    pts = np.array([[20.0, 6.0, 0.0], [5.0, 0.0, 0.0], [0.0, 11.0, 0.0]])
    np.testing.assert_allclose(sweep_travel(pts, np.zeros(3), np.array([1.0, 0, 0]), 10.0), [12.0, -5.0, np.inf])
    d = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    R = np.array([[d[0], -d[1], 0], [d[1], d[0], 0], [0, 0, 1]])  # rotates +x onto d
    np.testing.assert_allclose(sweep_travel(pts @ R.T + 3.0, np.full(3, 3.0), d, 10.0), [12.0, -5.0, np.inf])


def test_a_path_into_the_fixed_region_warns_before_running():
    """Aimed at the nose tip (no offset) with the lowest 10% fixed, the 110 mm ball's path meets
    the fixed chin band after ~58 mm (the 1.8 s of a 50 mm/s ball travel 90 mm): build_model warns
    with the travel and a remedy. The default aim (30 mm above the nose) never meets the fixed
    nodes, even at 50 mm/s, and the summary reports that as clearance None."""
    scene = Scene(face=FaceSpec(resolution="coarse", lower_fixed_fraction=0.1),
                  ball=BallSpec(rigid=True, velocity=50.0, target_offset=(0.0, 0.0, 0.0)), duration=1.8)
    with pytest.warns(SceneGeometryWarning, match=r"reaches the fixed region after \d+\.\d mm of its 90.0 mm"):
        built = build_model(scene)
    assert -60.0 < built.fixed_clearance_mm < 0.0
    ok = Scene(face=FaceSpec(resolution="coarse"), ball=BallSpec(rigid=True, velocity=50.0), duration=1.8)
    assert build_model(ok).fixed_clearance_mm == np.inf


@pytest.mark.parametrize("velocity", [20.0, 50.0])
def test_paper_velocity_extremes_run_the_full_duration(velocity):
    """The impact paper's slowest and fastest balls (20 and 50 mm/s) run the whole 1.8 s on the coarse
    face (tet4, rigid ball, mass scaling 100) without inverting an element: 36 and 90 mm of travel
    with the default aim. The skin the ball first touches is carried with it, so the largest
    displacement is at least the ball's travel after touching (v * 1.8 s - 0.5 mm, less 5 % for
    penalty penetration and sliding), and not more than 30 % above it (the tissue flap also
    rotates about the fixed band, moving its upper edge down: +18 % at 50 mm/s); the energy
    balance closes to 2 %."""
    scene = Scene(face=FaceSpec(resolution="coarse"), ball=BallSpec(rigid=True, velocity=velocity),
                  fidelity=Fidelity(order=1, integrator="explicit", mass_scaling=100.0), duration=1.8, n_frames=6)
    summary = simulate(scene, preview=False).summary()
    assert summary["fixed_clearance_mm"] is None
    travel = velocity * 1.8 - scene.ball.gap
    assert 0.95 * travel <= summary["max_displacement_mm"] <= 1.3 * travel
    assert summary["energy_error"] < 0.02


def test_skull_support_makes_the_face_yield_and_the_band_does_not():
    """The impact paper's fastest ball (50 mm/s) for the yielding scene's 0.36 s (18 mm of travel) on the
    coarse face (tet4, rigid ball, mass scaling 100). Held by the skull (bone-side nodes fixed) the
    tissue is squeezed against the maxilla: the nodal von Mises stress passes the first yield
    stress 0.015 MPa of the impact paper's table, plastic strain appears (> 0) in a positive share of the
    volume, and the ball's path stays clear of the fixed bone nodes (positive clearance, no
    warning). Held only at the lower band (the impact paper) the same ball turns the face about the band
    and no point yields. At 20 mm/s (7.2 mm of travel, below the ~12 mm at which the skull-held
    tissue starts to yield) the face stays elastic, as yielding_scene documents."""
    import warnings

    from toolkit.impact import yielding_scene

    fast = dict(rigid=True)
    scene = yielding_scene(50.0).with_face(resolution="coarse").with_ball(**fast).with_fidelity(
        order=1, integrator="explicit", mass_scaling=100.0)
    assert scene.face.support == "skull" and scene.duration == pytest.approx(0.36)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SceneGeometryWarning)
        s = simulate(scene, preview=False).summary()
    assert s["max_von_mises_mpa"] > FACE_YIELD[0][0]
    assert s["max_equivalent_plastic_strain"] > 0 and s["plastic_volume_fraction"] > 0
    assert s["fixed_clearance_mm"] > 0 and s["energy_error"] < 0.02
    band = simulate(scene.with_face(support="band"), preview=False).summary()
    assert band["max_equivalent_plastic_strain"] == 0 and band["max_von_mises_mpa"] < FACE_YIELD[0][0]
    slow = simulate(scene.with_ball(velocity=20.0), preview=False).summary()
    assert slow["max_equivalent_plastic_strain"] == 0


def test_support_is_validated_and_round_trips(tmp_path):
    with pytest.raises(ValueError, match="face support 'glue' is not one of"):
        FaceSpec(support="glue")
    from toolkit.impact import yielding_scene

    scene = yielding_scene(35.0)
    assert Scene.read(scene.write(tmp_path / "y.toml")) == scene


@pytest.mark.parametrize("resolution", ["coarse", "paper"])
def test_the_default_scene_is_mirror_symmetric_about_the_midsagittal_plane(resolution):
    """Every skin corner node of the phantom has a mirror image under x -> -x (to 1e-9 mm;
    the volume's tet split is not symmetric everywhere, the skin is), with the two lips of the
    mouth slit (coincident nodes) kept apart by their node sets, and the default ball starts
    and moves in the plane x = 0. benchmarks/impact_ladder.py relies on this to compare a run
    with the mirror image of its reference: a deformable ball pressed into this face slides to
    one side or the other (a symmetry-breaking branch)."""
    from toolkit.common.analysis.symmetry import mirror_index

    built = build_model(default_scene().with_face(resolution=resolution).with_ball(rigid=True))
    face = built.face
    skin = face.node_sets["skin"]
    skin = skin[skin < int(face.volume_cells[:, :4].max()) + 1]
    lips = np.isin(skin, face.node_sets["upper_lip_face"]) + 2 * np.isin(skin, face.node_sets["lower_lip_face"])
    assert mirror_index(face.points[skin], lips, tol=1e-9) is not None
    assert mirror_index(face.points[skin], tol=1e-9) is None  # the lips' coincident nodes need the labels
    assert abs(built.ball_centre[0]) < 1e-9 and default_scene().ball.direction[0] == 0.0


def test_default_scenes_fit_their_support():
    """The impact paper's band-held scene never meets a support (limit inf); the skull-held
    yielding scene at every paper velocity (20-50 mm/s over 0.36 s, at most 18 mm of travel) fits
    the ~19 mm the skull leaves on the coarse and the paper face (tet10)."""
    from toolkit.impact import yielding_scene
    from toolkit.impact.simulate import check_travel, face_mesh, travel_limit

    assert travel_limit(default_scene().with_face(resolution="coarse")) == np.inf
    for resolution in ("coarse", "paper"):
        scene = yielding_scene(50.0).with_face(resolution=resolution)
        face = face_mesh(scene)
        assert 18.0 < travel_limit(scene, face) < 21.0
        for v in (20.0, 30.0, 40.0, 50.0):
            check_travel(scene.with_ball(velocity=v), face)


def test_a_ball_driven_through_the_skull_is_refused_before_any_step(tmp_path, monkeypatch):
    """0.9 s at 50 mm/s (45 mm) on the skull-held face would crush the ~21 mm of tissue against the
    bone (an element inverts after ~27 mm): simulate and build_database refuse it with a SceneError
    before any step is computed or any file written, naming the longest duration that fits
    (--duration); that duration passes the check and one millisecond more does not."""
    import importlib
    import re
    from dataclasses import replace

    from toolkit.impact import SceneError, yielding_scene
    from toolkit.impact.database import build_database
    from toolkit.impact.simulate import check_travel

    sim = importlib.import_module("toolkit.impact.simulate")

    def no_step(*args, **kwargs):
        raise AssertionError("a step was computed")

    monkeypatch.setattr(sim, "run_explicit", no_step)
    scene = replace(yielding_scene(50.0).with_face(resolution="coarse").with_ball(rigid=True).with_fidelity(order=1),
                    duration=0.9)
    with pytest.raises(SceneError, match=r"45\.0 mm .* --duration (\d\.\d+)") as info:
        simulate(scene, out=tmp_path / "run")
    assert not (tmp_path / "run").exists()
    with pytest.raises(SceneError, match="--duration"):
        build_database(tmp_path / "db.h5", [30.0, 50.0], [], scene, workers=0, progress=False)
    assert not (tmp_path / "db.h5").exists()
    longest = float(re.search(r"--duration (\d\.\d+)", str(info.value)).group(1))
    assert 0.36 <= longest < 0.42
    check_travel(replace(scene, duration=longest))
    with pytest.raises(SceneError):
        check_travel(replace(scene, duration=longest + 0.001))
    with pytest.raises(SceneError, match="at 30 mm/s"):
        check_travel(replace(scene, duration=0.9).with_ball(velocity=30.0))
