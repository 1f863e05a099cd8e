"""Answers within a tolerance: the calibration, the out-of-distribution check, and the FE
fallback whose answer is the FE's own."""

import json
import math
import shutil
import subprocess
import sys
import warnings
from dataclasses import replace

import numpy as np
import pytest

from toolkit.static import load_case
from toolkit.static.database import StaticDatabase, plan_features
from toolkit.static.plan import SurgicalPlan
from toolkit.static.simulate import simulate
from toolkit.static.sliding_response import SlidingResponse
from toolkit.static.surrogate import Surrogate
from toolkit.static.trust import (
    Calibration,
    answer,
    answer_error,
    baseline_prediction,
    calibrate_surrogate,
    out_of_distribution,
)

#: every test here answers with a model trained to an accuracy (hard_model), or calibrates it
pytestmark = pytest.mark.long

COVERAGE = 0.8  # the coarse database's 7 test plans allow at most 1 - 1/8 = 87.5 %


@pytest.fixture(scope="module")
def calibrated(hard_model, db100, tmp_path_factory):
    """The shared coarse model, copied, calibrated on its 7 test plans."""
    out = tmp_path_factory.mktemp("trust") / "model"
    shutil.copytree(hard_model.directory, out)
    model = Surrogate.load(out)
    cal = calibrate_surrogate(model, db100, coverage=COVERAGE, progress=False)
    cal.save(out)
    return model, cal


def test_calibration_measures_held_out_plans_and_round_trips(calibrated, db100):
    model, cal = calibrated
    db = StaticDatabase.open(db100)
    assert sorted(c["key"] for c in cal.cases) == sorted(model.bundle.extra["test_keys"])
    # each case's error is the answer error of the network against the FE of that plan
    case = cal.cases[0]
    subject = db.subject(case["subject"])
    pred = model.predict_plan(subject, db.plan(case["key"]))
    assert answer_error(pred.displacement, db.displacements(case["key"])[-1]) == pytest.approx(case["error_mm"])
    # the baseline's error: the face's sliding response plus the residual regression, step by step
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        params = plan_features(db.plan(case["key"]), db.config.increments)
    response = SlidingResponse.build(subject, db.config.sliding)
    base, _ = response.trajectory(db.plan(case["key"]), db.config.increments, cal.residual.residual.predict(params))
    assert answer_error(base[-1], db.displacements(case["key"])[-1]) == pytest.approx(case["baseline_error_mm"])
    # each factor is the ceil((n + 1) c)-th smallest ratio: with n = 7 and c = 0.8, the 7th
    for who, key in (("network", "error_mm"), ("baseline", "baseline_error_mm")):
        ratios = sorted(c[key] / c["scale_mm"] for c in cal.cases)
        assert cal.bounds[who].factor == pytest.approx(ratios[math.ceil(8 * COVERAGE) - 1])
    # auto: the cheapest scale and answer whose bound, averaged over the plans, is within 10 % of the
    # narrowest; the bound is its own
    k = math.ceil(8 * COVERAGE) - 1
    mean_bound, cost = {}, {}
    for scale in ("disagreement", "constant"):
        scales = np.array([1.0 if scale == "constant" else c["disagreement_mm"] for c in cal.cases])
        for who, key in (("network", "error_mm"), ("baseline", "baseline_error_mm")):
            factor = sorted(c[key] / s for c, s in zip(cal.cases, scales))[k]
            mean_bound[scale, who] = factor * scales.mean()
            cost[scale, who] = np.median([c["network_s"] + c["baseline_s"] if scale == "disagreement"
                                          else c[f"{who}_s"] for c in cal.cases])
    near = [p for p, b in mean_bound.items() if b <= 1.1 * min(mean_bound.values())]
    assert (cal.scale, cal.answerer) == min(near, key=cost.get)
    assert cal.bound == cal.bounds[cal.answerer]
    loaded = Calibration.load(model.directory)
    assert loaded.bound == cal.bound and loaded.scale == cal.scale and loaded.answerer == cal.answerer
    assert loaded.bounds == cal.bounds and loaded.at(0.5).bounds["network"].factor <= cal.bounds["network"].factor
    np.testing.assert_array_equal(loaded.residual.residual.modes, cal.residual.residual.modes)
    assert loaded.plan_ranges == cal.plan_ranges and loaded.plan_hull == cal.plan_hull
    np.testing.assert_array_equal(loaded.arch_nodes, cal.arch_nodes)


