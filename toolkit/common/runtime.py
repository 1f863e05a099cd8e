"""Process-wide runtime settings: thread counts, headless rendering and Ctrl-C handling.

On 2 cores the kernels the toolkit runs are no faster with two threads than with one, or slower
(``benchmarks/threads.py``, its table in ``docs/index.md``). Nothing here runs on import: the
command line calls :func:`set_threads` (``--threads``, default 1), and Python users call it
themselves.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from contextlib import contextmanager

__all__ = ["set_threads", "configure_headless_rendering", "default_threads", "deferred_interrupt",
           "interrupt_outside_imports", "install_interrupt_outside_imports", "interrupt_after", "count_finished",
           "WORK_UNITS"]

_threadpool_limiter = None

#: units of work :func:`interrupt_after` counts
WORK_UNITS = ("job", "frame", "increment")
#: triggers set by :func:`interrupt_after`: unit -> [units finished since, units that send the SIGINT, to the group]
_interrupt_triggers: dict[str, list] = {}


def default_threads() -> int:
    """Thread count from ``TOOLKIT_NUM_THREADS`` (default 1)."""
    raw = os.environ.get("TOOLKIT_NUM_THREADS", "1")
    try:
        n = int(raw)
    except ValueError:
        raise ValueError(f"TOOLKIT_NUM_THREADS={raw!r} is not an integer; expected e.g. 1 or 2") from None
    if n < 1:
        raise ValueError(f"TOOLKIT_NUM_THREADS={n} must be >= 1")
    return n


def set_threads(n: int | None = None) -> int:
    """Limit BLAS/OpenMP and torch to ``n`` threads, in this process and the ones it starts.

    Explicit, because it changes the process: the thread pools already loaded are limited
    (threadpoolctl, and torch if imported), and ``OMP_NUM_THREADS``,
    ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS`` and ``TOOLKIT_NUM_THREADS`` are set so
    that libraries loaded later (torch picks its count when first imported) and worker
    processes started afterwards (the database's process pool, a Dask ``LocalCluster``)
    use ``n`` as well. Workers of a remote Dask cluster keep their own settings.

    Parameters
    ----------
    n : int or None
        Threads to use; ``None`` takes :func:`default_threads`.

    Returns
    -------
    int
        The thread count now in force.
    """
    global _threadpool_limiter
    n = default_threads() if n is None else int(n)
    if n < 1:
        raise ValueError(f"thread count must be >= 1, got {n}")
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "TOOLKIT_NUM_THREADS"):
        os.environ[var] = str(n)
    try:
        from threadpoolctl import threadpool_limits

        _threadpool_limiter = threadpool_limits(limits=n)
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency
        pass
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(n)
    return n


def configure_headless_rendering() -> None:
    """Make VTK render off-screen through EGL (Mesa) when no X display exists.

    Must run before pyvista/vtk create their first render window. Without a display VTK then
    renders off-screen with no warning. Respects a user's own
    ``VTK_DEFAULT_OPENGL_WINDOW``.
    """
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def interrupt_outside_imports(signum, frame) -> None:
    """SIGINT handler of the command line: raise ``KeyboardInterrupt``, or, while a module is
    being imported, raise it in the code that started the import as soon as the import returns.

    A ``KeyboardInterrupt`` raised in Python code that a compiled module runs while it
    initialises (pybind11's, importing torch) aborts the process (exit -6) instead of reaching
    the command's handler. The deferred interrupt is delivered by a trace function on the
    importing frame (tracing is on only until then). Installed by the command line only
    (:func:`install_interrupt_outside_imports`).
    """
    importer = None
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            importer = frame.f_back  # the outermost import's caller, once the walk ends
        frame = frame.f_back
    if importer is None:
        raise KeyboardInterrupt

    previous = sys.gettrace()  # a coverage tool's or debugger's, given back on delivery

    def deliver(frame, event, arg):
        sys.settrace(previous)
        frame.f_trace = None
        raise KeyboardInterrupt

    importer.f_trace = deliver
    importer.f_trace_lines = True
    if previous is None:
        sys.settrace(lambda frame, event, arg: None)  # tracing on, so that the importer's trace runs


def install_interrupt_outside_imports() -> None:
    """Make :func:`interrupt_outside_imports` the SIGINT handler if Ctrl-C has Python's default
    one (a process started in the background ignores it and keeps ignoring it); the command
    line's entry points call it, the library never does."""
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, interrupt_outside_imports)


@contextmanager
def deferred_interrupt():
    """Hold a Ctrl-C (SIGINT) arriving inside the block until the block ends, then raise it.

    Wraps short, atomic file updates (a merge) so that an impatient second Ctrl-C does not throw
    finished work away, and calls into extensions that abort the process when an interrupt
    reaches Python inside them (pymetis). Outside the main thread (where signals cannot be
    handled) it does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:
        raise KeyboardInterrupt


def interrupt_after(unit: str, count: int | None, *, group: bool = False) -> None:
    """Send a SIGINT (what Ctrl-C sends) once ``count`` more units of work have finished in this
    process: a Ctrl-C at a known point of a run, the same on a fast or a slow machine, for tests of
    what an interrupt leaves behind.

    Parameters
    ----------
    unit : ``"job"`` (a job :func:`~toolkit.common.training.database.run_jobs` has stored, its record or its
        failure: a simulation of ``static database`` or ``impact database``) or ``"frame"`` (a frame
        :func:`toolkit.impact.simulate` has finished, and written when it has an output folder) or
        ``"increment"`` (an increment of a static simulation has reached equilibrium)
    count : units counted from this call, >= 1; ``None`` removes the trigger
    group : send the signal to this process's group, as a terminal's Ctrl-C reaches every process
        of a command (worker processes included), instead of to this process alone; only for a
        process that leads its own group (``subprocess.Popen(..., start_new_session=True)``)

    The signal is sent once, right after the ``count``-th unit, from the main process (a database's
    jobs are counted where they are stored, not in its worker processes), and is handled like any
    SIGINT: by the command line's handler, or as Python's ``KeyboardInterrupt``. Nothing is counted
    until this is called.
    """
    if unit not in WORK_UNITS:
        raise ValueError(f"unit = {unit!r}; expected one of {list(WORK_UNITS)}")
    if count is None:
        _interrupt_triggers.pop(unit, None)
        return
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"count = {count!r}; expected an integer >= 1 (units of work before the SIGINT) or None")
    if group and os.getpgrp() != os.getpid():
        raise ValueError("group=True: this process does not lead its own process group, so the signal would "
                         "reach the processes that started it; start it with start_new_session=True")
    _interrupt_triggers[unit] = [0, count, group]


def count_finished(unit: str) -> None:
    """Count one finished unit of work (one of :data:`WORK_UNITS`) for :func:`interrupt_after`,
    and send its SIGINT when the count is reached; without a trigger for ``unit``, nothing."""
    trigger = _interrupt_triggers.get(unit)
    if trigger is None:
        return
    trigger[0] += 1
    if trigger[0] < trigger[1]:
        return
    del _interrupt_triggers[unit]
    if trigger[2]:
        os.killpg(os.getpgrp(), signal.SIGINT)
    else:
        signal.raise_signal(signal.SIGINT)
