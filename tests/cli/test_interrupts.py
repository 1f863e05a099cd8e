"""A Ctrl-C in any command: exit code 130, one ``interrupted: ...`` line that says how to finish,
no traceback, and an output folder that holds nothing or a result marked as interrupted.

Each command runs as ``python -m toolkit`` in its own process group and gets SIGINT (what a
terminal sends on Ctrl-C) while it works; the tiny coarse fixtures keep each case to seconds.
The long matrix (every long command at several interrupt times, then rerun) is
``benchmarks/bad_inputs.py --interrupts``."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

#: coarse impact options: a rigid ball on the tet4 face
IMPACT = ["--resolution", "coarse", "--order", "1", "--ball", "rigid"]


def interrupt(args, cwd: Path, *, after: float = 0.0, when_exists: Path | None = None, timeout: float = 120):
    """Start ``toolkit ARGS`` in ``cwd``, send SIGINT to its process group ``after`` seconds after
    ``when_exists`` appears (or after the start), and return (exit code, stderr, whether the
    command was still running at the interrupt)."""
    # SIGINT's default action in the command (a test run started in the background ignores it)
    proc = subprocess.Popen([sys.executable, "-m", "toolkit", *map(str, args)], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    t0 = time.monotonic()
    while when_exists is not None and not when_exists.exists() and proc.poll() is None:
        assert time.monotonic() - t0 < timeout, f"{when_exists} never appeared"
        time.sleep(0.05)
    time.sleep(after)
    running = proc.poll() is None
    if running:
        os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=timeout)
    return proc.returncode, err, running


def assert_interrupted(code: int, err: str, running: bool) -> None:
    assert running, "the command ended before the interrupt: the case tests nothing"
    assert code == 130, err[-2000:]
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
    """Interrupted once its first simulation is kept: the workers stop without a traceback or a
    leaked semaphore, and the database says how far it got."""
    from toolkit.common.database import database_status

    args = ["static", "dataset", "--resolution", "coarse", "--plans", "8", "--workers", "1", "--out", "db.h5"]
    result = interrupt(args, tmp_path, when_exists=tmp_path / "db.h5.shards", after=0.2)
    assert_interrupted(*result)
    status = database_status(tmp_path / "db.h5")
    assert status.records >= 1 and not status.complete and status.pending == 0


def test_static_simulate(tmp_path):
    """Paper resolution in 12 increments (about 8 s on AMD EPYC): still working after 2.5 s, seconds
    before its files, which come after the last increment. With the default 3 increments the
    command can reach its last writes by then, which ignore Ctrl-C so as to finish."""
    result = interrupt(["static", "simulate", "--resolution", "paper", "--increments", "12", "--no-preview",
                        "--out", "o"], tmp_path, after=2.5)
    assert_interrupted(*result)
    assert not (tmp_path / "o").exists()


def test_impact_simulate_mid_run(tmp_path):
    """Interrupted once its first frames are written: summary.json says "interrupted"."""
    args = ["impact", "simulate", *IMPACT, "--integrator", "explicit", "--no-preview", "--out", "o"]
    result = interrupt(args, tmp_path, when_exists=tmp_path / "o" / "face.xdmf", after=0.5)
    assert_interrupted(*result)
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["status"] == "interrupted"


@pytest.mark.parametrize("command", [
    ["static", "predict", "--model", "{R}/smodel", "--no-preview", "--out", "o"],
    ["static", "evaluate", "--model", "{R}/smodel", "--data", "{R}/static.h5", "--out", "o"],
    ["impact", "predict", "--model", "{R}/imodel", "--velocity", "35", "--out", "o"],
    ["impact", "evaluate", "--model", "{R}/imodel", "--data", "{R}/impact.h5", "--out", "o"],
], ids=lambda c: " ".join(c[:2]))
def test_predict_and_evaluate(command, models, tmp_path):
    """Interrupted while loading the model and computing (1 s in: torch alone takes longer to import)."""
    result = interrupt([a.replace("{R}", str(models)) for a in command], tmp_path, after=1.0)
    assert_interrupted(*result)
    assert_nothing_or_marked(tmp_path / "o")


def test_a_finished_command_ignores_a_late_interrupt(models, tmp_path):
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
