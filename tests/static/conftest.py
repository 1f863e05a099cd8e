"""Fixtures shared by the static surrogate's tests (built once per pytest run)."""

import pytest

from toolkit.static.dataset import DatasetConfig, generate
from toolkit.static.features import FeatureSpec
from toolkit.static.surrogate import SurrogateConfig, train_surrogate


@pytest.fixture(scope="session")
def db100(tmp_path_factory):
    """34 sagittal plans on the coarse face: 102 samples (~20 s)."""
    path = tmp_path_factory.mktemp("surrogate") / "db.h5"
    generate(path, DatasetConfig(resolution="coarse", plans=34), workers=0, progress=False)
    return path


@pytest.fixture(scope="session")
def hard_model(db100, tmp_path_factory):
    out = tmp_path_factory.mktemp("model") / "hard"
    config = SurrogateConfig(FeatureSpec("hard"), network="tiny", coarse_radii=True, epochs=200, lr=3e-3,
                             max_seconds=45.0)
    return train_surrogate(db100, out, config, progress=False)