@pytest.mark.parametrize("key, what", [("baseline", "influence matrix"), ("plan_hull", "plan_hull")])
def test_a_calibration_of_an_earlier_version_is_refused(calibrated, tmp_path, key, what):
    """A calibration whose residual regression was fit on another linear part would add it to
    the wrong one, and one without the training plans' support cannot check a plan: loading
    names the file, what it lacks and the command that makes a new one."""
    model, _ = calibrated
    shutil.copytree(model.directory, tmp_path / "model")
    meta = json.loads((tmp_path / "model" / "calibration.json").read_text())
    del meta[key]
    (tmp_path / "model" / "calibration.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=rf"calibration.json was written by an earlier version: .*{what}.*"
                                         r"toolkit static calibrate --model"):
        Calibration.load(tmp_path / "model")


def test_a_calibration_belongs_to_the_weights_it_was_made_for(calibrated, quick_model, tmp_path):
    """A calibration copied beside another model's weights is refused, naming the command that
    calibrates; saving new weights into a calibrated folder (a retraining) removes the calibration
    made for the weights it replaces."""
    from toolkit.common.training.bundle import ModelBundle

    model, _ = calibrated
    other = tmp_path / "other"
    shutil.copytree(quick_model.directory, other)
    for name in ("calibration.json", "calibration.npz"):
        shutil.copy(model.directory / name, other / name)
    with pytest.raises(ValueError, match=r"was made for another model .*toolkit static calibrate --model"):
        Calibration.load(other)
    retrained = tmp_path / "retrained"
    shutil.copytree(model.directory, retrained)
    assert Calibration.load(retrained).bound.factor > 0  # a copy of the folder keeps its calibration
    ModelBundle.load(quick_model.directory).save(retrained)
    assert not (retrained / "calibration.json").exists() and not (retrained / "calibration.npz").exists()
    with pytest.raises(FileNotFoundError, match="holds no calibration"):
        Calibration.load(retrained)


def test_too_few_plans_for_the_coverage_are_refused(hard_model, db100):
    with pytest.raises(ValueError, match="needs at least 19"):
        calibrate_surrogate(hard_model, db100, coverage=0.95, progress=False)


def test_a_plan_far_outside_the_training_data_falls_back_to_the_fe_and_is_the_fe(calibrated):
    model, cal = calibrated
    case = load_case(resolution="coarse")
    far = SurgicalPlan.from_dict({"lefort": {"translation_mm": [0.0, 9.0, 0.0]},
                                  "distal": {"translation_mm": [0.0, 12.0, 0.0]}}, phantom=case.subject)
    ood = out_of_distribution(cal, case.subject.mesh, far)
    assert ood["outside"] and any(r.startswith("plan:") for r in ood["reasons"])
    got = answer(model, case.subject, far, 100.0, calibration=cal)  # any estimate: the inputs decide
    assert got.answered_by == "fe" and got.reason.startswith("out of distribution")
    fe = simulate(case.subject, far, 3, "linear", "mucosa+lip")
    # the same simulation: equal up to the run-to-run rounding of the threaded sparse solve
    np.testing.assert_allclose(got.result.displacements, fe.displacements, rtol=0, atol=1e-9)
    assert got.seconds["fe"] > 0 and got.seconds["surrogate"] > 0


