"""Thread defaults (one thread: on a 2-core AMD EPYC multithreaded BLAS and torch are several
times slower), the user option, and an import that changes nothing in the process."""

import subprocess
import sys

import pytest


def _run(code, env_extra=None):
    import os

    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    env.update(env_extra or {})
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_default_is_one_thread_for_blas_and_torch():
    out = _run("import toolkit, torch, threadpoolctl; toolkit.set_threads();"
               "print(torch.get_num_threads(), max(p['num_threads'] for p in threadpoolctl.threadpool_info()))")
    assert out == "1 1"


def test_user_raises_the_thread_count():
    out = _run("import toolkit, torch; toolkit.set_threads(2); print(torch.get_num_threads())")
    assert out == "2"
    out = _run("import toolkit, torch; toolkit.set_threads(); print(torch.get_num_threads())",
               {"TOOLKIT_NUM_THREADS": "2"})
    assert out == "2"


def test_bad_thread_counts_are_refused(monkeypatch):
    from toolkit.common.runtime import default_threads, set_threads

    with pytest.raises(ValueError, match="thread count must be >= 1, got 0"):
        set_threads(0)
    monkeypatch.setenv("TOOLKIT_NUM_THREADS", "many")
    with pytest.raises(ValueError, match="TOOLKIT_NUM_THREADS='many' is not an integer"):
        default_threads()


def test_importing_the_package_changes_no_environment_variable_or_thread_limit():
    """``import toolkit`` (and its workflows) sets no OMP/OPENBLAS/MKL_NUM_THREADS and limits no
    thread pool, so a notebook that imports it beside other libraries keeps its settings: the
    environment, torch's thread count and the BLAS pools already loaded are what they were
    (torch defaults to more than one thread on a machine with more than one core, so a limit would
    show)."""
    out = _run("import os, numpy, torch, threadpoolctl\n"
               "env, t = dict(os.environ), torch.get_num_threads()\n"
               "pools = {p['filepath']: p['num_threads'] for p in threadpoolctl.threadpool_info()}\n"
               "import toolkit, toolkit.common, toolkit.static, toolkit.impact, toolkit.cli\n"
               "after = {p['filepath']: p['num_threads'] for p in threadpoolctl.threadpool_info()}\n"
               "print(dict(os.environ) == env, torch.get_num_threads() == t, "
               "all(after[k] == v for k, v in pools.items()), t > 1 or os.cpu_count() == 1)")
    assert out == "True True True True"


def test_set_threads_reaches_libraries_loaded_later_and_child_processes():
    """Called before torch is imported, the count still holds once torch loads (through
    OMP_NUM_THREADS), and a spawned worker process inherits it."""
    out = _run("import toolkit; toolkit.set_threads(1)\n"
               "import torch, subprocess, sys\n"
               "child = subprocess.run([sys.executable, '-c', 'import torch; print(torch.get_num_threads())'],"
               " capture_output=True, text=True).stdout.strip()\n"
               "print(torch.get_num_threads(), child)")
    assert out == "1 1"


def test_a_ctrl_c_during_an_import_is_raised_once_the_import_ends(tmp_path):
    """With the command line's SIGINT handler, an interrupt in the middle of a module's import
    (the module sends it to itself halfway through its code) lets the import finish, then raises
    KeyboardInterrupt (Python's default handler raises it inside the import, which a compiled
    module's initialisation turns into an abort)."""
    (tmp_path / "interrupting_module.py").write_text(
        "import signal\nsignal.raise_signal(signal.SIGINT)\nDONE = True\n")
    script = (
        "import signal, sys\n"
        "from toolkit.common.runtime import interrupt_outside_imports\n"
        "signal.signal(signal.SIGINT, interrupt_outside_imports if sys.argv[2] == 'toolkit'\n"
        "              else signal.default_int_handler)  # also when started with SIGINT ignored (a background job)\n"
        "sys.path.insert(0, sys.argv[1])\n"
        "try:\n"
        "    import interrupting_module\n"
        "    print('not interrupted')\n"
        "except KeyboardInterrupt:\n"
        "    print('after the import' if getattr(sys.modules.get('interrupting_module'), 'DONE', False)\n"
        "          else 'inside the import')\n")
    out = {h: subprocess.run([sys.executable, "-c", script, str(tmp_path), h], capture_output=True, text=True,
                             timeout=60).stdout.strip() for h in ("toolkit", "default")}
    assert out == {"toolkit": "after the import", "default": "inside the import"}
