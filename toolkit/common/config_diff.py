"""Compare a stored configuration with the one asked for, and name every difference.

Databases, checkpoints and trained models all carry the JSON configuration that made
them; before reusing one, the toolkit compares it with the caller's and refuses a
mismatch with :class:`IncompatibleError`, whose message lists each differing key as
``key: stored <value>, asked <value>`` (nested keys joined with dots).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping

from toolkit.common.errors import ToolkitError

__all__ = ["IncompatibleError", "differences", "require_same", "jsonable"]


class IncompatibleError(ToolkitError, ValueError):
    """A stored file (database, checkpoint, model) was built for another configuration.

    Attributes: ``differences`` (list of ``(key, stored, asked)``).
    """

    def __init__(self, message: str, differences: list[tuple[str, object, object]] | None = None):
        super().__init__(message)
        self.differences = differences or []


_MISSING = "<missing>"


def jsonable(value):
    """``value`` as plain JSON types (tuples become lists, numpy scalars Python numbers), so that a
    configuration compares equal to itself after a JSON round trip."""
    return json.loads(json.dumps(value, default=_default))


def _default(obj):
    try:  # numpy scalars and arrays
        return obj.tolist()
    except AttributeError:
        raise TypeError(f"{type(obj).__name__} {obj!r} is not JSON-serialisable") from None


def differences(stored: Mapping, asked: Mapping, ignore: tuple[str, ...] = (), prefix: str = "") -> list[tuple]:
    """Every ``(dotted key, stored value, asked value)`` where two JSON-like mappings differ.

    Floats compare with a relative tolerance of 1e-12; keys in ``ignore`` (dotted, e.g.
    ``"train.epochs"``) are skipped; a key present on one side only shows ``<missing>``.
    """
    out = []
    for key in sorted(set(stored) | set(asked), key=str):
        name = f"{prefix}{key}"
        if name in ignore:
            continue
        a, b = stored.get(key, _MISSING), asked.get(key, _MISSING)
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            out.extend(differences(a, b, ignore, prefix=f"{name}."))
        elif not _equal(a, b):
            out.append((name, a, b))
    return out


def _equal(a, b) -> bool:
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b or a == b and type(a) is type(b)
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return math.isclose(a, b, rel_tol=1e-12, abs_tol=0.0) or (math.isnan(a) and math.isnan(b))
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    return a == b


def require_same(stored: Mapping, asked: Mapping, what: str, ignore: tuple[str, ...] = (), hint: str = "") -> None:
    """Raise :class:`IncompatibleError` naming every difference between ``stored`` and ``asked``.

    ``what`` names the stored thing (e.g. ``"database db.h5"``); ``hint`` is appended (a remedy).
    """
    diff = differences(jsonable(dict(stored)), jsonable(dict(asked)), ignore)
    if diff:
        shown = "; ".join(f"{k}: stored {v!r}, asked {w!r}" for k, v, w in diff[:8])
        more = f" (and {len(diff) - 8} more)" if len(diff) > 8 else ""
        raise IncompatibleError(f"{what} was built for another configuration: {shown}{more}"
                                + (f". {hint}" if hint else ""), diff)
