"""What every command shares: the help format, ``--threads``/``--verbose``, argument types,
the database-run options and the Dask client."""

from __future__ import annotations

import argparse
import difflib
import re
import signal
import threading
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

RESOLUTIONS = ["coarse", "paper", "fine"]


#: what a Ctrl-C leaves behind, per kind of command (``{out}``: the ``--out`` given)
NOTHING_WRITTEN = "nothing was written to {out}; rerun the same command"
SIMULATIONS_KEPT = "the finished simulations are kept in {out}; rerun the same command to finish the database"
EPOCHS_KEPT = ("the finished epochs are kept in {out}/checkpoint.pt; rerun the same command with --resume to finish "
               "the training")


@dataclass(frozen=True)
class Command:
    """One subcommand: its one-line ``help``, its ``description``, the function that adds its
    arguments to a parser, the handler that runs it (returns the exit code) and what a Ctrl-C
    leaves behind (``interrupted``, printed as ``interrupted: ...``)."""

    help: str
    description: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    interrupted: str = "rerun the same command"


class Parser(argparse.ArgumentParser):
    """argparse's parser, whose errors suggest the closest valid option or choice ("did you
    mean --resolution?") and name the subcommand whose option was mistyped, with its usage."""

    def parse_args(self, args=None, namespace=None):
        namespace, extras = self.parse_known_args(args, namespace)
        if extras:  # reported by the subcommand that read the options, not by the top level
            parser = getattr(namespace, "command_parser", self)
            parser.error(f"unrecognized arguments: {' '.join(extras)}{did_you_mean(parser, extras)}")
        return namespace

    def error(self, message: str):
        choice = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)", message)
        if choice:
            close = difflib.get_close_matches(choice.group(1), re.findall(r"'([^']*)'", choice.group(2)), n=1)
            message += f"; did you mean {close[0]!r}?" if close else ""
        super().error(message)


def did_you_mean(parser: argparse.ArgumentParser, extras: list[str]) -> str:
    """``"; did you mean --x?"`` for the unrecognized options among ``extras`` that are close to
    one of ``parser``'s, else ``""``."""
    options = [o for o in parser._option_string_actions if o.startswith("--")]
    hints = []
    for token in extras:
        if token.startswith("--"):
            close = difflib.get_close_matches(token.split("=", 1)[0], options, n=1, cutoff=0.6)
            hints += [f"{close[0]} for {token.split('=', 1)[0]}"] if close else []
    return f"; did you mean {', '.join(hints)}?" if hints else ""


class HelpFormatter(argparse.HelpFormatter):
    """argparse's help, with ``(default: ...)`` after every option whose text does not already
    say its default. Flags (off unless given) and required options are left as written."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if ("default" in text or action.default is argparse.SUPPRESS or action.required or action.nargs == 0
                or not action.option_strings):
            return text
        return f"{text} (default: %(default)s)" if text else "default: %(default)s"


def add_common(parser: argparse.ArgumentParser) -> None:
    """``--threads`` and ``--verbose``, on every subcommand."""
    parser.add_argument("--threads", type=positive_int, default=None,
                        help="BLAS/torch threads (default: TOOLKIT_NUM_THREADS or 1; 1 is fastest on 2 cores)")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")


def add_units(parser: argparse.ArgumentParser) -> None:
    """``--units``: the length unit of a mesh file, converted to mm."""
    parser.add_argument("--units", default="mm", choices=["mm", "m", "cm", "um"],
                        help="length unit of the --mesh file, converted to mm")


#: :data:`toolkit.common.meshes.axes.AXES` (named here so that building the parser imports no numerical
#: library; a test keeps them equal)
AXES = ("toolkit", "LPS", "RAS")


def add_axes(parser: argparse.ArgumentParser, files: str = "the --mesh and --bone files") -> None:
    """``--axes``: the anatomical axes of the input files, converted to the toolkit's on reading."""
    parser.add_argument("--axes", default="toolkit", choices=list(AXES),
                        help=f"axes of {files}: toolkit (x the patient's left, y anterior, z superior), LPS (DICOM, "
                             "ITK-SNAP: y posterior) or RAS (3D Slicer: x right), converted on reading; a face whose "
                             "anatomy says other axes is refused with the value that fits")


def torch_threads(args: argparse.Namespace) -> None:
    """torch picks its thread count at import: apply --threads (default 1) again once it is loaded."""
    import torch  # noqa: F401

    from toolkit.common.runtime import set_threads

    set_threads(args.threads)


@contextmanager
def uninterruptible():
    """Ignore Ctrl-C (SIGINT) inside the block: a command's last writes (a result folder, seconds
    at most) either do not start or finish, so an interrupted command leaves nothing half
    written. Outside the main thread nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def positive_int(text: str) -> int:
    """An integer >= 1 (an argparse type)."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1 or str(value) != text.strip().lstrip("+"):
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0 (an argparse type)."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


