"""A tiny impact learning database shared by the database and surrogate tests: the skull-held
yielding scene on the coarse face with the fastest fidelity (tet4, rigid ball, mass scaling 100),
12 frames over 0.36 s, the impact paper's six velocities and one held-out velocity (35 mm/s); built once
per session in this process (~5 s)."""

import pytest

from toolkit.impact import yielding_scene

TINY_VELOCITIES = (20.0, 26.0, 32.0, 38.0, 44.0, 50.0)
TINY_HELD_OUT = (35.0,)


def tiny_scene():
    from dataclasses import replace

    scene = yielding_scene().with_face(resolution="coarse").with_ball(rigid=True)
    return replace(scene.with_fidelity(order=1, integrator="explicit", mass_scaling=100.0), n_frames=12)


@pytest.fixture(scope="session")
def tiny_db_path(tmp_path_factory):
    from toolkit.impact.database import build_database

    path = tmp_path_factory.mktemp("impact-db") / "tiny.h5"
    report = build_database(path, TINY_VELOCITIES, TINY_HELD_OUT, tiny_scene(), workers=0, progress=False)
    assert not report.failed, report.failed
    return path


@pytest.fixture(scope="session")
def tiny_db(tiny_db_path):
    from toolkit.impact.database import load_database

    return load_database(tiny_db_path)