#: a distal movement the sampler can draw (5 mm setback, 5 degrees)
DISTAL = {"translation_mm": [0.0, -5.0, 0.0], "rotation_vector_deg": [5.0, 0.0, 0.0]}


def _plan(case, lefort, distal):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return SurgicalPlan.from_dict({"lefort": lefort, "distal": distal}, phantom=case.subject)


@pytest.mark.parametrize("distal", [{"translation_mm": [0.0, 0.0, 11.5], "rotation_vector_deg": [-13.3, 0, 0]},
                                    {"translation_mm": [0.0, 1.0, 0.0]}], ids=["top of the ranges", "below them"])
def test_a_plan_within_the_samplers_hull_is_in_distribution_beyond_the_training_plans_box(calibrated, distal):
    """The hull is what the database's sampler spans (translation lengths and angles up to the top of
    the physiological ranges, sagittal, jaws closing by at most 10 mm), not the box of the plans it
    drew: a plan at the top of every range, straight up, lies outside that box and is in
    distribution; so is an unrotated 1 mm distal advance, below the ranges' bottom (2.1 mm,
    0.5 degrees) but between drawn motions of opposite directions."""
    _, cal = calibrated
    case = load_case(resolution="coarse")
    assert cal.plan_hull["distal.translation_mm"] == [0.0, 11.5]
    assert cal.plan_hull["lefort.lateral_translation_mm"] == [0.0, 0.0]
    plan = _plan(case, {"translation_mm": [0.0, 0.0, 6.3], "rotation_vector_deg": [9.8, 0, 0]}, distal)
    assert plan_features(plan, 1)[0][2] > cal.plan_ranges["lefort.translation_z_mm"][1]  # beyond the box
    ood = out_of_distribution(cal, case.subject.mesh, plan)
    assert not ood["outside"], ood["reasons"]
    assert 0 < ood["plan"]["nearest_plan_distance"]
    model, _ = calibrated  # static predict without a tolerance says the same
    assert model.predict_plan(case.subject, plan).summary()["extrapolation"] == {"outside": False, "parameters": {}}


@pytest.mark.parametrize("lefort, distal, parameter", [
    ({"translation_mm": [0.0, 6.6, 0.0]}, {**DISTAL, "translation_mm": [0.0, -5.0, 0.0]}, "lefort.translation_mm"),
    ({"translation_mm": [0.0, 3.0, 0.0]}, {**DISTAL, "rotation_vector_deg": [-13.5, 0.0, 0.0]}, "distal.rotation_deg"),
    ({"translation_mm": [0.5, 3.0, 0.0]}, DISTAL, "lefort.lateral_translation_mm"),
    ({"translation_mm": [0.0, 3.0, 0.0]}, {**DISTAL, "rotation_vector_deg": [5.0, 0.0, 2.0]},
     "distal.off_axis_rotation_deg"),
    ({"translation_mm": [0.0, 0.0, -6.0]}, {**DISTAL, "translation_mm": [0.0, 0.0, 11.0]}, "jaw_closing_mm"),
], ids=["lefort beyond the range", "distal rotated beyond it", "lateral", "yaw", "jaws through each other"])
def test_a_plan_the_sampler_cannot_draw_is_out_of_distribution(calibrated, lefort, distal, parameter):
    """... and ``static predict`` without a tolerance gives the same verdict on the same parameter."""
    model, cal = calibrated
    case = load_case(resolution="coarse")
    plan = _plan(case, lefort, distal)
    ood = out_of_distribution(cal, case.subject.mesh, plan)
    assert ood["outside"] and list(ood["plan"]["parameters"]) == [parameter]
    assert any(r.startswith("plan:") and parameter in r for r in ood["reasons"])
    predicted = model.predict_plan(case.subject, plan).summary()["extrapolation"]
    assert predicted == {k: v for k, v in ood["plan"].items() if k != "nearest_plan_distance"}


