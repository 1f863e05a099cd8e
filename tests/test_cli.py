"""The command line a new user meets first."""

import argparse
import contextlib
import io as io_lib
import json
import subprocess
import sys
from pathlib import Path

import pytest

from toolkit.cli import build_parser, main
from toolkit.cli._common import Parser
from toolkit.common.meshes import io


def test_demo_writes_validated_phantoms(tmp_path):
    """``toolkit demo`` writes the three coarse phantoms as .inp and .vtu with all sets,
    PNG previews and a summary, and runs the static workflow on the coarse face."""
    out = tmp_path / "demo-output"
    assert main(["demo", "--out", str(out)]) == 0
    for name in ("face_hex", "face_tet10", "ball"):
        for suffix in (".inp", ".vtu", ".png"):
            assert (out / f"{name}{suffix}").stat().st_size > 0, name + suffix
    face = io.read(out / "face_hex.inp", require_node_sets=["fixed", "maxilla", "mandible", "mucosa_sliding",
                                                            "lip_sliding", "skin"], require_element_sets=["lip_muscle"])
    face.check()
    assert io.read(out / "face_tet10.vtu").volume_type == "tet10"
    summary = json.loads((out / "summary.json").read_text())
    assert {r["mesh"] for r in summary["meshes"]} == {"face_hex", "face_tet10", "ball"}
    assert all(r["min_scaled_jacobian"] > 0 for r in summary["meshes"])
    assert summary["static"]["increments"] == 3 and summary["static"]["max_penetration_mm"] <= 1e-9
    assert (out / "static" / "result.vtu").exists() and (out / "static" / "preview.png").exists()
    assert summary["impact"]["energy_error"] < 0.02 and (out / "impact" / "face.xdmf").exists()


