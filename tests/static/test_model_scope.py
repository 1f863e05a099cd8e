"""What a static surrogate knows about its training data: an evaluation never scores a training
simulation without saying so and refuses a database of other settings; a prediction records how
far its plan lies outside the training plans."""

import json
import warnings

import numpy as np
import pytest

from toolkit.common.config_diff import IncompatibleError
from toolkit.static.database import DatabaseConfig, StaticDatabase, build_database, subject_phantom
from toolkit.static.plan import PHYSIOLOGICAL_RANGES, PlanRangeWarning, SurgicalPlan, default_plan, sample_plans
from toolkit.static.surrogate import evaluate_surrogate


def _database(tmp_path_factory, name, **kw):
    path = tmp_path_factory.mktemp("scope") / f"{name}.h5"
    build_database(path, DatabaseConfig(resolution="coarse", **kw), workers=0, progress=False)
    return path


@pytest.fixture
def model(quick_model):
    """The 2-epoch tiny model on ``db6`` (tests/static/conftest.py)."""
    return quick_model


def test_the_training_database_is_scored_on_its_test_split(db6, model):
    m = evaluate_surrogate(model, db6).metrics
    assert m["scored"] == "test split of the training database"
    assert m["training_samples_scored"] == 0
    assert m["samples"] == 3 * len(model.bundle.extra["test_keys"])


def test_another_database_is_scored_without_the_training_simulations(db6, model, tmp_path_factory):
    """A database of 8 plans with the same seed holds the 6 of the training database (plan i
    depends only on the seed and i) under the same keys: the 4 or so the model trained or
    validated on are excluded, by what they are (subject shape, plan, Poisson's ratio), and
    the metrics say how many."""
    db8 = _database(tmp_path_factory, "db8", plans=8)
    result = evaluate_surrogate(model, db8)
    m = result.metrics
    seen = len(set(StaticDatabase.open(db6).samples.key) - set(model.bundle.extra["test_keys"]))
    assert m["training_samples_excluded"] == 3 * seen
    assert m["scored"] == f"all samples of another database, {3 * seen} training samples excluded"
    assert m["samples"] == 3 * (8 - seen)
    assert not set(result.per_sample.key) - (set(StaticDatabase.open(db8).samples.key)
                                                - (set(StaticDatabase.open(db6).samples.key)
                                                   - set(model.bundle.extra["test_keys"])))


def test_a_database_of_other_plans_is_scored_whole(model, tmp_path_factory):
    """Another seed draws other plans with the same keys (s000-p00000...): nothing is excluded."""
    other = _database(tmp_path_factory, "seed1", plans=2, seed=1)
    m = evaluate_surrogate(model, other).metrics
    assert m["training_samples_excluded"] == 0 and m["samples"] == 6
    assert m["scored"].startswith("all samples of another database")


def test_requested_simulations_count_the_training_ones(db6, model):
    train_key = sorted(set(StaticDatabase.open(db6).samples.key) - set(model.bundle.extra["test_keys"]))[0]
    m = evaluate_surrogate(model, db6, keys=[train_key]).metrics
    assert m["training_samples_scored"] == 3


@pytest.mark.parametrize("setting", [{"sliding": "none"}, {"increments": 2}, {"material": "neo-hookean"}])
def test_a_database_of_other_settings_is_refused(model, tmp_path_factory, setting):
    """Another sliding model, increment count or material changes what a sample means: refused
    before scoring, naming the setting and the option that rebuilds a matching database."""
    key, value = next(iter(setting.items()))
    other = _database(tmp_path_factory, f"{key}", plans=1, **setting)
    with pytest.raises(IncompatibleError, match=f"{key}: stored .*, asked {value!r}") as info:
        evaluate_surrogate(model, other)
    assert f"--{key} " in str(info.value)
    assert [d[0] for d in info.value.differences] == [key]


