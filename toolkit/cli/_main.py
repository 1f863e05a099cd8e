"""``toolkit``: wires the subcommands, sets the threads, and turns the toolkit's errors (any
:class:`~toolkit.common.errors.ToolkitError`, bad input, a missing file, a failed solve) into
``error: ...`` on stderr with exit code 2; so is a full disk or another failed write
(``OSError``). A Ctrl-C exits with 130 and one line, ``interrupted: ...``, saying what the
command left and how to finish it; once a command has finished, a Ctrl-C while the interpreter
shuts down is ignored, and one during a module's import is raised when the import ends (run as
a program: :func:`~toolkit.common.runtime.interrupt_outside_imports`)."""

from __future__ import annotations

import argparse
import logging
import signal
import sys

from toolkit.cli import ct, demo, impact, mesh, phantom, static
from toolkit.cli._common import Command, HelpFormatter, Parser, add_common, with_options

__all__ = ["main", "build_parser"]

DESCRIPTION = "Facial soft-tissue biomechanics: phantoms, orthognathic FEM, ball-impact FEM, surrogates."
GROUPS = {"static": static, "impact": impact}
COMMANDS = {"demo": demo.COMMAND, "phantom": phantom.COMMAND, "ct": ct.COMMAND, "mesh": mesh.COMMAND}


def build_parser() -> argparse.ArgumentParser:
    from toolkit import __version__

    parser = Parser(prog="toolkit", description=DESCRIPTION, formatter_class=HelpFormatter)
    parser.add_argument("--version", action="version", version=f"toolkit {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, command in COMMANDS.items():
        _add(sub, name, command)
    for name, group in GROUPS.items():
        p = sub.add_parser(name, help=group.HELP, description=group.DESCRIPTION, formatter_class=HelpFormatter)
        group_sub = p.add_subparsers(dest=f"{name}_command", metavar=f"{name.upper()}_COMMAND", required=True)
        for sub_name, command in group.COMMANDS.items():
            _add(group_sub, sub_name, command)
    return parser


def _add(subparsers, name: str, command: Command) -> None:
    p = subparsers.add_parser(name, help=command.help, description=command.description, formatter_class=HelpFormatter)
    command.add_arguments(p)
    add_common(p)
    p.set_defaults(func=command.run, interrupted=command.interrupted, command_parser=p)


def main(argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default: the program's arguments) and return its exit code:
    0, 2 for an error, 130 for a Ctrl-C (``interrupted: ...`` says what it left and how to finish)."""
    from toolkit.common.errors import ToolkitError

    program = argv is None
    if program:
        from toolkit.common.runtime import install_interrupt_outside_imports

        install_interrupt_outside_imports()
    argv = sys.argv[1:] if argv is None else list(argv)
    args = None
    try:
        args = build_parser().parse_args(argv)
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                            format="%(levelname)s %(message)s")
        from toolkit.common.runtime import set_threads

        set_threads(args.threads)
        code = int(args.func(args) or 0)
        if code == 0:
            _record_command(args, argv)
    except KeyboardInterrupt:
        return _interrupted(args, program)
    except ImportError as exc:
        # a Ctrl-C while a compiled module initialises reaches Python as its ImportError
        # ("initialization failed", raised from the KeyboardInterrupt)
        if isinstance(exc.__cause__ or exc.__context__, KeyboardInterrupt):
            return _interrupted(args, program)
        raise
    except (ToolkitError, ValueError, KeyError, FileNotFoundError, RuntimeError) as exc:
        _close_progress_bars()
        print(f"error: {with_options(str(exc), argv)}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk, a folder made read-only during the run
        _close_progress_bars()
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"error: {where}{exc.strerror or exc} (the files finished before it are complete)", file=sys.stderr)
        return 2
    if program:  # the work is done and written: a Ctrl-C while the interpreter shuts down changes nothing
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    return code


def _record_command(args, argv: list[str]) -> None:
    """Add ``command`` (the command line that wrote it) to the ``summary.json`` of the output
    folder ``--out`` of a command that finished, so that the folder says how to make it again."""
    import json
    import shlex
    from pathlib import Path

    from toolkit.common.meshes.io import atomic_path

    out = getattr(args, "out", None)
    path = Path(out) / "summary.json" if out is not None else None
    if path is None or not path.is_file():
        return
    summary = json.loads(path.read_text())
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps({**summary, "command": shlex.join(["toolkit", *argv])}, indent=2))


def _interrupted(args, program: bool) -> int:
    """Say what a Ctrl-C left and how to finish; 130."""
    if program:  # one Ctrl-C is enough: a second one while this is said or at shutdown changes nothing
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    _close_progress_bars()
    left = "nothing was started; rerun the same command" if args is None else \
        args.interrupted.format(out=getattr(args, "out", None))
    print(f"interrupted: {left}", file=sys.stderr)
    return 130


def _close_progress_bars() -> None:
    """Close the progress bars an error left open, so that its message starts a line of its own
    (not the end of the bar's line)."""
    tqdm = sys.modules.get("tqdm")
    for bar in list(getattr(getattr(tqdm, "tqdm", None), "_instances", ())):
        bar.close()
