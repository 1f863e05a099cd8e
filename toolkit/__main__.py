"""``python -m toolkit``: the ``toolkit`` command line."""

import sys

if __name__ == "__main__":
    try:
        from toolkit.cli import main
    except KeyboardInterrupt:  # Ctrl-C while the command line loads: nothing has started
        print("interrupted: nothing was done; rerun the same command", file=sys.stderr)
        sys.exit(130)
    try:
        code = main()
    except KeyboardInterrupt:  # a Ctrl-C that reached Python twice (a library re-raising it): said once already
        code = 130
    sys.exit(code)
