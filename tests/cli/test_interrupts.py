"""A Ctrl-C in any command: exit code 130, one ``interrupted: ...`` line that says how to finish,
no traceback, and an output folder that holds nothing or a result marked as interrupted.

Each command runs as ``python -m toolkit`` does (``toolkit/__main__.py``), in its own process
group, and gets a SIGINT (what a terminal sends on Ctrl-C) at a known point of its work, so that
a slow machine gives the verdict a fast one gives: after its first stored simulation or written
frame or its first increment (:func:`toolkit.common.runtime.interrupt_after`), or as the module
of a network starts to be imported. The tiny coarse fixtures keep each
case to seconds. Interrupts at fractions of each command's run, then a rerun, are
``benchmarks/bad_inputs.py --interrupts``."""

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest

#: coarse impact options: a rigid ball on the tet4 face
IMPACT = ["--resolution", "coarse", "--order", "1", "--ball", "rigid"]

#: SIGINT to the command's process group (its worker processes too) once its first simulation is stored
AFTER_FIRST_JOB = "from toolkit.common.runtime import interrupt_after\ninterrupt_after('job', 1, group=True)\n"
#: SIGINT once the second frame is written
AFTER_SECOND_FRAME = "from toolkit.common.runtime import interrupt_after\ninterrupt_after('frame', 2)\n"
#: SIGINT once the static simulation's first increment has reached equilibrium
AFTER_FIRST_INCREMENT = "from toolkit.common.runtime import interrupt_after\ninterrupt_after('increment', 1)\n"
#: SIGINT as the import of module ``{module}`` begins (the import then runs on)
AT_IMPORT = """\
import signal, sys

class CtrlC:
    def find_spec(self, name, path=None, target=None):
        if name == "{module}":
            sys.meta_path.remove(self)
            signal.raise_signal(signal.SIGINT)
        return None

sys.meta_path.insert(0, CtrlC())
"""
#: the module each model's loading imports first: the static network runs in numpy on the CPU
#: (no torch), the impact one in torch
NETWORK_MODULE = {"static": "toolkit.static.pointnet2_inference", "impact": "torch"}


def interrupted(args, cwd: Path, trigger: str, timeout: float = 120) -> tuple[int, str]:
    """Run ``toolkit ARGS`` in ``cwd`` as ``python -m toolkit`` does, in a new process group, after
    the Python lines ``trigger`` that arrange its SIGINT; return (exit code, stderr)."""
    script = f"{trigger}\nimport runpy\nrunpy.run_module('toolkit', run_name='__main__', alter_sys=True)\n"
    # SIGINT's default action in the command (a test run started in the background ignores it)
    done = subprocess.run([sys.executable, "-c", script, *map(str, args)], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout, start_new_session=True,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    return done.returncode, done.stderr


def assert_interrupted(code: int, err: str) -> None:
    assert code == 130, f"exit {code} (0: the command ended before its interrupt)\n{err[-2000:]}"
    assert "Traceback" not in err, err[-2000:]
    assert "leaked" not in err, err[-2000:]
    lines = [ln for ln in err.splitlines() if ln.startswith("interrupted: ")]
    assert len(lines) == 1 and "rerun the same command" in lines[0], err[-2000:]


def assert_nothing_or_marked(out: Path) -> None:
    """The output folder holds nothing, or a summary.json whose status says the run did not finish."""
    files = sorted(p.name for p in out.iterdir()) if out.exists() else []
    if not files:
        return
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] in ("interrupted", "failed"), files


def test_a_database_run_on_worker_processes(tmp_path):
    """Interrupted once its first simulation is stored (the Ctrl-C reaches the worker process
    too): the worker stops without a traceback or a leaked semaphore, and the database holds the
    simulations finished by then and says it is not complete."""
    from toolkit.common.training.database import database_status

    args = ["static", "database", "--resolution", "coarse", "--plans", "8", "--workers", "1", "--out", "db.h5"]
    assert_interrupted(*interrupted(args, tmp_path, AFTER_FIRST_JOB))
    status = database_status(tmp_path / "db.h5")
    assert status.records >= 1 and not status.complete and status.pending == 0


def test_static_simulate(tmp_path):
    """Interrupted after the first of its increments: no output folder, since the files come after
    the last increment (whose writes ignore Ctrl-C so as to finish)."""
    code, err = interrupted(["static", "simulate", "--resolution", "coarse", "--no-preview", "--out", "o"], tmp_path,
                            AFTER_FIRST_INCREMENT)
    assert_interrupted(code, err)
    assert not (tmp_path / "o").exists()


def test_impact_simulate_mid_run(tmp_path):
    """Interrupted once its second frame is written: summary.json says "interrupted", with the two
    frames."""
    args = ["impact", "simulate", *IMPACT, "--integrator", "explicit", "--no-preview", "--out", "o"]
    assert_interrupted(*interrupted(args, tmp_path, AFTER_SECOND_FRAME))
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["status"] == "interrupted" and summary["frames_written"] == 2


def test_mesh_while_its_image_renders(tmp_path):
    """Interrupted as the labels image starts to render, the mesh made: nothing written (the image
    renders before the files, which are written together)."""
    from toolkit.common import face_hex
    from toolkit.mesh.phantom import phantom_surfaces, write_surfaces

    files = write_surfaces(tmp_path / "surfaces", phantom_surfaces(face_hex("coarse")))
    bones = [f"--bone={name}={files[name]}" for name in ("lefort", "distal", "proximal_left", "proximal_right")]
    args = ["mesh", "--tissue", files["tissue"], *bones, "--size", "12", "--order", "1", "--out", "out/face.vtu"]
    (tmp_path / "out").mkdir()
    assert_interrupted(*interrupted(args, tmp_path, AT_IMPORT.replace("{module}", "toolkit.common.plotting")))
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == []


@pytest.mark.long
@pytest.mark.parametrize("command", [
    ["static", "predict", "--model", "{R}/smodel", "--no-preview", "--out", "o"],
    ["static", "evaluate", "--model", "{R}/smodel", "--data", "{R}/static.h5", "--out", "o"],
    ["impact", "predict", "--model", "{R}/imodel", "--velocity", "35", "--out", "o"],
    ["impact", "evaluate", "--model", "{R}/imodel", "--data", "{R}/impact.h5", "--out", "o"],
], ids=lambda c: " ".join(c[:2]))
def test_predict_and_evaluate(command, models, tmp_path):
    """Interrupted as the network's module starts to be imported (the numpy inference for a static
    model, torch for an impact one): the import ends, then the command stops, leaving nothing or a
    result marked as interrupted."""
    trigger = AT_IMPORT.replace("{module}", NETWORK_MODULE[command[0]])
    code, err = interrupted([a.replace("{R}", str(models)) for a in command], tmp_path, trigger)
    assert_interrupted(code, err)
    assert_nothing_or_marked(tmp_path / "o")


def test_a_finished_command_ignores_a_late_interrupt(tmp_path):
    """A Ctrl-C after the command's work is written (while the interpreter shuts down) changes
    nothing: exit code 0, not death by the signal (-2)."""
    from toolkit.cli._main import main  # noqa: F401 - the module the program runs

    code = subprocess.run(
        [sys.executable, "-c", "import os, signal, sys\n"
         "from toolkit.cli import main\n"
         "code = main()\n"
         "os.kill(os.getpid(), signal.SIGINT)\n"
         "sys.exit(code)\n",
         "phantom", "face-hex", "--resolution", "coarse", "--out", "f.inp"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert code.returncode == 0, code.stderr
    assert "Traceback" not in code.stderr
    assert (tmp_path / "f.inp").exists()