def test_in_distribution_plan_answered_by_whichever_the_tolerance_allows(calibrated, db100):
    model, cal = calibrated
    db = StaticDatabase.open(db100)
    key = model.bundle.extra["test_keys"][0]
    subject, plan = db.subject(0), db.plan(key)
    assert not out_of_distribution(cal, subject.mesh, plan)["outside"]
    loose = answer(model, subject, plan, 100.0, calibration=cal)
    chosen = cal.for_tolerance(100.0)
    assert loose.answered_by == {"network": "surrogate", "baseline": "baseline"}[chosen.answerer], loose.reason
    assert (loose.estimate["scale"], loose.estimate["answerer"]) == (chosen.scale, chosen.answerer)
    assert loose.seconds["fe"] == 0.0
    cal = replace(cal, candidates=((cal.scale, cal.answerer),))  # the calibration's own pair only
    network_only = replace(cal, answerer="network", bound=cal.bounds["network"])
    by_network = answer(model, subject, plan, 100.0, calibration=network_only)
    assert by_network.answered_by == "surrogate"
    np.testing.assert_allclose(by_network.result.displacement, model.predict_plan(subject, plan).displacement)
    baseline_only = replace(cal, answerer="baseline", bound=cal.bounds["baseline"])
    by_baseline = answer(model, subject, plan, 100.0, calibration=baseline_only)
    assert by_baseline.answered_by == "baseline"
    np.testing.assert_allclose(by_baseline.result.displacements,
                               baseline_prediction(model, cal.residual, subject, plan).displacements)
    # the baseline does not depend on the network: with the constant scale (network not run) it is the same
    no_network = answer(model, subject, plan, 100.0, calibration=replace(baseline_only, scale="constant"))
    assert no_network.result.material == by_baseline.result.material
    np.testing.assert_array_equal(no_network.result.displacements, by_baseline.result.displacements)
    assert by_baseline.result.summary()["min_scaled_jacobian"] > 0
    est = answer(model, subject, plan, 100.0, calibration=cal).estimate
    assert est["bound_mm"] == pytest.approx(cal.bound.factor * est["scale_mm"])
    assert est["node_mm"].shape == (subject.mesh.n_points,)
    assert np.percentile(est["node_mm"], 95) == pytest.approx(est["bound_mm"])
    tight = answer(model, subject, plan, est["bound_mm"] / 2, calibration=cal)
    assert tight.answered_by == "fe" and "above the tolerance" in tight.reason
    assert answer_error(tight.result.displacement, db.displacements(key)[-1]) < 1e-6


def test_the_tolerance_chooses_the_pair_with_the_least_expected_time(calibrated):
    """Of the four calibrated pairs (scale x answerer), a tolerance takes the one whose mean time per
    answer over the calibration plans is least: its own time on each plan, plus the FE's on the
    plans its bound would leave to the FE. Above every bound that is the fastest pair; below every
    bound, every pair leaves every plan to the FE and the fastest pair still wins."""
    _, cal = calibrated
    assert set(cal.candidates) == {(s, a) for s in ("disagreement", "constant") for a in ("network", "baseline")}
    k = math.ceil(8 * COVERAGE) - 1

    def pair(scale, who):
        """Each calibration plan's bound and the pair's time on it."""
        scales = np.array([1.0 if scale == "constant" else c["disagreement_mm"] for c in cal.cases])
        key = "error_mm" if who == "network" else "baseline_error_mm"
        factor = sorted(c[key] / x for c, x in zip(cal.cases, scales))[k]
        return factor * scales, np.array([c["network_s"] + c["baseline_s"] if scale == "disagreement"
                                          else c[f"{who}_s"] for c in cal.cases])

    fe = np.array([c["fe_s"] for c in cal.cases])
    pairs = {c: pair(*c) for c in cal.candidates}
    edges = np.unique(np.concatenate([b for b, _ in pairs.values()]))
    for tol in (1e-6, *edges, *(edges * 1.01), 1e9):  # on and just above every bound
        got = cal.for_tolerance(tol)
        times = {c: np.mean(t + np.where(b > tol, fe, 0.0)) for c, (b, t) in pairs.items()}
        assert times[got.scale, got.answerer] == pytest.approx(min(times.values()))
        scales = np.array([1.0 if got.scale == "constant" else c["disagreement_mm"] for c in cal.cases])
        np.testing.assert_allclose(got.bound.bound(scales), pairs[got.scale, got.answerer][0])
    one = replace(cal, candidates=(("constant", "network"),))
    assert one.for_tolerance(1e-6) is one


