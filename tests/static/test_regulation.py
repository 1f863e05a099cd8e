"""Mesh regulation between increments (the lip-sliding paper): untangling inverted elements by moving
only the nodes no boundary condition holds, keeping boundary nodes on their surface."""

import numpy as np
import pytest

from toolkit.common.phantoms.phantom import block
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


@pytest.fixture()
def tet10_cube():
    """4 x 4 x 4 block of 10 mm cubes, each split into 6 tet10, with the nodes off its boundary movable."""
    mesh = block([np.linspace(0, 40, 5)] * 3, "tet10")
    x = mesh.points
    interior = np.all((x > 0) & (x < 40), axis=1)
    return mesh, interior


def test_tet10_regulation_untangles_a_corner_and_its_edges_follow(tet10_cube):
    """An interior corner node pushed (9, 9, 9) mm inverts corner tetrahedra; regulation
    untangles them exactly as it does the same block of tet4 (the corner tetrahedra are what
    it optimises), and leaves every interior mid-edge node of the regulated elements on its
    straight edge (the mesh's edges were straight)."""
    from toolkit.common.fem.reference import TET_EDGES

    mesh, interior = tet10_cube
    conn = mesh.cells["tet10"]
    x = mesh.points.copy()
    node = np.flatnonzero(interior & np.isin(np.arange(mesh.n_points), conn[:, :4]))[0]
    x[node] += [9.0, 9.0, 9.0]
    assert element_quality(mesh, x).min() < 0
    reg = regulate(mesh, x, interior, target=0.2)
    linear = block([np.linspace(0, 40, 5)] * 3, "tet4")
    x4 = linear.points.copy()
    x4[node] += [9.0, 9.0, 9.0]  # the tet10 block numbers its corner nodes as the tet4 block
    reg4 = regulate(linear, x4, np.all((x4 > 0) & (x4 < 40), axis=1), target=0.2)
    assert reg.min_quality_before < 0 and reg.min_quality_after > 0.05
    assert reg.min_quality_after == pytest.approx(reg4.min_quality_after, abs=1e-9)
    moved = np.flatnonzero(np.linalg.norm(reg.points - x, axis=1) > 0)
    assert np.all(interior[moved])
    mid = conn[:, 4:].ravel()
    a, b = conn[:, TET_EDGES[:, 0]].ravel(), conn[:, TET_EDGES[:, 1]].ravel()
    touched = np.isin(mid, moved) | np.isin(a, moved) | np.isin(b, moved)
    sel = touched & interior[mid]
    assert sel.sum() > 6
    np.testing.assert_allclose(reg.points[mid[sel]], 0.5 * (reg.points[a[sel]] + reg.points[b[sel]]), atol=1e-9)


@pytest.mark.parametrize("curvature_mm", [0.0, 1.0])
def test_tet10_regulation_gives_a_folded_edge_its_shape_back(tet10_cube, curvature_mm):
    """A mid-edge node pushed 9 mm off its 10 mm edge folds its elements while every corner
    tetrahedron stays as it was: regulation puts the node back at its pre-operative offset from
    the edge's midpoint (0: a straight edge; 1 mm: a curved one), so the quality is the mesh's
    own again; nodes that may not move stay where they are."""
    mesh, interior = tet10_cube
    conn = mesh.cells["tet10"]
    inner_mid = np.flatnonzero(interior & np.isin(np.arange(mesh.n_points), conn[:, 4:]))[0]
    points = mesh.points.copy()
    points[inner_mid] += curvature_mm * np.array([0.0, 0.6, 0.8])
    mesh = mesh.with_points(points)
    q0 = element_quality(mesh, points).min()
    x = points.copy()
    x[inner_mid] += [9.0, -9.0, 9.0]
    assert element_quality(mesh, x).min() < 0
    reg = regulate(mesh, x, interior, target=0.2)
    np.testing.assert_allclose(reg.points[inner_mid], points[inner_mid], atol=1e-9)
    assert reg.min_quality_after == pytest.approx(q0)
    assert np.all(reg.points[~interior] == x[~interior])


def test_tet10_regulation_unfolds_around_a_mid_edge_node_it_may_not_move(tet10_cube):
    """A mid-edge node held where a boundary condition put it (on a moving bone, say), 4 mm off
    its straight 10 mm edge, folds its elements while every corner tetrahedron is as it was.
    Putting mid-edge nodes back on their edges cannot help (this one may not move), so
    regulation moves the nodes around it for the quadratic map's own Jacobian: every element
    is valid again and the held node has not moved."""
    from toolkit.common.fem.reference import TET_EDGES

    mesh, interior = tet10_cube
    conn = mesh.cells["tet10"]
    mid, a, b = conn[:, 4:].ravel(), conn[:, TET_EDGES[:, 0]].ravel(), conn[:, TET_EDGES[:, 1]].ravel()
    inner = np.flatnonzero(interior[mid] & interior[a] & interior[b])[0]
    held = mid[inner]
    edge = mesh.points[b[inner]] - mesh.points[a[inner]]
    off = np.cross(edge, [1.0, 0.0, 0.0] if abs(edge[0]) < 0.9 * np.linalg.norm(edge) else [0.0, 1.0, 0.0])
    x = mesh.points.copy()
    x[held] += 4.0 * off / np.linalg.norm(off)
    assert element_quality(mesh, x).min() < 0
    movable = interior.copy()
    movable[held] = False
    reg = regulate(mesh, x, movable, target=0.2)
    assert reg.min_quality_before < 0 and reg.min_quality_after > 0.05
    np.testing.assert_array_equal(reg.points[held], x[held])
    assert np.all(reg.points[~movable] == x[~movable])


def test_a_folded_hexahedron_beside_tet10_blocks_is_regulated_without_a_quadratic_map():
    """A mesh of tet10 and hex8 blocks: a hexahedron folded by a node that may not move (pushed
    25 mm through its 10 mm cell) has no quadratic map to descend on, so regulation keeps stage
    one's answer instead of failing; the held node stays where it was put."""
    from toolkit.common.meshes.mesh import Mesh

    tets = block([np.linspace(0, 20, 3)] * 3, "tet10")
    hexes = block([np.linspace(0, 30, 4)] * 3, "hex8")
    mesh = Mesh(np.vstack([tets.points, hexes.points + [100.0, 0.0, 0.0]]),
                {"tet10": tets.cells["tet10"], "hex8": hexes.cells["hex8"] + tets.n_points})
    inside = np.flatnonzero(np.all((hexes.points > 0) & (hexes.points < 30), axis=1)) + tets.n_points
    movable = np.zeros(mesh.n_points, dtype=bool)
    movable[inside[1:]] = True
    x = mesh.points.copy()
    x[inside[0]] += [25.0, 25.0, 25.0]
    assert element_quality(mesh, x).min() < 0
    reg = regulate(mesh, x, movable, target=0.2)
    assert reg.min_quality_after >= reg.min_quality_before
    np.testing.assert_array_equal(reg.points[~movable], x[~movable])
