"""Tiny coarse databases and models for the command-line tests, built once per session in this
process (~15 s): a static database of 3 plans with a one-epoch tiny PointNet++, an impact
database of two velocities and one held out (rigid ball, tet4, 6 frames) with a one-epoch
model of the impact paper's configuration."""

import pytest


@pytest.fixture(scope="session")
def models(tmp_path_factory):
    """A tiny static model and a tiny impact model with their coarse databases (~20 s)."""
    from dataclasses import replace

    from toolkit.impact import yielding_scene
    from toolkit.impact.database import build_database as build_impact_database
    from toolkit.impact.surrogate import CONFIGS
    from toolkit.impact.surrogate import train_surrogate as train_impact
    from toolkit.static.database import DatabaseConfig, build_database
    from toolkit.static.surrogate import SurrogateConfig, train_surrogate

    root = tmp_path_factory.mktemp("interrupts")
    build_database(root / "static.h5", DatabaseConfig(resolution="coarse", plans=3), workers=0, progress=False)
    train_surrogate(root / "static.h5", SurrogateConfig(network="tiny", coarse_radii=True, epochs=1),
                    out=root / "smodel", progress=False)
    scene = yielding_scene().with_face(resolution="coarse").with_ball(rigid=True)
    scene = replace(scene.with_fidelity(order=1, integrator="explicit", mass_scaling=100.0), n_frames=6)
    build_impact_database(root / "impact.h5", (30.0, 40.0), (35.0,), scene, workers=0, progress=False)
    train_impact(root / "impact.h5", CONFIGS["paper"].with_(epochs=1), out=root / "imodel", progress=False)
    return root