def test_a_bundle_without_its_training_simulations_says_so(db6, model, tmp_path_factory):
    """A model saved without ``seen_simulations`` (or the dental arch's nodes) still scores and
    predicts, saying what it cannot know."""
    from toolkit.common.training import ModelBundle
    from toolkit.static.surrogate import Surrogate

    b = model.bundle
    extra = {k: v for k, v in b.extra.items() if k not in ("seen_simulations", "arch_nodes")}
    out = ModelBundle(b.kind, b.config, b.data, b.scalers, b.state_dict, extra).save(
        tmp_path_factory.mktemp("old") / "m")
    old = Surrogate.load(out)
    other = _database(tmp_path_factory, "old_other", plans=1, seed=2)
    m = evaluate_surrogate(old, other).metrics
    assert "does not record its training simulations" in m["scored"] and m["training_samples_excluded"] is None
    phantom = subject_phantom("coarse", 0)
    # the verdict on a plan comes from the database's sampler settings, which every model records
    assert old.predict_plan(phantom, default_plan(phantom)).summary()["extrapolation"]["outside"] in (True, False)


# ------------------------------------------------------------------ extrapolation
def test_a_training_plan_is_inside_the_training_ranges(db6, model):
    phantom = subject_phantom("coarse", 0)
    plans = sample_plans(6, np.random.default_rng([0, 0]), phantom=phantom)
    train_plans = {f"s000-p{p:05d}" for p in range(6)} - set(model.bundle.extra["test_keys"])
    plan = plans[int(sorted(train_plans)[0][-5:])]
    ex = model.predict_plan(phantom, plan).summary()["extrapolation"]
    assert ex == {"outside": False, "parameters": {}}


def test_a_plan_beyond_the_training_ranges_is_recorded(model, tmp_path):
    """A setback of 20 mm (the sampler draws distal translations up to the physiological top) is
    recorded in the summary and in summary.json: the parameter, its value, the range the training
    database's sampler spans and how far outside."""
    phantom = subject_phantom("coarse", 0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PlanRangeWarning)
        plan = SurgicalPlan.from_dict({"distal": {"translation_mm": [0.0, -20.0, 0.0]}}, phantom=phantom)
    with warnings.catch_warnings(record=True) as predicted:  # warned where the plan was built, not again
        warnings.simplefilter("always")
        result = model.predict_plan(phantom, plan)
    assert [str(w.message) for w in predicted if issubclass(w.category, PlanRangeWarning)] == []
    ex = result.summary()["extrapolation"]
    assert ex["outside"] is True
    length = ex["parameters"]["distal.translation_mm"]
    top = PHYSIOLOGICAL_RANGES["distal"].translation_mm[1]
    assert length["value"] == pytest.approx(20.0) and length["train_range"] == [0.0, top]
    assert length["outside_by"] == pytest.approx(20.0 - top, abs=1e-6) and length["outside_by"] > 0
    result.write(tmp_path / "pred", preview=False)
    assert json.loads((tmp_path / "pred" / "summary.json").read_text())["extrapolation"] == json.loads(
        json.dumps(ex))


def test_the_commands_print_what_was_scored_and_the_extrapolation(db6, model, tmp_path, capsys):
    """`toolkit static evaluate` says which samples it scored; `toolkit static predict` of a plan
    beyond the training plans says so, naming the parameter and its training range."""
    from toolkit.cli import main

    saved = model.bundle.save(tmp_path / "m")
    assert main(["static", "evaluate", "--model", str(saved), "--data", str(db6), "--out", str(tmp_path / "ev"),
                 "--no-preview"]) == 0
    assert "scored: test split of the training database" in capsys.readouterr().out
    plan = tmp_path / "plan.toml"
    plan.write_text("[distal]\ntranslation_mm = [0.0, -20.0, 0.0]\n")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PlanRangeWarning)
        assert main(["static", "predict", "--model", str(saved), "--plan", str(plan), "--out", str(tmp_path / "p"),
                     "--no-preview"]) == 0
    out = capsys.readouterr().out
    assert "plan: OUTSIDE the training data" in out and "distal.translation_mm = 20 (trained 0 to" in out
