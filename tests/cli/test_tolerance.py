"""``toolkit static|impact simulate --tolerance MM``: the fastest measured options within MM,
printed and recorded as ``fidelity`` in summary.json; options given are kept; tolerances that
are not finite positive numbers, or below the most faithful option's own uncertainty, are
refused before anything runs."""

import importlib
import json

import pytest

from toolkit.cli import main
from toolkit.common.fidelity import choose_fidelity, load_ladder

RECORD_KEYS = {"tolerance_mm", "options", "fixed", "error_mm", "metric", "reference", "uncertainty_mm",
               "wall_time_s", "measured_on", "sources"}


@pytest.fixture
def no_compute(monkeypatch):
    """The simulate functions of both workflows fail the test when called."""
    def ran(*args, **kwargs):
        raise AssertionError("the computation ran")

    for module in ("toolkit.static.simulate", "toolkit.impact.simulate"):
        monkeypatch.setattr(importlib.import_module(module), "simulate", ran)


@pytest.fixture
def captured(monkeypatch):
    """The scene (impact) or the keywords (static) a run would simulate, stopped before it runs."""
    from toolkit.static.case import StaticCase

    received = {}

    def stop_static(case, fidelity=None, **kwargs):
        received.update(case=case, fidelity=fidelity, **kwargs)
        raise RuntimeError("stopped before simulating")

    def stop_impact(scene, **kwargs):
        received.update(scene=scene, **kwargs)
        raise RuntimeError("stopped before simulating")

    monkeypatch.setattr(StaticCase, "simulate", stop_static)
    monkeypatch.setattr(importlib.import_module("toolkit.impact.simulate"), "simulate", stop_impact)
    return received


