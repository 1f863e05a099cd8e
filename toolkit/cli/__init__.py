"""Command line: ``toolkit demo``, ``toolkit phantom``, ``toolkit static ...``, ``toolkit impact ...``.

One module per command group (:mod:`~toolkit.cli.demo`, :mod:`~toolkit.cli.phantom`,
:mod:`~toolkit.cli.static`, :mod:`~toolkit.cli.impact`), each with the functions that add a
subcommand's arguments and the handler that calls the library; :mod:`~toolkit.cli._main`
wires them. Only this package prints; the library raises, warns or logs.
"""

from toolkit.cli._main import build_parser, main

__all__ = ["main", "build_parser"]
