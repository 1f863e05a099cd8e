"""Impact answers within a tolerance on the tiny coarse database (tests/impact/conftest.py): the
calibration is split-conformal over velocities the model never trained on, the estimate is
per node and frame, a velocity or aim beyond the training data is flagged and answered by the
quasi-static FE (equal to `simulate`'s), and bad tolerances are refused before any compute."""

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from toolkit.cli import main  # noqa: E402
from toolkit.common.meshes import io  # noqa: E402
from toolkit.common.training.conformal import conformal_rank  # noqa: E402
from toolkit.impact import trust  # noqa: E402
from toolkit.impact.database import build_database, load_database  # noqa: E402
from toolkit.impact.simulate import simulate  # noqa: E402
from toolkit.impact.surrogate import CONFIGS, Surrogate, train_surrogate  # noqa: E402

from .conftest import TINY_HELD_OUT, TINY_VELOCITIES, tiny_scene  # noqa: E402

#: every test here answers with a model trained to an accuracy, or calibrates it
pytestmark = pytest.mark.long

#: velocities of the calibration database: none trained on, 9 = the fewest a 90 % bound needs
CALIBRATION_VELOCITIES = (21.0, 23.5, 28.0, 30.0, 34.0, 37.0, 41.0, 45.5, 48.0)


@pytest.fixture(scope="module")
def calibration_db(tmp_path_factory):
    path = tmp_path_factory.mktemp("impact-cal") / "cal.h5"
    report = build_database(path, CALIBRATION_VELOCITIES, [], tiny_scene(), workers=0, progress=False)
    assert not report.failed, report.failed
    return path


@pytest.fixture(scope="module")
def model_dir(tiny_db_path, tmp_path_factory):
    """A strong LSTM trained for 80 epochs, no time limit (~7 s on an Intel Xeon), on the tiny
    database's training velocities."""
    out = tmp_path_factory.mktemp("impact-trust") / "model"
    train_surrogate(tiny_db_path, CONFIGS["strong"].with_(epochs=80, patience=None, max_seconds=None,
                                                          lr_schedule="constant"),
                    "velocity", out=out, seed=0, progress=False)
    return out


@pytest.fixture(scope="module")
def calibrated(model_dir, calibration_db, tiny_db_path):
    model = Surrogate.load(model_dir)
    cal = trust.calibrate_surrogate(model, calibration_db, training=tiny_db_path, progress=False)
    cal.save(model_dir)
    return model, cal


def test_calibration_is_the_conformal_rank_of_unseen_velocities(calibrated, calibration_db, tiny_db):
    """Every calibration velocity is one the model did not train on; the factor is the
    ceil((n + 1) 0.9)-th smallest error/scale ratio; each case's error is the p95 over nodes and
    frames recomputed here; the interpolation reproduces the training FE at its velocities and
    is linear between them; the saved calibration loads identical."""
    model, cal = calibrated
    assert [c["velocity_mm_s"] for c in cal.cases] == list(CALIBRATION_VELOCITIES)
    ratios = sorted(c["error_mm"] / c["scale_mm"] for c in cal.cases)
    assert cal.bound.factor == pytest.approx(ratios[conformal_rank(len(ratios), 0.9) - 1], rel=1e-12)
    db = load_database(calibration_db)
    u, _ = model.predict(34.0, db.inputs)
    i = int(np.flatnonzero(db.velocities == 34.0)[0])
    err = np.percentile(np.linalg.norm(u - db.displacement[i], axis=-1).ravel(), 95)
    assert cal.cases[4]["error_mm"] == pytest.approx(err, rel=1e-9)
    for v in TINY_VELOCITIES:
        j = int(np.flatnonzero(tiny_db.velocities == v)[0])
        np.testing.assert_allclose(cal.interpolate(v), tiny_db.displacement[j], atol=1e-6)
    mid = cal.interpolate(23.0)
    np.testing.assert_allclose(mid, 0.5 * (cal.interpolate(20.0) + cal.interpolate(26.0)), atol=1e-5)
    back = trust.Calibration.load(model.directory)
    assert back.bound == cal.bound and back.cases == cal.cases
    np.testing.assert_array_equal(back.fields, cal.fields)
    assert back.at(0.8).bound.factor <= cal.bound.factor


def test_too_few_unseen_velocities_are_refused(model_dir, tiny_db_path):
    """The training database holds one velocity the model did not see: a 90 % bound needs 9,
    and the error says how to build a calibration database."""
    model = Surrogate.load(model_dir)
    with pytest.raises(ValueError, match=r"holds 1 simulation.*at least 9.*toolkit impact database --velocities"):
        trust.calibrate_surrogate(model, tiny_db_path, progress=False)
    with pytest.raises(ValueError, match="scale"):
        trust.calibrate_surrogate(model, tiny_db_path, scale="ensemble", progress=False)


def test_in_range_velocity_is_answered_by_the_surrogate_within_a_loose_tolerance(calibrated):
    """At 33 mm/s (inside 20-50, on the trained aim) the surrogate answers a tolerance above its
    bound, with an estimate per frame and node whose p95 is the bound; at half the bound the
    quasi-static FE answers."""
    model, cal = calibrated
    ans = trust.answer(model, 33.0, 1000.0, calibration=cal)
    assert ans.answered_by == "surrogate" and not ans.ood["outside"]
    node = ans.estimate["node_mm"]
    assert node.shape == ans.displacement.shape[:2]
    assert np.percentile(node, 95) == pytest.approx(ans.estimate["bound_mm"], rel=1e-9)
    tight = trust.answer(model, 33.0, 0.5 * ans.estimate["bound_mm"], calibration=cal)
    assert tight.answered_by == "fe" and "above the tolerance" in tight.reason
    assert tight.seconds["fe"] > 0 and tight.fe_integrator == "quasi-static"


