"""The static FE over the physiological plan space: hard plans and meshes complete, failing
steps are cut, regulation never touches the skin, and a plan that
truly cannot be simulated raises SimulationError naming the increment, the element and a
remedy. (Completion rates over hundreds of plans: benchmarks/static_robustness.py.)"""

import importlib
import warnings

import numpy as np
import pytest

from toolkit.common.phantoms.face_variants import jittered, remeshed
from toolkit.common.phantoms.phantom import face_hex
from toolkit.static import NodeType, RigidMotion, SimulationOptions, SurgicalPlan, default_plan, simulate
from toolkit.static.plan import PlanRangeWarning, sample_plans
from toolkit.static.simulate import SimulationError

simulate_module = importlib.import_module("toolkit.static.simulate")


@pytest.fixture(scope="module")
def paper():
    return face_hex("paper")


@pytest.fixture(scope="module")
def coarse():
    return face_hex("coarse")


def _ok(result, phantom):
    s = result.summary()
    assert s["min_scaled_jacobian"] > 0
    assert phantom.mesh.with_points(phantom.mesh.points + result.displacement).scaled_jacobian().min() > 0
    return s


@pytest.mark.long
def test_hard_plans_at_paper_resolution_complete(paper):
    """At paper resolution, the packaged plan without sliding (the lip-sliding paper's method 1)
    and the sampled sagittal plan 3 of seed 0 (distal 12 degrees, which presses the posterior lower
    corner where the ramus meets the fixed edge) complete with every element positive."""
    _ok(simulate(paper, default_plan(paper), 3, "linear", "none"), paper)
    plan = sample_plans(4, 0, "sagittal", phantom=paper, max_jaw_closing_mm=None)[3]
    _ok(simulate(paper, plan), paper)


@pytest.mark.long
def test_a_plan_that_needs_a_wider_release_band_gets_one(paper):
    """Full-mode plan 10 of seed 0 lifts the Le Fort I segment ~9 mm at its lateral edge
    towards the fixed skull, 10 mm away across the default band: without sliding, the band
    cannot take the compression (measured: 2 elements inverted at increment 3 after 16
    sub-steps). With the default ``wider_release`` the plan is run again with a 15 mm band
    and completes, every element positive, the summary reporting the band used; with
    ``wider_release=()`` it still fails, naming the element."""
    plan = sample_plans(11, 0, "full", phantom=paper, max_jaw_closing_mm=10.0)[10]
    with pytest.raises(SimulationError, match=r"increment 3: .*inverted"):
        simulate(paper, plan, 3, "linear", "none", options=SimulationOptions(wider_release=()))
    result = simulate(paper, plan, 3, "linear", "none")
    assert _ok(result, paper)["release_width_mm"] == 15.0 and result.release_width == 15.0
    assert simulate(paper, default_plan(paper), 3, "linear", "none").release_width == 10.0
    with pytest.raises(ValueError, match=r"wider_release = \(20.0, 15.0\) mm"):
        SimulationOptions(wider_release=(20.0, 15.0))
    assert SimulationOptions(release_width=15.0).wider_release == (15.0, 20.0)  # only 20 mm will be tried