def _subcommands(parser, path=()):
    """``(path, parser)`` of the top-level parser and of every subcommand, depth first."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _subcommands(sub, (*path, name))


SUBCOMMANDS = [path for path, _ in _subcommands(build_parser())]


def test_python_m_toolkit_is_the_toolkit_command(tmp_path):
    """``python -m toolkit`` runs the same command line: help, a command, and an error with its
    exit code 2."""
    done = subprocess.run([sys.executable, "-m", "toolkit", "--help"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "usage: toolkit" in done.stdout
    for name in ("demo", "phantom", "static", "impact"):
        assert name in done.stdout
    done = subprocess.run([sys.executable, "-m", "toolkit", "phantom", "face-tet4", "--out", str(tmp_path / "f.vtu")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and io.read(tmp_path / "f.vtu").volume_type == "tet4"
    done = subprocess.run([sys.executable, "-m", "toolkit", "phantom", "face-hex", "--mouth-open", "40", "--out",
                           str(tmp_path / "g.vtu")], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stderr.startswith("error: ")


def test_building_the_parser_loads_no_numerical_library():
    """Every command pays for its parser: building it imports neither torch, nor scipy's image or
    sparse modules, nor the mesher (a fresh interpreter, so that other tests' imports do not count)."""
    code = ("import sys\nfrom toolkit.cli import build_parser\nbuild_parser()\n"
            "heavy = ('torch', 'scipy.ndimage', 'scipy.sparse', 'pyamg', 'meshio')\n"
            "print(sorted(m for m in heavy if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]", done.stdout


def test_every_command_has_help():
    """Every command and subcommand answers ``--help`` (exit 0) with its usage line."""
    assert len(SUBCOMMANDS) == 1 + 6 + 6 + 6  # toolkit, its 6 commands, static's 6, impact's 6
    for path in SUBCOMMANDS:
        out = io_lib.StringIO()
        with pytest.raises(SystemExit) as done, contextlib.redirect_stdout(out):
            main([*path, "--help"])
        assert done.value.code == 0, path
        assert out.getvalue().startswith(f"usage: {' '.join(('toolkit', *path))}"), path


@pytest.mark.parametrize("path", [p for p in SUBCOMMANDS if p not in [(), ("static",), ("impact",)]],
                         ids=" ".join)
def test_every_option_shows_its_default(path):
    """Each option that takes a value and is not required says its default in ``--help``
    (argparse's value, or in words where the value is None: "the scene's", "the packaged
    bimaxillary plan", ...); flags are off unless given."""
    parser = dict(_subcommands(build_parser()))[path]
    printed = " ".join(parser.format_help().split())
    formatter = parser._get_formatter()
    for action in parser._actions:
        if not action.option_strings or action.nargs == 0 or action.required:
            continue
        text = " ".join(formatter._expand_help(action).split()) if action.help else ""
        assert "default" in text, (path, action.option_strings)
        if action.default is not None and "default" not in action.help:
            assert f"(default: {action.default})" in printed, (path, action.option_strings)


def test_impact_train_configurations_are_named_paper_strong_baseline(monkeypatch, capsys):
    """``toolkit impact train --config strong`` trains that configuration; ``--help`` lists paper,
    strong and baseline, and another name (``seed``) is refused with the choices."""
    import toolkit.impact.surrogate as surrogate

    received = {}

    def stop(data, cfg, split, **kwargs):
        received["cfg"] = cfg
        raise RuntimeError("stopped before training")

    monkeypatch.setattr(surrogate, "train_surrogate", stop)
    parser = dict(_subcommands(build_parser()))[("impact", "train")]
    assert "{paper,strong,baseline}" in parser.format_help()
    assert main(["impact", "train", "--data", "db.h5", "--out", "model", "--config", "strong"]) == 2
    assert "error: stopped before training" in capsys.readouterr().err
    assert received["cfg"] is surrogate.CONFIGS["strong"]
    with pytest.raises(SystemExit):
        main(["impact", "train", "--data", "db.h5", "--out", "model", "--config", "seed"])
    assert "invalid choice: 'seed'" in capsys.readouterr().err


def test_phantom_command_and_clear_errors(tmp_path, capsys):
    assert main(["phantom", "face-tet4", "--seed", "3", "--out", str(tmp_path / "f.vtu")]) == 0
    assert io.read(tmp_path / "f.vtu").volume_type == "tet4"
    assert main(["phantom", "face-hex", "--mouth-open", "40", "--out", str(tmp_path / "g.vtu")]) == 2
    assert "mouth_open = 40.0 mm is outside the validated range [0.0, 12.0]" in capsys.readouterr().err


def test_static_simulate_writes_the_documented_outputs(tmp_path):
    """``toolkit static simulate`` with no arguments but --out runs the packaged plan on the
    coarse phantom and writes result.vtu (displacement, boundary_type), the increments as
    XDMF, summary.json with the documented keys, and preview.png."""
    out = tmp_path / "static"
    assert main(["static", "simulate", "--out", str(out)]) == 0
    result = io.read(out / "result.vtu")
    assert result.point_data["displacement"].shape == (result.n_points, 3)
    assert set(result.point_data["boundary_type"].tolist()) <= {0, 1, 2, 3, 4}
    series = io.read_time_series(out / "increments.xdmf")
    assert series.point_data["displacement"].shape == (4, result.n_points, 3)
    summary = json.loads((out / "summary.json").read_text())
    for key in ("nodes", "elements", "increments", "wall_time_s", "max_displacement_mm", "min_scaled_jacobian",
                "max_penetration_mm"):
        assert key in summary, key
    assert summary["increments"] == 3 and summary["min_scaled_jacobian"] > 0
    assert (out / "preview.png").stat().st_size > 0
    # the folder says what ran, with which toolkit, and how to run it again
    from toolkit import __version__
    from toolkit.static import SurgicalPlan, default_plan, load_case

    assert summary["toolkit_version"] == __version__
    from toolkit.static.boundary import NodeType

    assert set(summary["boundary_type_codes"]) == {str(int(t)) for t in NodeType}  # the legend of boundary_type
    assert summary["command"] == f"toolkit static simulate --out {out}"
    ran = SurgicalPlan.read(out / "plan.toml")
    assert ran.to_dict() == default_plan(load_case(resolution="coarse").subject).to_dict()


def test_version_and_did_you_mean(capsys):
    """``toolkit --version`` prints the version; a mistyped option is reported by its subcommand
    with the closest option, and a mistyped subcommand with the closest one."""
    from toolkit import __version__

    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and capsys.readouterr().out.strip() == f"toolkit {__version__}"
    with pytest.raises(SystemExit) as info:
        main(["static", "simulate", "--resolutoin", "coarse", "--no-previw", "--out", "x"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "usage: toolkit static simulate" in err
    assert "unrecognized arguments: --resolutoin coarse --no-previw; did you mean --resolution for --resolutoin, " \
           "--no-preview for --no-previw?" in err
    with pytest.raises(SystemExit):
        main(["impact", "simulat"])
    assert "invalid choice: 'simulat'" in (err := capsys.readouterr().err) and "did you mean 'simulate'?" in err
    with pytest.raises(SystemExit):
        main(["static", "simulate", "--out", "x", "--zzz"])
    assert "unrecognized arguments: --zzz\n" in capsys.readouterr().err


def test_static_simulate_from_a_mesh_file_and_plan(tmp_path):
    """A face read from Abaqus with a plan file (pivots given) runs the same workflow."""
    from toolkit.common import face_hex
    from toolkit.static import default_plan

    ph = face_hex("coarse")
    io.write(tmp_path / "face.inp", ph.mesh)
    default_plan(ph).write(tmp_path / "plan.toml")
    out = tmp_path / "run"
    assert main(["static", "simulate", "--mesh", str(tmp_path / "face.inp"), "--plan", str(tmp_path / "plan.toml"),
                 "--sliding", "mucosa", "--no-preview", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["nodes"] == ph.mesh.n_points and summary["min_scaled_jacobian"] > 0


@pytest.mark.long  # a Dask cluster's start-up / a factorization of a 3D grid: ~8 s each
def test_static_database_on_a_local_dask_cluster(tmp_path, capsys):
    """`--dask local` runs the simulations on a LocalCluster and fills the same database index
    as in-process generation."""
    pytest.importorskip("distributed")
    from toolkit.static.database import read_samples

    common = ["static", "database", "--resolution", "coarse", "--plans", "2"]
    assert main([*common, "--workers", "1", "--dask", "local", "--out", str(tmp_path / "dask.h5")]) == 0
    assert main([*common, "--workers", "0", "--out", str(tmp_path / "local.h5")]) == 0
    a, b = read_samples(tmp_path / "dask.h5"), read_samples(tmp_path / "local.h5")
    assert len(a) == 6 and (a.status == "ok").all()
    assert a[["key", "increment", "lefort_tx", "distal_ry"]].equals(b[["key", "increment", "lefort_tx", "distal_ry"]])


OUT_COMMANDS = [
    ["static", "simulate"], ["static", "train", "--data", "db.h5"], ["static", "evaluate", "--model", "m", "--data",
                                                                        "db.h5"],
    ["static", "predict", "--model", "m"], ["static", "database", "--plans", "2"], ["impact", "simulate"],
    ["impact", "train", "--data", "db.h5"], ["impact", "evaluate", "--model", "m", "--data", "db.h5"],
    ["impact", "predict", "--model", "m", "--velocity", "30"], ["impact", "database"], ["demo"],
    ["phantom", "face-tet4"],
]


@pytest.mark.parametrize("command", OUT_COMMANDS, ids=" ".join)
def test_an_unwritable_output_is_refused_before_any_computation(command, tmp_path, monkeypatch, capsys):
    """``--out`` under ``/proc``, an existing file where a folder goes or an existing folder where
    a file goes is refused at once (exit 2, the path and ``--out`` named), before the inputs are
    even read: the inputs named here do not exist, and the library's simulate/train functions
    fail the test if called."""
    import importlib

    def ran(*args, **kwargs):
        raise AssertionError("the computation ran")

    for module, name in [("static.simulate", "simulate"), ("impact.simulate", "simulate"),
                         ("static.surrogate", "train_surrogate"), ("impact.surrogate", "train_surrogate"),
                         ("static.database", "build_database"), ("impact.database", "build_database")]:
        monkeypatch.setattr(importlib.import_module(f"toolkit.{module}"), name, ran)
    existing = tmp_path / "face.inp"
    existing.write_text("results of an earlier run")
    writes_a_file = command[0] == "phantom" or "database" in command
    for out in ["/proc/x", str(tmp_path if writes_a_file else existing)]:
        assert main([*command, "--out", out]) == 2, out
        err = capsys.readouterr().err
        assert err.startswith("error: ") and repr(out) in err and "--out" in err, err
    assert existing.read_text() == "results of an earlier run"


def test_the_library_refuses_an_unwritable_out_before_computing(tmp_path):
    """The same check where ``out`` enters the library: toolkit.impact.simulate and both
    train_surrogate functions refuse before building a model or opening a database."""
    from toolkit.common.outputs import OutputError
    from toolkit.impact import default_scene, simulate
    from toolkit.impact.surrogate import train_surrogate as train_impact
    from toolkit.static.surrogate import train_surrogate as train_static

    (tmp_path / "face.inp").write_text("x")
    with pytest.raises(OutputError, match="is an existing file"):
        simulate(default_scene(), out=tmp_path / "face.inp")
    with pytest.raises(OutputError, match="model directory '/proc/x'"):
        train_impact(tmp_path / "missing.h5", out="/proc/x")
    with pytest.raises(OutputError, match="model directory '/proc/x'"):
        train_static(tmp_path / "missing.h5", out="/proc/x")


def _big_plan(path):
    """The packaged plan with a 14 mm Le Fort I advance (more than twice the 6.3 mm range), force = false."""
    path.write_text("force = false\n[lefort]\ntranslation_mm = [0.0, 14.0, 0.0]\n")
    return path


def _stop_simulation(monkeypatch, received):
    from toolkit.static.case import StaticCase

    def stop(case, **kwargs):
        received["case"] = case
        raise RuntimeError("stopped before simulating")

    monkeypatch.setattr(StaticCase, "simulate", stop)


def test_force_applies_to_a_plan_file(tmp_path, monkeypatch, capsys):
    """``static simulate --plan big.toml --force`` accepts a plan file beyond twice the range
    (the file says force = false); without --force the error names the option --force."""
    plan = _big_plan(tmp_path / "big.toml")
    received = {}
    _stop_simulation(monkeypatch, received)
    assert main(["static", "simulate", "--plan", str(plan), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert "more than twice" in err and "(command line: --force)" in err and "case" not in received
    with pytest.warns(UserWarning, match="accepted because force=True"):
        assert main(["static", "simulate", "--plan", str(plan), "--force", "--out", str(tmp_path / "run")]) == 2
    assert "error: stopped before simulating" in capsys.readouterr().err
    assert received["case"].plan.force and received["case"].plan.motions["lefort"].translation_mm == 14.0


def test_units_option_reads_a_mesh_in_metres(tmp_path, monkeypatch, capsys):
    """A face written in metres is refused with a remedy naming --units m, and read in mm with it."""
    from toolkit.common import face_hex
    from toolkit.static import default_plan

    ph = face_hex("coarse")
    io.write(tmp_path / "face_m.inp", ph.mesh.with_points(ph.mesh.points / 1000.0))
    default_plan(ph).write(tmp_path / "plan.toml")
    received = {}
    _stop_simulation(monkeypatch, received)
    args = ["static", "simulate", "--mesh", str(tmp_path / "face_m.inp"), "--plan", str(tmp_path / "plan.toml"),
            "--out", str(tmp_path / "run")]
    assert main(args) == 2
    assert "--units m" in capsys.readouterr().err and "case" not in received
    assert main([*args, "--units", "m"]) == 2
    assert "error: stopped before simulating" in capsys.readouterr().err
    assert received["case"].mesh.points == pytest.approx(ph.mesh.points)


def test_axes_option_reads_a_mesh_in_lps(tmp_path, monkeypatch, capsys):
    """A face written in LPS (y posterior, as DICOM) is refused before simulating with a remedy
    naming --axes LPS, and read back to the phantom's points with it."""
    from toolkit.common import face_hex
    from toolkit.common.meshes.axes import mesh_to_toolkit
    from toolkit.static import default_plan

    ph = face_hex("coarse")
    io.write(tmp_path / "face_lps.inp", mesh_to_toolkit(ph.mesh, "LPS"))
    default_plan(ph).write(tmp_path / "plan.toml")
    received = {}
    _stop_simulation(monkeypatch, received)
    args = ["static", "simulate", "--mesh", str(tmp_path / "face_lps.inp"), "--plan", str(tmp_path / "plan.toml"),
            "--out", str(tmp_path / "run")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "face_lps.inp is not in the toolkit's axes" in err and "--axes LPS" in err and "case" not in received
    assert main([*args, "--axes", "LPS"]) == 2
    assert "error: stopped before simulating" in capsys.readouterr().err
    assert received["case"].mesh.points == pytest.approx(ph.mesh.points)
    assert main(["impact", "simulate", "--axes", "LPS", "--out", str(tmp_path / "impact")]) == 2
    assert "--axes LPS applies to a --mesh file" in capsys.readouterr().err


def test_defaults_are_the_best_measured_configurations(monkeypatch, capsys):
    """static train: hard variant with the linear prior; impact train: the strong LSTM;
    impact simulate: the quasi-static integrator (the scene's own with --scene), and an explicit-only
    option without ``--integrator explicit`` refused."""
    parsers = dict(_subcommands(build_parser()))
    args = parsers[("static", "train")].parse_args(["--data", "db.h5", "--out", "m"])
    assert args.variant == "hard" and args.linear_prior is True
    args = parsers[("static", "train")].parse_args(["--data", "db.h5", "--out", "m", "--variant", "explicit",
                                                    "--no-linear-prior"])
    assert args.variant == "explicit" and args.linear_prior is False
    assert parsers[("impact", "train")].parse_args(["--data", "db.h5", "--out", "m"]).config == "strong"
    import importlib

    received = {}

    def stop(scene, **kwargs):
        received["scene"] = scene
        raise RuntimeError("stopped before simulating")

    monkeypatch.setattr(importlib.import_module("toolkit.impact.simulate"), "simulate", stop)
    assert main(["impact", "simulate", "--out", "unused"]) == 2
    assert received["scene"].fidelity.integrator == "quasi-static"
    assert main(["impact", "simulate", "--integrator", "explicit", "--safety", "0.5", "--out", "unused"]) == 2
    assert received["scene"].fidelity.integrator == "explicit" and received["scene"].fidelity.safety == 0.5
    received.clear()  # an explicit-only option without --integrator explicit is refused before any run
    assert main(["impact", "simulate", "--mass-scaling", "100", "--out", "unused"]) == 2
    assert "scene" not in received
    assert "--mass-scaling 100 applies to the explicit integrator only" in capsys.readouterr().err


def test_every_remedy_names_an_option_that_exists():
    """Library messages give the command-line spelling of their remedy as ``(command line: --x)``
    or ``(--x ...)``; every such option exists on some command."""
    import re
    from pathlib import Path

    import toolkit

    options = {o for _, p in _subcommands(build_parser()) for a in p._actions for o in a.option_strings}
    named = set()
    for source in Path(toolkit.__file__).parent.rglob("*.py"):
        named |= set(re.findall(r"(?:command line: |\()(--[a-z][a-z-]*)", source.read_text()))
    assert {"--force", "--units", "--safety", "--integrator"} <= named
    assert named <= options, named - options


def test_an_error_starts_its_own_line_after_a_progress_bar(monkeypatch, capsys):
    """An error raised while a progress bar is open is printed on a fresh line, not at the end
    of the bar's line."""
    import sys

    from tqdm import tqdm

    def fail(args):
        bar = tqdm(total=10, desc="increments", file=sys.stderr)
        bar.update(3)
        raise ValueError("the solve failed")

    args = build_parser().parse_args(["static", "simulate", "--out", "unused"])
    args.func = fail
    monkeypatch.setattr(Parser, "parse_args", lambda self, argv=None: args)
    assert main([]) == 2
    lines = capsys.readouterr().err.split("\n")
    assert "error: the solve failed" in lines, lines


@pytest.mark.parametrize("workflow", ["static", "impact"])
def test_train_refuses_to_overwrite_an_interrupted_training(workflow, tmp_path, capsys):
    """``train`` without --resume on a model directory holding only checkpoint.pt (an interrupted
    training) is refused before the database is read, naming --resume; the checkpoint is kept."""
    (tmp_path / "checkpoint.pt").write_bytes(b"finished epochs")
    assert main([workflow, "train", "--data", str(tmp_path / "missing.h5"), "--out", str(tmp_path)]) == 2
    assert "interrupted training" in capsys.readouterr().err
    assert (tmp_path / "checkpoint.pt").read_bytes() == b"finished epochs"


@pytest.mark.parametrize("argv, expected", [
    (["static", "simulate", "--threads", "0"], "argument --threads: expected an integer >= 1, got '0'"),
    (["static", "train", "--data", "db.h5", "--epochs", "0"], "argument --epochs: expected an integer >= 1"),
    (["static", "train", "--data", "db.h5", "--batch-size", "2.5"], "argument --batch-size: expected an integer"),
    (["static", "train", "--data", "db.h5", "--lr", "nan"], "argument --lr: expected a number > 0, got 'nan'"),
    (["impact", "train", "--data", "db.h5", "--max-minutes", "-1"], "argument --max-minutes: expected a number > 0"),
])
def test_counts_and_rates_are_checked_as_the_options_are_read(argv, expected, capsys):
    """Thread, epoch and batch counts, the learning rate and time limits are refused by the parser
    (usage error, exit 2), not deep in a run or as a traceback."""
    with pytest.raises(SystemExit) as done:
        main([*argv, "--out", "unused"])
    assert done.value.code == 2 and expected in capsys.readouterr().err


def test_an_empty_velocity_list_is_refused_not_replaced_by_the_default(monkeypatch, capsys):
    """``impact database --velocities ''`` is refused: it does not start the default nine runs."""
    import importlib

    def ran(*args, **kwargs):
        raise AssertionError("the database build ran")

    monkeypatch.setattr(importlib.import_module("toolkit.impact.database"), "build_database", ran)
    assert main(["impact", "database", "--velocities", "", "--out", "unused.h5"]) == 2
    assert "--velocities gives no velocity" in capsys.readouterr().err


@pytest.mark.parametrize("argv, expected", [
    (["static", "simulate", "--plan", "missing.toml"], "plan file 'missing.toml' does not exist"),
    (["impact", "simulate", "--scene", "missing.toml"], "scene file 'missing.toml' does not exist"),
    (["static", "simulate", "--mesh", "missing.inp", "--plan", "missing.toml"], "does not exist"),
])
def test_a_missing_input_file_is_named_with_its_option(argv, expected, tmp_path, capsys):
    assert main([*argv, "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert expected in err and "[Errno" not in err, err


def test_a_full_disk_is_an_error_line_not_a_traceback(monkeypatch, capsys):
    """An OSError while writing (no space left, a folder made read-only mid-run) prints the file
    and the reason on one ``error:`` line, exit code 2."""
    def full(args):
        raise OSError(28, "No space left on device", "run/face.h5")

    args = build_parser().parse_args(["static", "simulate", "--out", "unused"])
    args.func = full
    monkeypatch.setattr(Parser, "parse_args", lambda self, argv=None: args)
    assert main([]) == 2
    assert capsys.readouterr().err.startswith("error: run/face.h5: No space left on device")


def test_a_write_that_fails_midway_leaves_no_result(tmp_path, monkeypatch, capsys):
    """A static result whose third file fails to write (the disk full at the increments): one
    ``error:`` line, exit 2, and the output folder holds none of the result's files, so nothing
    half-written looks complete."""
    import importlib

    simulate_module = importlib.import_module("toolkit.static.simulate")

    def full(path, *args, **kwargs):
        Path(path).with_suffix(".h5").write_bytes(b"\x89HDF partial")
        raise OSError(28, "No space left on device", str(Path(path).with_suffix(".h5")))

    monkeypatch.setattr(simulate_module, "write_time_series", full)
    out = tmp_path / "run"
    assert main(["static", "simulate", "--resolution", "coarse", "--no-preview", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("error: ") == 1 and "No space left on device" in err and "Traceback" not in err, err
    assert sorted(p.name for p in out.iterdir()) == []


def _limited_run(tmp_path, max_file_bytes: int, *argv: str) -> subprocess.CompletedProcess:
    """``python -m toolkit ARGV`` in ``tmp_path`` whose writes beyond ``max_file_bytes`` per file
    fail for real (``ulimit -f``: EFBIG from the kernel, as a full disk gives ENOSPC)."""
    import resource
    import signal

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails instead of killing the process
        resource.setrlimit(resource.RLIMIT_FSIZE, (max_file_bytes, max_file_bytes))

    return subprocess.run([sys.executable, "-m", "toolkit", *argv], cwd=tmp_path, preexec_fn=limit,
                          capture_output=True, text=True, timeout=300)


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX file-size limits")
def test_a_real_write_that_fails_is_one_error_line_and_leaves_no_result(tmp_path):
    """A kernel-refused write (no mock): the increments' HDF5 file cannot grow past 100 kB. HDF5
    reports such a failure late and then crashes; the room is checked first, so the command
    prints one ``error:`` line naming the file, exits 2, and its folder holds nothing."""
    done = _limited_run(tmp_path, 100_000, "static", "simulate", "--resolution", "coarse", "--no-preview",
                        "--out", "run")
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("error: ") == 1 and "Traceback" not in done.stderr, done.stderr
    assert "increments.h5: File too large" in done.stderr and "(ulimit -f)" in done.stderr
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == []


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX file-size limits")
def test_a_database_whose_merge_cannot_be_written_keeps_every_simulation(tmp_path):
    """Each simulation's shard fits and is kept; the merged database cannot be written: one
    ``error:`` line naming it, exit 2, and the same command without the limit merges the six
    simulations without running them again."""
    argv = ("static", "database", "--resolution", "coarse", "--plans", "6", "--workers", "0", "--out", "db.h5")
    done = _limited_run(tmp_path, 400_000, *argv)
    assert done.returncode == 2, done.stderr
    errors = [line for line in done.stderr.splitlines() if "error: " in line]
    assert len(errors) == 1 and errors[0].startswith("error: db.h5: File too large"), done.stderr
    assert "Traceback" not in done.stderr
    assert len(list((tmp_path / "db.h5.shards").glob("*.h5"))) == 6
    again = subprocess.run([sys.executable, "-m", "toolkit", *argv], cwd=tmp_path, capture_output=True, text=True,
                           timeout=300)
    assert again.returncode == 0 and "0 simulations done, 6 already there" in again.stdout, again.stderr


@pytest.mark.parametrize("argv, option", [
    (["static", "database", "--plans", "0", "--out", "db.h5"], "--plans"),
    (["impact", "simulate", "--velocity", "-30", "--out", "o"], "--velocity"),
    (["phantom", "face-hex", "--mouth-open", "-5", "--out", "f.vtu"], "--mouth-open"),
    (["impact", "database", "--ball", "rigid", "--velocities", "30,-40", "--out", "d.h5"], "--velocities"),
])
def test_a_library_error_names_the_option_the_user_typed(tmp_path, monkeypatch, capsys, argv, option):
    """The library names its parameter (``plans``, ``ball velocity``, ``mouth_open``); the command
    line adds the option typed for it, so the user reads what to change."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and f"(command line: {option})" in err, err
    assert "--ball" not in err  # typed, but not what the error is about


@pytest.mark.parametrize("argv", [["static", "database", "--resolution", "coarse", "--plans", "2"],
                                  ["impact", "database", "--resolution", "coarse", "--ball", "rigid"]])
def test_a_bad_worker_count_is_refused_before_the_database_file_is_made(tmp_path, capsys, argv):
    out = tmp_path / "d.h5"
    assert main([*argv, "--workers", "-1", "--out", str(out)]) == 2
    assert "workers must be >= 0" in capsys.readouterr().err
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_the_parser_names_the_libraries_choices():
    """The calibration choices the parser lists (kept there so that building it imports no
    numerical library) are the libraries' own."""
    from toolkit.cli import impact, static
    from toolkit.impact import trust as impact_trust
    from toolkit.static import trust as static_trust

    assert impact.IMPACT_SCALES == impact_trust.SCALES
    assert static.STATIC_SCALES == static_trust.SCALES and static.STATIC_ANSWERERS == static_trust.ANSWERERS