def test_a_velocity_beyond_the_training_falls_back_to_the_quasi_static_fe(calibrated):
    """10 mm/s lies 10 mm/s below the training velocities: flagged with that distance, answered
    by the FE whatever the tolerance, and the answer is `simulate`'s quasi-static run to 1e-9 mm."""
    model, cal = calibrated
    ans = trust.answer(model, 10.0, 1000.0, calibration=cal)
    assert ans.answered_by == "fe" and ans.reason.startswith("out of distribution: velocity")
    assert ans.ood["velocity"]["parameters"]["velocity_mm_s"]["outside_by"] == pytest.approx(10.0)
    assert ans.ood["velocity"]["nearest_training_mm_s"] == pytest.approx(10.0)
    fe = simulate(tiny_scene().with_ball(velocity=10.0).with_fidelity(integrator="quasi-static", mass_scaling=1.0))
    np.testing.assert_allclose(ans.displacement, fe.displacement, rtol=0, atol=1e-9)


def test_a_surrogate_answer_with_an_inverted_element_falls_back_to_the_fe(calibrated, monkeypatch):
    """Within a loose tolerance, a surrogate answer that folds one element in one frame fails its
    checks: the quasi-static FE answers, and the reason names the inverted element."""
    model, cal = calibrated
    predict = trust._quiet_predict

    def folding(model, velocity, inputs):
        u, vm = predict(model, velocity, inputs)
        face = model_face[0]
        cell = face.volume_cells[~inputs.fixed[face.volume_cells].any(axis=1)][0]  # no held node
        u = u.copy()
        u[-1, cell[0]] = 2.0 * (face.points[cell[1:4]].mean(axis=0) - face.points[cell[0]])
        return u, vm

    from toolkit.impact.simulate import face_mesh

    model_face = [face_mesh(tiny_scene())]
    monkeypatch.setattr(trust, "_quiet_predict", folding)
    ans = trust.answer(model, 33.0, 1000.0, calibration=cal)
    assert ans.answered_by == "fe" and "failed its checks: an element first inverts in frame" in ans.reason
    assert ans.summary()["checks"]["answer"]["passed"] and ans.seconds["checks"] > 0


def test_another_aim_is_out_of_distribution(calibrated):
    """A ball aimed 20 mm lower than the training scene's aim: the scene differs in the ball's
    target, so the FE answers even though the velocity is a trained one."""
    model, cal = calibrated
    scene = tiny_scene().with_ball(velocity=32.0, target_offset=(0.0, 0.0, 10.0))
    ood = trust.out_of_distribution(model, scene)
    assert ood["outside"] and ood["scene"]["differences"][0][0] == "ball.target_offset"
    assert not ood["velocity"]["outside"]
    same = trust.out_of_distribution(model, tiny_scene().with_ball(velocity=32.0)
                                     .with_fidelity(integrator="quasi-static", mass_scaling=1.0))
    assert not same["outside"], same["reasons"]


@pytest.mark.parametrize("tolerance", [0, -1.0, float("nan"), float("inf"), "1", True, None])
def test_bad_tolerances_are_refused_before_any_compute(calibrated, tolerance, monkeypatch):
    model, cal = calibrated
    monkeypatch.setattr(model, "predict", lambda *a, **k: pytest.fail("predicted before refusing"))
    with pytest.raises(ValueError, match="tolerance"):
        trust.answer(model, 33.0, tolerance, calibration=cal)


def test_calibrate_and_predict_within_a_tolerance_commands(model_dir, calibration_db, tiny_db_path, tmp_path, capsys):
    """`toolkit impact calibrate` saves the calibration; `predict --tolerance` writes face.xdmf with
    an error_estimate per frame and summary.json with the answer; a model without calibration
    and --coverage without --tolerance are refused naming the remedy."""
    import shutil

    bare = tmp_path / "bare"
    shutil.copytree(model_dir, bare)
    for name in ("calibration.json", "calibration.npz"):
        (bare / name).unlink(missing_ok=True)
    assert main(["impact", "predict", "--model", str(bare), "--velocity", "33", "--tolerance", "1",
                 "--out", str(tmp_path / "none")]) != 0
    assert "toolkit impact calibrate --model" in capsys.readouterr().err
    assert main(["impact", "predict", "--model", str(bare), "--velocity", "33", "--coverage", "0.8",
                 "--out", str(tmp_path / "none2")]) != 0
    assert "--coverage and --target go with --tolerance" in capsys.readouterr().err
    assert not (tmp_path / "none").exists() and not (tmp_path / "none2").exists()
    assert main(["impact", "calibrate", "--model", str(bare), "--data", str(calibration_db),
                 "--train-data", str(tiny_db_path)]) == 0
    assert "9 velocities the model did not train on" in capsys.readouterr().out
    out = tmp_path / "answer"
    assert main(["impact", "predict", "--model", str(bare), "--velocity", "33", "--tolerance", "1000",
                 "--no-preview", "--out", str(out)]) == 0
    assert "answered by the surrogate" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["answer"]["answered_by"] == "surrogate" and summary["answer"]["tolerance_mm"] == 1000.0
    series = io.read_time_series(out / "face.xdmf")
    est = series.point_data["error_estimate"]
    assert est.shape == series.point_data["displacement"].shape[:2]
    assert np.percentile(est, 95) == pytest.approx(summary["answer"]["estimate"]["bound_mm"], rel=1e-5)
    assert TINY_HELD_OUT[0] not in CALIBRATION_VELOCITIES
