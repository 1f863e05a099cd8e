"""Each test process (one per core under pytest-xdist, see ``addopts`` in pyproject.toml) runs
on one thread, as the command line does by default: importing ``toolkit`` limits no threads,
so the harness sets it once per process. Subprocesses (CLI tests,
notebook kernels, database workers) inherit it through the environment.

Tests marked ``long`` (notebooks, the documentation's code blocks, training to an accuracy,
the finer meshes) are left out of ``python -m pytest`` unless it is given ``--long`` (every
test) or a ``-m`` expression (``-m long``: only them)."""

import toolkit


def pytest_addoption(parser):
    parser.addoption("--long", action="store_true",
                     help="also run the tests marked long (-m long runs only them)")


def pytest_configure(config):
    toolkit.set_threads(1)


def pytest_collection_modifyitems(config, items):
    if config.getoption("--long") or config.getoption("markexpr"):
        return
    long = [item for item in items if item.get_closest_marker("long")]
    if long:
        config.hook.pytest_deselected(items=long)
        items[:] = [item for item in items if not item.get_closest_marker("long")]


def pytest_report_header(config):
    if not (config.getoption("--long") or config.getoption("markexpr")):
        return "tests marked long are left out: --long runs them too, -m long only them"
