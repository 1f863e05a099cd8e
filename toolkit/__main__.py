"""``python -m toolkit``: the ``toolkit`` command line."""

import sys

if __name__ == "__main__":
    from toolkit.common.runtime import install_interrupt_outside_imports

    install_interrupt_outside_imports()
    try:
        from toolkit.cli import main
    except KeyboardInterrupt:  # Ctrl-C while the command line loads: nothing has started
        print("interrupted: nothing was done; rerun the same command", file=sys.stderr)
        sys.exit(130)
    try:
        code = main()
    except KeyboardInterrupt:  # a Ctrl-C that reached Python twice (a library re-raising it): said once already
        code = 130
    if code == 130:
        # A Ctrl-C that lands in Python code a C extension runs through PyRun_String (pybind11's
        # py::exec, while torch is imported) sets CPython's "unhandled Ctrl-C" flag even though the
        # command handled it; `python -m` then ends the process by SIGINT instead of exit 130. Any
        # PyRun_String that completes clears the flag.
        try:
            import ctypes

            ctypes.pythonapi.PyRun_SimpleString(b"")
        except (ImportError, AttributeError, OSError):
            pass
    sys.exit(code)
