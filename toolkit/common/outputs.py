"""Output locations, checked before any computation.

A long run (a paper-size simulation, a training) that fails only when it writes its result loses
minutes of work. The functions here refuse, at the start, a location the run could not write:
an existing file where a folder is expected (or a folder where a file is), a parent that is a
file, a folder that does not exist and cannot be created (``/proc/x``), or one that is not
writable (a read-only file system). They create nothing: the probe file they write in the
nearest existing folder is removed at once.

>>> check_output_dir("results/face", what="output folder")  # doctest: +SKIP
PosixPath('results/face')
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from toolkit.common.errors import ToolkitError

__all__ = ["OutputError", "check_output_dir", "check_output_file", "check_model_dir"]


class OutputError(ToolkitError, ValueError):
    """An output location cannot be written (checked before the computation that fills it)."""


def check_output_dir(path: str | os.PathLike, *, what: str = "output folder", option: str = "out") -> Path:
    """``path`` as a Path, when a folder can be created or written there; else :class:`OutputError`.

    Parameters
    ----------
    path : the folder (created later by the writer when missing)
    what : what the folder is for, in the message (``"output folder"``, ``"model directory"``)
    option : the argument that names it, in the remedy (``out``; the command line's ``--out``)
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{what} {str(path)!r} is an existing file; expected a folder (created when missing): "
                          f"give another {_remedy(option)}")
    _check_writable(path, what, option)
    return path


def check_output_file(path: str | os.PathLike, *, what: str = "output file", option: str = "out") -> Path:
    """``path`` as a Path, when a file can be written there; else :class:`OutputError`.

    An existing file is accepted (the writers replace it atomically, and resumable databases
    extend it); an existing folder is not.
    """
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{what} {str(path)!r} is an existing folder; expected a file name: give another "
                          f"{_remedy(option)}, e.g. {str(path / 'out')!r} with its suffix")
    _check_writable(path.parent if str(path.parent) else Path("."), what, option, target=path)
    return path


def check_model_dir(path: str | os.PathLike, *, resume: bool) -> Path:
    """:func:`check_output_dir` for a training's model directory, which also refuses to start
    afresh over an interrupted training (``checkpoint.pt`` without ``model.pt``) unless
    ``resume``: a new run would overwrite the finished epochs of that checkpoint."""
    path = check_output_dir(path, what="model directory")
    if not resume and (path / "checkpoint.pt").is_file() and not (path / "model.pt").exists():
        raise OutputError(f"model directory {str(path)!r} holds an interrupted training (checkpoint.pt, no "
                          "model.pt); continue it with resume=True (command line: --resume), or give another "
                          f"{_remedy('out')} to start afresh")
    return path


def _check_writable(folder: Path, what: str, option: str, target: Path | None = None) -> None:
    """Refuse ``folder`` when it (or the first existing folder above it) cannot take new files."""
    target = folder if target is None else target
    existing = folder.absolute()
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise OutputError(f"{what} {str(target)!r} cannot be created: {str(existing)!r} is a file, not a folder; "
                          f"give another {_remedy(option)}")
    try:
        with tempfile.TemporaryFile(dir=existing, prefix=".toolkit-write-check-"):
            pass
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise OutputError(f"{what} {str(target)!r} cannot be written: {str(existing)!r} does not take new files "
                          f"({reason}); give a writable {_remedy(option)}") from None


def _remedy(option: str) -> str:
    """``out`` -> ``out= (command line: --out)``."""
    return f"{option}= (command line: --{option.replace('_', '-')})"
