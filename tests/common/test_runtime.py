"""Thread defaults (SPEC: one thread is fastest on the 2-core machine) and the user option."""

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