@pytest.mark.long
@pytest.mark.filterwarnings("ignore::toolkit.static.plan.PlanRangeWarning")  # the forced plan's sub-steps
def test_a_plan_blocked_at_the_held_cut_frees_it(paper):
    """Full-mode plan 10 of seed 0 at ``fine`` rotates the left proximal segment ~12 degrees
    and sets the distal mandible back with a ~12 degree yaw: the skin just below the lower
    end of the held posterior cut (z ~ 31 mm, 10 mm above the condyle) is dragged ~1 mm
    against its fixed neighbour 1.3 mm above and that element inverts, whatever the
    release band or the cutting. The same
    corner blocks paper when the plan's mandibular movements are doubled (Le Fort I kept
    still): with ``free_cut_radius=0`` it fails there, naming the element, whose nodes
    include fixed nodes off the bone; by default those cut nodes near it are freed, the plan
    completes with every element positive, and the result lists the freed nodes (fixed,
    off the bone, within 6 mm, freed). No bony boundary condition changes."""
    plan = sample_plans(11, 0, "full", phantom=paper, max_jaw_closing_mm=10.0)[10]
    motions = dict(plan.motions)
    motions["lefort"] = RigidMotion.identity(motions["lefort"].pivot)
    for name in ("distal", "proximal_left", "proximal_right"):
        motions[name] = motions[name].scaled(2.0)
    with pytest.warns(PlanRangeWarning, match="beyond the physiological range"):
        plan = SurgicalPlan(motions, force=True)
    with pytest.raises(SimulationError, match=r"increment 3: .*inverted") as info:
        simulate(paper, plan, options=SimulationOptions(max_cuts=2, wider_release=(), free_cut_radius=0.0))
    mesh = paper.mesh
    element_nodes = simulate_module._element_nodes(mesh, info.value.element)
    cut = np.setdiff1d(mesh.node_sets["fixed"], mesh.node_sets["bone"])
    assert np.isin(element_nodes, cut).any()
    assert "free_cut_radius" in info.value.suggestion

    result = simulate(paper, plan, options=SimulationOptions(max_cuts=2, wider_release=()))
    s = _ok(result, paper)
    freed = result.freed_cut
    assert s["freed_cut_nodes"] == freed.size >= 1 and s["release_width_mm"] == 10.0
    assert np.isin(freed, cut).all()
    centroid = mesh.points[element_nodes].mean(axis=0)
    assert np.linalg.norm(mesh.points[freed] - centroid, axis=1).max() < 6.0
    assert (result.boundary.types[freed] == NodeType.FREE).all() and np.isin(freed, result.boundary.released).all()
    as_built = simulate_module.boundary_conditions(mesh, paper.segments, "mucosa+lip")[0]
    others = np.setdiff1d(np.arange(mesh.n_points), freed)
    assert np.array_equal(result.boundary.types[others], as_built.types[others])
    with pytest.raises(ValueError, match=r"free_cut_radius = -1.0 mm"):
        SimulationOptions(free_cut_radius=-1.0)


def test_failing_steps_are_cut_and_increments_stay_where_they_were(coarse, monkeypatch):
    """A step wider than 0.2 of the plan is made to fail: each of the 3 increments is cut in
    two, reported as 2 sub-steps with 1 failed attempt, and the stored increments are still
    at k/3 of the plan. The linear scheme on updated geometry then equals a 6-increment run
    at its even increments (the same six steps), to 1e-9 mm."""
    plan = default_plan(coarse)
    real_step = simulate_module._step

    def step(model, state, target, guess=None, predicted=None):
        frac = max(abs(target.motion(n).angle_deg - (state.plan.motion(n).angle_deg if state.plan else 0.0))
                   / max(plan.motion(n).angle_deg, 1e-12) for n in ("lefort", "distal"))
        if frac > 0.2 + 1e-9:
            raise simulate_module._StepFailure("step too wide (test)")
        return real_step(model, state, target, guess, predicted)

    monkeypatch.setattr(simulate_module, "_step", step)
    cut = simulate(coarse, plan, 3)
    assert [(r.substeps, r.failed_attempts) for r in cut.reports] == [(2, 1)] * 3
    monkeypatch.setattr(simulate_module, "_step", real_step)
    six = simulate(coarse, plan, 6)
    np.testing.assert_allclose(cut.displacements, six.displacements[::2], rtol=0, atol=1e-9)


