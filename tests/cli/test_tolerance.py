"""``toolkit static|impact simulate --tolerance MM``: the fastest measured options within MM,
printed and recorded as ``fidelity`` in summary.json; options given are kept; tolerances that
are not finite positive numbers, or below the most faithful option's own uncertainty, are
refused before anything runs."""

import importlib
import json

import pytest

from toolkit.cli import main

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
    """At 1 mm the coarse phantom, linear, 1 increment, mucosa + lip sliding is the fastest
    measured option (0.64 mm); the run takes it and summary.json says why."""
    out = tmp_path / "run"
    assert main(["static", "simulate", "--tolerance", "1", "--no-preview", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("fidelity for 1 mm: resolution coarse, material linear, increments 1, sliding "
                              "mucosa+lip; measured error 0.644 mm")
    summary = json.loads((out / "summary.json").read_text())
    record = summary["fidelity"]
    assert set(record) == RECORD_KEYS
    assert record["options"] == {"resolution": "coarse", "material": "linear", "increments": 1,
                                 "sliding": "mucosa+lip"}
    assert record["error_mm"] <= 1.0 and record["tolerance_mm"] == 1.0 and record["fixed"] == {}
    assert [s["file"] for s in record["sources"]] == ["static_ladder.csv", "static_convergence.csv"]
    assert (summary["increments"], summary["material"], summary["sliding"]) == (1, "linear", "mucosa+lip")
    assert summary["nodes"] < 2000  # the coarse phantom


def test_impact_tolerance_runs_the_choice_and_records_it(tmp_path, capsys):
    """At 1 mm the quasi-static tet10 run with a rigid ball is the fastest measured (0.455 mm).
    The scene file (coarse face, 0.1 s in 4 load steps, deformable explicit) keeps the run short;
    the tolerance replaces its ball and integrator."""
    from dataclasses import replace

    from toolkit.impact import default_scene

    scene = replace(default_scene().with_face(resolution="coarse").with_fidelity(load_steps=4), duration=0.1,
                    n_frames=2)
    scene.write(tmp_path / "scene.toml")
    out = tmp_path / "run"
    assert main(["impact", "simulate", "--scene", str(tmp_path / "scene.toml"), "--tolerance", "1", "--no-preview",
                 "--out", str(out)]) == 0
    assert "fidelity for 1 mm: order 2, ball rigid" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    record = summary["fidelity"]
    assert set(record) == RECORD_KEYS
    assert record["options"] == {"order": 2, "ball": "rigid", "mass_scaling": 1.0, "safety": 0.9,
                                 "integrator": "quasi-static"}
    assert record["error_mm"] <= 1.0 < record["uncertainty_mm"] + 1.0 and "coarse" in record["measured_on"]
    assert summary["ball"] == "rigid" and summary["element"] == "tet10"


def test_a_given_option_is_kept_and_the_choice_is_among_its_rows(captured, capsys):
    assert main(["static", "simulate", "--tolerance", "1", "--material", "neo-hookean", "--out", "unused"]) == 2
    assert captured["material"] == "neo-hookean" and captured["fidelity"].fixed == {"material": "neo-hookean"}
    assert captured["fidelity"].error_mm <= 1.0
    assert main(["impact", "simulate", "--tolerance", "1", "--ball", "deformable", "--out", "unused"]) == 2
    scene = captured["scene"]
    assert scene.ball.rigid is False and scene.fidelity.integrator == "quasi-static" and scene.fidelity.order == 2
    assert captured["fidelity"].options["ball"] == "deformable"
    capsys.readouterr()


@pytest.mark.parametrize("argv, expected", [
    (["static", "simulate", "--tolerance", "1", "--increments", "5"],
     "the static ladder did not measure increments = 5 (measured: 1, 3, 10)"),
    (["static", "simulate", "--tolerance", "1", "--resolution", "fine"],
     "the static ladder did not measure resolution = 'fine' (measured: coarse, paper)"),
    (["static", "simulate", "--tolerance", "0.25", "--material", "linear"],
     "no measured static option with material linear is within 0.25 mm"),
    (["impact", "simulate", "--tolerance", "1", "--integrator", "explicit", "--mass-scaling", "100"],  # 1.26 mm at best
     "no measured impact option with mass_scaling 100, integrator explicit is within 1 mm"),
])
def test_a_given_option_the_ladder_cannot_meet_is_refused(argv, expected, no_compute, capsys):
    assert main([*argv, "--out", "unused"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and expected in err, err


@pytest.mark.parametrize("workflow, tolerance, uncertainty", [("static", "0.1", "0.126 mm"),
                                                               ("impact", "0.5", "0.765 mm")])
def test_a_tolerance_below_the_reference_uncertainty_is_refused_before_computing(workflow, tolerance, uncertainty,
                                                                                 no_compute, tmp_path, capsys):
    out = tmp_path / "run"
    assert main([workflow, "simulate", "--tolerance", tolerance, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"tolerance {tolerance} mm is below the uncertainty" in err and uncertainty in err
    assert "Give a tolerance of at least" in err and not (out / "summary.json").exists()


@pytest.mark.parametrize("workflow", ["static", "impact"])
@pytest.mark.parametrize("bad", ["0", "-1", "nan", "inf", "one"])
def test_a_tolerance_that_is_not_a_finite_positive_number_is_refused(workflow, bad, no_compute, capsys):
    with pytest.raises(SystemExit) as done:
        main([workflow, "simulate", "--tolerance", bad, "--out", "unused"])
    err = capsys.readouterr().err
    assert done.value.code == 2
    assert f"argument --tolerance: expected a tolerance in mm, a finite number > 0 such as 0.5, got '{bad}'" in err