def test_another_material_or_face_is_out_of_distribution(calibrated):
    model, cal = calibrated
    case = load_case(resolution="coarse")
    ood = out_of_distribution(cal, case.subject.mesh, case.plan, material="neo-hookean")
    assert ood["outside"] and ood["reasons"][-1].startswith("material")
    moved = case.subject.mesh.with_points(case.subject.mesh.points * 1.3)
    ood = out_of_distribution(cal, moved, case.plan)
    assert ood["outside"] and "from the nearest training subject" in ood["reasons"][0]
    # a face close on average but wider at its edges: outside the box the training subjects span
    X = case.subject.mesh.points
    wider = case.subject.mesh.with_points(X + np.where(np.abs(X[:, :1]) > 0.9 * np.abs(X[:, 0]).max(),
                                                       np.sign(X[:, :1]) * [[3.0, 0.0, 0.0]], 0.0))
    ood = out_of_distribution(cal, wider, case.plan)
    assert ood["shape"]["rms_to_nearest_subject_mm"] < cal.shape_spread_mm
    assert ood["outside"] and "outside the box" in ood["reasons"][0]
    assert ood["shape"]["outside_envelope_mm"] == pytest.approx(3.0)


@pytest.mark.parametrize("tolerance", [0.0, -1.0, float("nan"), float("inf"), "0.5"])
def test_a_tolerance_that_is_not_a_positive_number_is_refused(calibrated, tolerance):
    model, cal = calibrated
    case = load_case(resolution="coarse")
    with pytest.raises(ValueError, match="expected a positive number of mm"):
        answer(model, case.subject, case.plan, tolerance, calibration=cal)


def test_cli_calibrate_and_predict_within_a_tolerance(hard_model, db100, tmp_path):
    model = tmp_path / "model"
    shutil.copytree(hard_model.directory, model)

    def run(*args):
        return subprocess.run([sys.executable, "-m", "toolkit", "static", *args], capture_output=True, text=True)

    r = run("predict", "--model", str(model), "--resolution", "coarse", "--tolerance", "0.5", "--out",
            str(tmp_path / "p0"))
    assert r.returncode != 0 and "toolkit static calibrate --model" in r.stderr
    assert not (tmp_path / "p0").exists()
    r = run("calibrate", "--model", str(model), "--data", str(db100), "--coverage", "0.8")
    assert r.returncode == 0, r.stderr
    assert "bounds it at 80%" in r.stdout and "answers with the pair whose expected time" in r.stdout
    r = run("predict", "--model", str(model), "--resolution", "coarse", "--tolerance", "1000", "--out",
            str(tmp_path / "p1"), "--no-preview")
    assert r.returncode == 0, r.stderr
    summary = json.loads((tmp_path / "p1" / "summary.json").read_text())
    assert summary["answer"]["answered_by"] in ("surrogate", "baseline", "fe")  # the packaged plan may lie outside
    assert "answered by" in r.stdout
    r = run("predict", "--model", str(model), "--resolution", "coarse", "--tolerance", "0.5", "--coverage", "0.99",
            "--out", str(tmp_path / "p2"))
    assert r.returncode != 0 and "at least 99" in r.stderr and not (tmp_path / "p2").exists()