def test_a_step_that_folds_the_mucosa_frees_it_around_the_element(coarse, monkeypatch):
    """A step is made to fail on an element beside the sliding mucosa until mucosa near it is
    freed: the first quarter of the first increment fails after two cuts, the sliding mucosa
    within ``free_mucosa_radius`` of the element's centroid is freed, and the run goes on without
    another cut (3 sub-steps: two quarters and a half; 3 failed attempts). The result lists
    exactly those nodes, free in its boundary; every other node keeps its type; the nodes still
    sliding keep their own pre-operative offset, and end on their bone at it. With
    ``free_mucosa_radius=0`` the same run fails, its remedy naming the option; a step that folds
    wherever the mucosa still slides frees it patch by patch, up to a tenth of the sliding
    mucosa, and then fails."""
    plan = default_plan(coarse)
    as_built = simulate_module._build_model(coarse, "linear", "mucosa+lip", None, SimulationOptions())
    mucosa = as_built.mucosa
    X = coarse.mesh.points
    # an element with a sliding node, on the maxilla's side (where the plan moves the bone)
    elements = coarse.mesh.volume_blocks[0].cells
    sliding = np.isin(elements, mucosa).any(axis=1)
    element = int(np.flatnonzero(sliding)[0])
    centroid = X[elements[element]].mean(axis=0)
    expected = mucosa[np.linalg.norm(X[mucosa] - centroid, axis=1) < 6.0]
    real_step = simulate_module._step

    def step(model, state, target, guess=None, predicted=None):
        if not model.freed_mucosa.size:
            raise simulate_module._StepFailure("folds (test)", element)
        return real_step(model, state, target, guess, predicted)

    monkeypatch.setattr(simulate_module, "_step", step)
    result = simulate(coarse, plan, 3, options=SimulationOptions(wider_release=()))
    assert [(r.substeps, r.failed_attempts) for r in result.reports] == [(3, 3), (1, 0), (1, 0)]
    np.testing.assert_array_equal(result.freed_mucosa, expected)
    assert result.summary()["freed_mucosa_nodes"] == expected.size > 0
    types = result.boundary.types
    assert (types[expected] == NodeType.FREE).all()
    others = np.setdiff1d(np.arange(coarse.mesh.n_points), expected)
    np.testing.assert_array_equal(types[others], as_built.bc.types[others])

    model = simulate_module._build_model(coarse, "linear", "mucosa+lip", None, SimulationOptions())
    assert "sliding mucosa nodes" in model.free_near(element)
    np.testing.assert_allclose(model.offset, model._offsets(model.mucosa)[0], atol=1e-12)
    still = model.mucosa
    x = X + result.displacement
    for s, name in enumerate(model.bc.segment_names):
        sel = model.bc.segment[still] == s
        if sel.any():
            surface = coarse.segments[name].surface
            moved = plan.motion(name).apply(surface.points)
            ext = simulate_module._on_extended(x[still[sel]], moved, surface, model.rims[name])
            np.testing.assert_allclose(ext.distance, model.offset[sel], atol=1e-6)

    with pytest.raises(SimulationError, match="folds") as info:
        simulate(coarse, plan, 3, options=SimulationOptions(wider_release=(), free_mucosa_radius=0.0))
    assert "free_mucosa_radius" in info.value.suggestion

    # a step that folds wherever the mucosa still slides: freed patch by patch up to a tenth of it
    models = []

    def always(model, state, target, guess=None, predicted=None):
        models.append(model)
        still = np.isin(elements, model.mucosa).any(axis=1)
        raise simulate_module._StepFailure("folds (test)", int(np.flatnonzero(still)[0]))

    monkeypatch.setattr(simulate_module, "_step", always)
    with pytest.raises(SimulationError, match="folds"):
        simulate(coarse, plan, 3, options=SimulationOptions(wider_release=()))
    freed = models[-1].freed_mucosa.size
    assert 0.05 * mucosa.size < freed <= 0.1 * mucosa.size
    with pytest.raises(ValueError, match=r"free_mucosa_radius = -1.0 mm"):
        SimulationOptions(free_mucosa_radius=-1.0)


