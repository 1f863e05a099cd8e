"""Fixtures shared by the static surrogate's tests (built once per pytest run)."""

import pytest

from toolkit.static.database import DatabaseConfig, build_database
from toolkit.static.features import FeatureSpec
from toolkit.static.surrogate import SurrogateConfig, train_surrogate


@pytest.fixture(scope="session")
def db6(tmp_path_factory):
    """6 sagittal plans on the coarse face: 18 samples (~2 s)."""
    path = tmp_path_factory.mktemp("db6") / "db6.h5"
    build_database(path, DatabaseConfig(resolution="coarse", plans=6), workers=0, progress=False)
    return path


@pytest.fixture(scope="session")
def quick_model(db6, tmp_path_factory):
    """A tiny hard-boundary model trained for 2 epochs on ``db6``: for what holds whatever the
    model's accuracy (~1 s)."""
    config = SurrogateConfig(FeatureSpec("hard"), network="tiny", coarse_radii=True, epochs=2)
    return train_surrogate(db6, config, out=tmp_path_factory.mktemp("model") / "quick", progress=False)


@pytest.fixture(scope="session")
def db100(tmp_path_factory):
    """34 sagittal plans on the coarse face: 102 samples (~15 s)."""
    path = tmp_path_factory.mktemp("surrogate") / "db.h5"
    build_database(path, DatabaseConfig(resolution="coarse", plans=34), workers=0, progress=False)
    return path


@pytest.fixture(scope="session")
def hard_model(db100, tmp_path_factory):
    """The tiny hard-boundary network on ``db100``, at most 200 epochs with early stopping (15
    epochs without a better validation loss): a budget in epochs, so that a slower machine trains
    the same model (it stops at epoch 68, ~40 s on an Intel Xeon)."""
    out = tmp_path_factory.mktemp("model") / "hard"
    config = SurrogateConfig(FeatureSpec("hard"), network="tiny", coarse_radii=True, epochs=200, lr=3e-3)
    return train_surrogate(db100, config, out=out, progress=False)