def test_static_tolerance_runs_the_choice_and_records_it(tmp_path, capsys):
    """At 1 mm the run takes the option :func:`choose_fidelity` picks from the packaged ladder
    (the fastest measured within it), prints it with its measured error, and summary.json says why."""
    choice = choose_fidelity("static", 1.0)
    out = tmp_path / "run"
    assert main(["static", "simulate", "--tolerance", "1", "--no-preview", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    options = ", ".join(f"{k} {v}" for k, v in choice.options.items())
    assert printed.startswith(f"fidelity for 1 mm: {options}; measured error {choice.error_mm:.3g} mm"), printed
    summary = json.loads((out / "summary.json").read_text())
    record = summary["fidelity"]
    assert set(record) == RECORD_KEYS
    assert record["options"] == choice.options
    assert record["error_mm"] <= 1.0 and record["tolerance_mm"] == 1.0 and record["fixed"] == {}
    assert "95th percentile" in record["metric"]
    assert [s["file"] for s in record["sources"]] == ["static_ladder.csv", "static_convergence.csv"]
    assert (summary["increments"], summary["material"], summary["sliding"]) == (
        choice.options["increments"], choice.options["material"], choice.options["sliding"])


def test_impact_tolerance_runs_the_choice_and_records_it(tmp_path, capsys):
    """At 3 mm the run takes the option :func:`choose_fidelity` picks. The scene file (coarse
    face, 0.1 s in 4 load steps) keeps the run short; the tolerance replaces its ball and
    integrator."""
    from dataclasses import replace

    from toolkit.impact import default_scene

    choice = choose_fidelity("impact", 3.0)
    scene = replace(default_scene().with_face(resolution="coarse").with_fidelity(load_steps=4), duration=0.1,
                    n_frames=2)
    scene.write(tmp_path / "scene.toml")
    out = tmp_path / "run"
    assert main(["impact", "simulate", "--scene", str(tmp_path / "scene.toml"), "--tolerance", "3", "--no-preview",
                 "--out", str(out)]) == 0
    assert f"fidelity for 3 mm: order {choice.options['order']}, ball {choice.options['ball']}" in \
        capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    record = summary["fidelity"]
    assert set(record) == RECORD_KEYS
    assert record["options"] == choice.options
    assert record["error_mm"] <= 3.0 and "coarse" in record["measured_on"] and "95th percentile" in record["metric"]
    assert summary["ball"] == choice.options["ball"]
    assert summary["element"] == ("tet10" if choice.options["order"] == 2 else "tet4")


def test_a_given_option_is_kept_and_the_choice_is_among_its_rows(captured, capsys):
    assert main(["static", "simulate", "--tolerance", "1", "--material", "neo-hookean", "--out", "unused"]) == 2
    assert captured["material"] == "neo-hookean" and captured["fidelity"].fixed == {"material": "neo-hookean"}
    assert captured["fidelity"].error_mm <= 1.0
    assert main(["impact", "simulate", "--tolerance", "3", "--ball", "deformable", "--out", "unused"]) == 2
    scene = captured["scene"]
    assert scene.ball.rigid is False and scene.fidelity.integrator == "quasi-static" and scene.fidelity.order == 2
    assert captured["fidelity"].options["ball"] == "deformable"
    capsys.readouterr()


@pytest.mark.parametrize("argv, expected", [
    (["static", "simulate", "--tolerance", "1", "--increments", "5"],
     "the static ladder did not measure increments = 5 (measured: 1, 3, 10)"),
    (["static", "simulate", "--tolerance", "1", "--resolution", "fine"],
     "the static ladder did not measure resolution = 'fine' (measured: coarse, paper)"),
])
def test_an_option_the_ladder_did_not_measure_is_refused(argv, expected, no_compute, capsys):
    assert main([*argv, "--out", "unused"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and expected in err, err


@pytest.mark.parametrize("workflow, fixed", [("static", {"material": "linear"}),
                                             ("impact", {"mass_scaling": 100.0, "integrator": "explicit"})])
def test_a_given_option_the_ladder_cannot_meet_is_refused(workflow, fixed, no_compute, capsys):
    """A tolerance between the most faithful option's uncertainty and the best error of the rows
    with the given options: refused, naming the options and the tolerance."""
    ladder = load_ladder(workflow)
    rows = ladder.rows
    for key, value in fixed.items():
        rows = rows[rows[key] == value]
    best = float(rows["error_mm"].min())
    assert ladder.uncertainty_mm < best, "the ladder leaves no tolerance to test this refusal with"
    tolerance = float(f"{0.5 * (ladder.uncertainty_mm + best):.3g}")
    options = {"material": "--material", "mass_scaling": "--mass-scaling", "integrator": "--integrator"}
    argv = [workflow, "simulate", "--tolerance", f"{tolerance:g}"]
    for key, value in fixed.items():
        argv += [options[key], f"{value:g}" if isinstance(value, float) else str(value)]
    assert main([*argv, "--out", "unused"]) == 2
    err = capsys.readouterr().err
    named = ", ".join(f"{k} {v:g}" if isinstance(v, float) else f"{k} {v}" for k, v in fixed.items())
    expected = f"no measured {workflow} option with {named} is within {tolerance:g} mm"
    assert err.startswith("error: ") and expected in err, err


@pytest.mark.parametrize("workflow", ["static", "impact"])
def test_a_tolerance_below_the_reference_uncertainty_is_refused_before_computing(workflow, no_compute, tmp_path,
                                                                                 capsys):
    uncertainty = load_ladder(workflow).uncertainty_mm
    tolerance = f"{0.8 * uncertainty:.2g}"
    out = tmp_path / "run"
    assert main([workflow, "simulate", "--tolerance", tolerance, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"tolerance {tolerance} mm is below the uncertainty" in err and f"{uncertainty:.3g} mm" in err, err
    assert "Give a tolerance of at least" in err and not (out / "summary.json").exists()


@pytest.mark.parametrize("workflow", ["static", "impact"])
@pytest.mark.parametrize("bad", ["0", "-1", "nan", "inf", "one"])
def test_a_tolerance_that_is_not_a_finite_positive_number_is_refused(workflow, bad, no_compute, capsys):
    with pytest.raises(SystemExit) as done:
        main([workflow, "simulate", "--tolerance", bad, "--out", "unused"])
    err = capsys.readouterr().err
    assert done.value.code == 2
    assert f"argument --tolerance: expected a tolerance in mm, a finite number > 0 such as 0.5, got '{bad}'" in err
