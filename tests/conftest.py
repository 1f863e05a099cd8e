"""The suite runs on one thread, as the command line does by default: importing ``toolkit``
limits no threads, so the harness sets it once. Subprocesses (CLI tests,
notebook kernels, database workers) inherit it through the environment."""

import toolkit


def pytest_configure(config):
    toolkit.set_threads(1)