def probability(text: str) -> float:
    """A probability in (0, 1) (an argparse type)."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"{text!r} is not a probability in (0, 1), e.g. 0.9")
    return value


def tolerance_mm(text: str) -> float:
    """A tolerance in mm: a finite number > 0 (an argparse type)."""
    try:
        return positive_float(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected a tolerance in mm, a finite number > 0 such as 0.5, got "
                                         f"{text!r}") from None


def floats(text: str) -> list[float]:
    """``"20,26.5"`` -> ``[20.0, 26.5]`` (an argparse type)."""
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def two_points(text: str, option: str, example: str) -> tuple[tuple[float, float, float], ...]:
    """``X,Y,Z:X,Y,Z`` (mm), or a file of two lines ``X,Y,Z`` -> two points; ``option`` and
    ``example`` name the option and a valid value in the error."""
    source = text
    if ":" not in text and Path(text).is_file():
        lines = [ln.strip() for ln in Path(text).read_text(errors="replace").splitlines() if ln.strip()]
        source = ":".join(lines)
    points = []
    for part in source.split(":"):
        try:
            values = tuple(float(v) for v in part.split(","))
        except ValueError:
            values = ()
        points.append(values)
    if len(points) != 2 or any(len(p) != 3 for p in points):
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected two points X,Y,Z:X,Y,Z in mm (e.g. {example}; write {option}=-X,... when the first "
            "begins with a minus sign) or a file of two lines X,Y,Z")
    return tuple(points)


def ints(text: str) -> list[int]:
    """``"3,17"`` -> ``[3, 17]`` (an argparse type)."""
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def add_database_run(parser: argparse.ArgumentParser, items: str) -> None:
    """Where a learning database's simulations run and where it is written (both workflows)."""
    parser.add_argument("--workers", type=int, default=1, help="local worker processes (0: in this process)")
    parser.add_argument("--dask", "--scheduler", dest="dask", metavar="ADDRESS", default=None,
                        help="run on a Dask cluster: a scheduler address (tcp://host:8786) or 'local' for a "
                             "LocalCluster of --workers processes (default: no Dask, local processes)")
    parser.add_argument("--retry-failed", action="store_true", help=f"rerun {items} recorded as failed")
    parser.add_argument("--out", required=True, type=Path, help="database file (.h5)")


@contextmanager
def dask_client(address: str | None, workers: int):
    """A Dask client for ``--dask`` (a scheduler address, or ``local``: a LocalCluster of
    ``workers`` single-threaded processes); None without it. Closed on exit."""
    if not address:
        yield None
        return
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=max(workers, 1), threads_per_worker=1, dashboard_address=None) \
        if address == "local" else None
    client = None
    try:
        client = Client(cluster if cluster is not None else address)
        yield client
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()


def with_options(message: str, argv: list[str]) -> str:
    """``message`` of a library error, followed by ``(command line: OPTION, ...)`` for the options
    the user typed that it is about: the message names the option's parameter (``plans``, ``ball
    velocity`` for ``--velocity``, ``velocity`` for ``--velocities``) and shows the value typed
    (``-30`` as ``-30.0``). Options the message already names are left out."""
    named = []
    for option, value in _typed_options(argv):
        if option in message:
            continue
        name = option[2:].replace("-", "_")
        names = {name, name.replace("_", " "), re.sub(r"ies$", "y", name), re.sub(r"s$", "", name)}
        if any(re.search(rf"\b{re.escape(n)}\b", message) for n in names if n) and _shows(message, value):
            named.append(option)
    return f"{message} (command line: {', '.join(dict.fromkeys(named))})" if named else message


def _typed_options(argv: list[str]) -> list[tuple[str, str]]:
    """The options of a command line with the value typed after each (``""`` for a flag)."""
    out = []
    for i, arg in enumerate(argv):
        if arg.startswith("--") and len(arg) > 2:
            option, sep, value = arg.partition("=")
            if not sep and i + 1 < len(argv) and not argv[i + 1].startswith("--"):
                value = argv[i + 1]
            out.append((option, value))
    return out


def _shows(message: str, value: str) -> bool:
    """Whether ``message`` shows one of the comma-separated parts of ``value`` (numbers compared
    as numbers, so ``-30`` is shown by ``-30.0``)."""
    numbers = set()
    for text in re.findall(r"-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?|nan|inf", message):
        try:
            numbers.add(float(text))
        except ValueError:
            pass
    for part in filter(None, value.split(",")):
        try:
            number = float(part)
        except ValueError:
            if re.search(rf"\b{re.escape(part)}\b", message):
                return True
        else:
            if number in numbers or (number != number and "nan" in message):
                return True
    return False
