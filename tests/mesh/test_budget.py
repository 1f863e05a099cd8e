"""``toolkit.mesh.budget``: the size of a mesh and its memory, estimated before meshing, and the
refusal of a size that would not fit."""

import re
import time

import numpy as np
import pytest

from toolkit.common import face_hex
from toolkit.mesh.budget import estimate_size, finest_fitting_size
from toolkit.mesh.face import FaceInputError, mesh_face
from toolkit.mesh.phantom import phantom_surfaces


@pytest.fixture(scope="module")
def surfaces():
    return phantom_surfaces(face_hex("coarse"))


def test_the_estimate_scales_like_the_bulk_and_the_boundary(surfaces):
    """Halving the size multiplies the elements by between 4 (all boundary) and 8 (all bulk), and
    the memory grows with them."""
    p, t = surfaces.tissue.points, surfaces.tissue.cells["tri3"]
    a, b = estimate_size(p, t, 6.0), estimate_size(p, t, 3.0)
    assert 4.0 < b.elements / a.elements < 8.0
    assert b.simulation_gib > a.simulation_gib and b.mesher_gib > a.mesher_gib
    assert b.nodes == pytest.approx(1.6 * b.elements, rel=0.01)


def test_the_estimate_is_within_a_third_of_a_face_it_was_not_fitted_to(surfaces):
    """The fit comes from the paper phantom's surfaces; the coarse phantom's, meshed at 8 mm (a
    size outside the fit too), has its element count within a third of the estimate."""
    face = mesh_face(surfaces.tissue, surfaces.bones, surfaces.commissures, size_mm=8.0, order=2)
    expected = face.report["estimate"]["elements"]
    assert abs(face.report["elements"] - expected) < expected / 3, (face.report["elements"], expected)


def test_a_size_that_does_not_fit_is_refused_before_meshing(surfaces):
    """With 1 GiB allowed, 2 mm is refused in well under a second (no meshing), naming the finest
    size that fits, which does fit, and the option that sets the limit."""
    t0 = time.perf_counter()
    with pytest.raises(FaceInputError, match=r"--memory") as err:
        mesh_face(surfaces.tissue, surfaces.bones, surfaces.commissures, size_mm=2.0, memory_gib=1.0)
    assert time.perf_counter() - t0 < 5.0
    fits = float(re.search(r"--size ([0-9.]+) or coarser fits", str(err.value)).group(1))
    p, t = surfaces.tissue.points, surfaces.tissue.cells["tri3"]
    assert estimate_size(p, t, fits).peak_gib <= 1.0 < estimate_size(p, t, fits - 0.1).peak_gib
    assert fits == finest_fitting_size(p, t, 1.0)
    assert np.isfinite(fits) and fits > 2.0
