"""Mesh regulation between increments (the lip-sliding paper): untangling inverted elements by moving
only the nodes no boundary condition holds, keeping boundary nodes on their surface."""

import numpy as np
import pytest

from toolkit.common.phantom import block
from toolkit.static.regulation import element_quality, regulate


@pytest.fixture()
def cube():
    """4 x 4 x 4 hex block of 10 mm cells with its interior nodes movable."""
    mesh = block([np.linspace(0, 40, 5)] * 3)
    x = mesh.points
    interior = np.all((x > 0) & (x < 40), axis=1)
    return mesh, interior


def test_regulation_untangles_an_inverted_element(cube):
    """An interior node pushed (11, 11, 11) mm, past its diagonal neighbour, inverts elements;
    regulation moves only movable nodes and brings every element above the target (0.2)."""
    mesh, interior = cube
    x = mesh.points.copy()
    node = np.flatnonzero(interior)[0]
    x[node] += [11.0, 11.0, 11.0]
    assert element_quality(mesh, x).min() < 0
    reg = regulate(mesh, x, interior, target=0.2)
    assert reg.min_quality_before < 0 and reg.min_quality_after >= 0.2 - 1e-9
    assert element_quality(mesh, reg.points).min() == pytest.approx(reg.min_quality_after)
    moved = np.flatnonzero(np.linalg.norm(reg.points - x, axis=1) > 0)
    assert moved.size == reg.moved and np.all(interior[moved])
    assert 0 < reg.max_shift < 30.0


def test_regulation_keeps_boundary_nodes_on_their_plane_and_leaves_good_meshes(cube):
    """A movable node of the bottom face (z = 0) dragged inside its face folds an element;
    regulation moves it only within the plane z = 0. A mesh already above the target is
    returned unchanged (moved 0)."""
    mesh, interior = cube
    x = mesh.points.copy()
    bottom = np.flatnonzero((x[:, 2] == 0) & (x[:, 0] == 20) & (x[:, 1] == 20))[0]
    x[bottom, 0] += 14.0
    movable = interior.copy()
    movable[bottom] = True
    assert element_quality(mesh, x).min() < 0.05
    reg = regulate(mesh, x, movable, target=0.2)
    assert reg.min_quality_after > 0.2 - 1e-9
    assert reg.points[bottom, 2] == pytest.approx(0.0, abs=1e-12)
    same = regulate(mesh, mesh.points, movable, target=0.2)
    assert same.moved == 0 and np.array_equal(same.points, mesh.points)