def test_a_plan_that_cannot_be_simulated_names_increment_element_and_remedy(coarse):
    """Driving the mandible 40 mm up into the maxilla (3.5 times the range, forced) crushes
    the tissue between the jaws whatever the step: SimulationError names the increment, the
    worst element (with its centroid) and a remedy that says the step was cut 2 times, after
    trying each wider release band."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plan = SurgicalPlan.for_phantom(coarse, distal=RigidMotion(translation=(0.0, 0.0, 40.0),
                                                                  pivot=coarse.segments["distal"].pivot), force=True)
    with pytest.raises(SimulationError) as info:
        simulate(coarse, plan, 3, options=SimulationOptions(max_cuts=2))
    exc = info.value
    msg = str(exc)
    assert msg.startswith(f"increment {exc.increment}:") and exc.element is not None
    assert f"element {exc.element}" in msg and "centroid" in msg
    assert "cut 2 times (4 sub-steps)" in exc.suggestion and exc.suggestion in msg
    assert "with each release band tried: 10, 15, 20 mm" in msg


@pytest.mark.parametrize("cell_type", ["tet4", "mixed"])
def test_poor_real_meshes_follow_a_mandible_advance(coarse, cell_type):
    """A real-like mesh (the face as Kuhn tetrahedra, or hexahedra mixed with wedges) whose
    interior nodes are jittered down to a worst scaled Jacobian of ~0.01-0.03 follows a
    5 mm mandible advance: every element stays positive, regulation does not touch its
    pre-operative slivers (none falls below half its own quality), and the skin moves
    like on the clean hexahedral mesh (mean difference < 0.6 mm: tet4 is stiffer, nu 0.47)."""
    plan = SurgicalPlan.for_phantom(coarse, distal=RigidMotion(translation=(0.0, 5.0, 0.0),
                                                              pivot=coarse.segments["distal"].pivot))
    poor = jittered(remeshed(coarse, cell_type), 0.01, amplitude=3.0)
    q0 = poor.mesh.scaled_jacobian().min()
    assert 0.01 < q0 < 0.05
    res = simulate(poor, plan)
    s = _ok(res, poor)
    ref = simulate(coarse, plan)
    skin = coarse.mesh.node_sets["skin"]
    assert np.linalg.norm(res.displacement[skin] - ref.displacement[skin], axis=1).mean() < 0.6
    assert s["substeps"] == 3


def test_regulation_moves_no_skin_node_and_keeps_mucosa_on_the_bone(paper, monkeypatch):
    """A full-3D sampled plan (plan 24 of the paper learning database's subject 0: full mode,
    drawn from ``default_rng([0, 0])``) brings elements below a scaled Jacobian of 0.1 during
    its increments; mesh regulation moves ~20 nodes there so that the run completes. It never
    moves a skin node (the prediction) nor a fixed, attached or lip node; mucosa nodes it moved
    are put back on their bone (gap < 1e-9 mm after the run)."""
    plan = sample_plans(25, np.random.default_rng([0, 0]), "full", phantom=paper)[24]
    moved = []
    real = simulate_module.regulate

    def spy(mesh, points, movable, **kw):
        reg = real(mesh, points, movable, **kw)
        moved.append(np.flatnonzero(np.linalg.norm(reg.points - points, axis=1) > 0))
        return reg

    monkeypatch.setattr(simulate_module, "regulate", spy)
    res = simulate(paper, plan)
    s = _ok(res, paper)
    assert s["regulated_nodes"] > 0 and s["max_mucosa_gap_mm"] < 1e-9
    moved = np.unique(np.concatenate(moved))
    bc = res.boundary
    assert moved.size and not np.intersect1d(moved, paper.mesh.node_sets["skin"]).size
    assert np.all(np.isin(bc.types[moved], (0, 3)))  # free or mucosa only


@pytest.mark.long
def test_mucosa_past_the_edge_of_a_bone_is_not_gathered_on_the_edge(paper):
    """Full-mode plan 11 of seed 0 (distal 10 degrees, 9 mm forward) slides the tissue over the
    right ramus ~10 mm forward and down, past the lower edge of its bone surface (an open
    patch). Projected onto the closest point, those mucosa nodes would all land on the edge line,
    and with Neo-Hookean the corner element there would collapse (two of its nodes meeting,
    whatever the release band, 10/15/20 mm). Projected onto the plane of the
    edge triangle instead, they lie beyond the edge on the extended surface, and the linear run
    has nodes there: each sits on that plane (normal offset < 1e-6 mm) and off the edge line."""
    from toolkit.common.analysis.surface_distance import beyond_rim_onto_plane, closest_points

    plan = sample_plans(12, 0, "full", phantom=paper, max_jaw_closing_mm=10.0)[11]
    result = simulate(paper, plan)
    _ok(result, paper)
    bc, x = result.boundary, paper.mesh.points + result.displacement
    beyond_any = 0
    for s, name in enumerate(bc.segment_names):
        nodes = np.flatnonzero((bc.types == 3) & (bc.segment == s))
        if not nodes.size:
            continue
        surf = paper.segments[name].surface
        moved = plan.motion(name).apply(surf.points)
        cp = closest_points(x[nodes], moved, surf.cells["tri3"])
        ext, beyond = beyond_rim_onto_plane(x[nodes], cp, moved, surf.cells["tri3"])
        assert np.abs(ext.distance).max() < 1e-6  # every mucosa node on its (extended) bone
        assert np.all(cp.distance[beyond] > 1e-3)  # those beyond are off the edge line
        beyond_any += int(beyond.sum())
    assert beyond_any > 0


def test_a_solver_that_cannot_run_is_refused_with_the_options():
    """An unknown solver, or one whose package is missing, is refused when the options are made,
    before any computation (not after the retries of a failed first solve)."""
    with pytest.raises(ValueError, match="unknown solver 'foo'"):
        SimulationOptions(solver="foo")
    if importlib.util.find_spec("sksparse") is None:
        with pytest.raises(ValueError, match=r"'cholmod' needs scikit-sparse .* use solver 'auto'"):
            SimulationOptions(solver="cholmod")
    from toolkit.common.fem import pardiso

    if not pardiso.available():
        with pytest.raises(ValueError, match="'pardiso' needs MKL"):
            SimulationOptions(solver="pardiso")
    assert SimulationOptions(solver="amg").solver == "amg"
