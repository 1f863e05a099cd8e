"""Mesh container, topology and element quality."""

import numpy as np
import pytest

from toolkit.common.meshes.mesh import DegenerateElementError, InvertedElementError, Mesh, MeshError
from toolkit.common.meshes.topology import boundary_faces, kuhn_tets, tet10_from_tet4

CUBE = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
REG_TET = np.array([[1, 1, 1], [-1, 1, -1], [1, -1, -1], [-1, -1, 1]], float)  # regular, positive


def grid_hexes(n=3, shear=0.0):
    """Structured ``n^3`` hex grid of the unit cube (VTK order), optionally sheared."""
    s = np.linspace(0, 1, n + 1)
    P = np.stack(np.meshgrid(s, s, s, indexing="ij"), -1).reshape(-1, 3)
    P[:, 0] += shear * P[:, 2]
    ids = np.arange(P.shape[0]).reshape((n + 1,) * 3)
    c = np.empty((n, n, n, 2, 2, 2), dtype=np.int64)
    for a in (0, 1):
        for b in (0, 1):
            for d in (0, 1):
                c[..., a, b, d] = ids[a:n + a, b:n + b, d:n + d]
    order = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
    hexes = np.stack([c[..., i, j, k].ravel() for i, j, k in order], axis=1)
    return P, hexes, c


def tet_volumes(points, tets):
    x = points[tets[:, :4]]
    return np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0]) / 6.0


def test_ideal_elements_have_scaled_jacobian_one():
    """Unit cube and regular tetrahedron are the ideal elements (SJ = 1)."""
    assert Mesh(CUBE, {"hex8": [np.arange(8)]}).scaled_jacobian() == pytest.approx([1.0])
    assert Mesh(REG_TET, {"tet4": [[0, 1, 2, 3]]}).scaled_jacobian() == pytest.approx([1.0])
    p10, t10 = tet10_from_tet4(REG_TET, np.array([[0, 1, 2, 3]]))
    assert Mesh(p10, {"tet10": t10}).scaled_jacobian() == pytest.approx([1.0])


def test_sheared_hex_scaled_jacobian_is_cosine_of_shear():
    """Shearing a cube by angle a gives corner determinants cos(a) (unit edge vectors)."""
    a = np.deg2rad(30)
    pts = CUBE.copy()
    pts[:, 0] += np.tan(a) * pts[:, 2]
    assert Mesh(pts, {"hex8": [np.arange(8)]}).scaled_jacobian()[0] == pytest.approx(np.cos(a), rel=1e-12)


def test_check_names_inverted_element():
    """Swapping two nodes inverts the element; check() names it (global index) and its value."""
    P, hexes, _ = grid_hexes(2)
    bad = hexes.copy()
    bad[5] = bad[5][[1, 0, 3, 2, 5, 4, 7, 6]]
    mesh = Mesh(P, {"hex8": bad})
    with pytest.raises(InvertedElementError, match=r"element 5") as info:
        mesh.check()
    assert info.value.elements.tolist() == [5]
    assert info.value.values[0] < 0


def test_check_flags_degenerate_tet():
    """A nearly flat tetrahedron is refused as degenerate, not as inverted."""
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.3, 0.3, 1e-6]])
    with pytest.raises(DegenerateElementError, match="degenerate"):
        Mesh(flat, {"tet4": [[0, 1, 2, 3]]}).check()


def test_tet10_folded_by_midside_node_is_inverted():
    """Pushing a mid-edge node far past the opposite face folds the quadratic map."""
    p10, t10 = tet10_from_tet4(REG_TET, np.array([[0, 1, 2, 3]]))
    p10 = p10.copy()
    mid = t10[0, 4]  # edge (0, 1)
    p10[mid] = p10[t10[0, 2]] + 2.0 * (p10[t10[0, 2]] - p10[mid])
    assert Mesh(p10, {"tet10": t10}).scaled_jacobian()[0] < 0


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(points=np.zeros((4, 2)), cells={}), r"expected \(n_points, 3\)"),
        (dict(points=np.full((4, 3), np.nan), cells={}), "NaN"),
        (dict(points=REG_TET, cells={"tet4": [[0, 1, 2, 7]]}), "refers to node 7"),
        (dict(points=REG_TET, cells={"pyramid5": [[0, 1, 2, 3, 0]]}), "unknown cell type 'pyramid5'"),
        (dict(points=REG_TET, cells={"tet4": [[0, 1, 2]]}), r"expected \(n_cells, 4\)"),
        (dict(points=REG_TET, cells={"tet4": [[0, 1, 2, 3]]}, node_sets={"a": [9]}), "node set 'a' holds node 9"),
        (dict(points=REG_TET, cells={"tet4": [[0, 1, 2, 3]]}, element_sets={"e": [1]}), "element set 'e'"),
        (dict(points=REG_TET, cells={"tet4": [[0, 1, 2, 3]]}, point_data={"u": np.zeros(3)}), r"expected \(4, ...\)"),
    ],
)
def test_constructor_rejects_bad_input(kwargs, match):
    with pytest.raises(MeshError, match=match):
        Mesh(**kwargs)


def test_mesh_is_immutable_and_sets_normalised():
    m = Mesh(REG_TET, {"tet4": [[0, 1, 2, 3]]}, node_sets={"a": [3, 1, 1]})
    assert m.node_sets["a"].tolist() == [1, 3]
    assert m.node_sets["a"].dtype == np.int64
    with pytest.raises(ValueError):
        m.points[0, 0] = 1.0
    with pytest.raises(TypeError):
        m.node_sets["b"] = np.array([0])
    moved = m.translated([1.0, 0, 0])
    assert np.allclose(moved.points - m.points, [1, 0, 0]) and moved.node_sets["a"].tolist() == [1, 3]
    with pytest.raises(KeyError, match="the mesh has"):
        m.node_set("missing")


def test_boundary_faces_are_outward_and_enclose_the_volume():
    """Divergence theorem: sum over boundary faces of (x . n) dA / 3 equals the volume."""
    P, hexes, c = grid_hexes(3, shear=0.3)
    mesh = Mesh(P, {"hex8": hexes})
    faces = mesh.boundary_faces()
    assert faces.shape == (6 * 9, 4)
    x = P[faces]
    # split quads into two triangles for an exact flux of a linear field on planar quads
    flux = 0.0
    for tri in ((0, 1, 2), (0, 2, 3)):
        a, b, cc = x[:, tri[0]], x[:, tri[1]], x[:, tri[2]]
        n = 0.5 * np.cross(b - a, cc - a)
        flux += np.einsum("ij,ij->", (a + b + cc) / 3.0, n) / 3.0
    assert flux == pytest.approx(1.0, rel=1e-12)  # shear keeps the volume


def test_kuhn_split_is_conforming_and_keeps_volume():
    """A conforming split leaves exactly 2 boundary triangles per boundary quad and no
    interior 'boundary'; tet volumes add up to the hex volume and are all positive."""
    P, hexes, corners = grid_hexes(3, shear=0.2)
    tets = kuhn_tets(corners, P)
    vols = tet_volumes(P, tets)
    assert (vols > 0).all()
    assert vols.sum() == pytest.approx(1.0, rel=1e-12)
    assert boundary_faces("tet4", tets).shape[0] == 2 * boundary_faces("hex8", hexes).shape[0]


def test_tet10_midside_nodes_are_shared_and_at_midpoints():
    P, _, corners = grid_hexes(2)
    tets = kuhn_tets(corners, P)
    p10, t10 = tet10_from_tet4(P, tets)
    from toolkit.common.meshes.topology import TET_EDGES

    assert np.allclose(p10[t10[:, 4:]], 0.5 * (p10[t10[:, TET_EDGES[:, 0]]] + p10[t10[:, TET_EDGES[:, 1]]]))
    # Euler: each unique edge once -> mid-node count equals the edge count of the tet4 mesh
    edges = np.unique(np.sort(tets[:, TET_EDGES].reshape(-1, 2), axis=1), axis=0)
    assert p10.shape[0] - P.shape[0] == edges.shape[0]


def test_surface_mesh_maps_back_to_parent_nodes():
    P, hexes, _ = grid_hexes(2)
    mesh = Mesh(P, {"hex8": hexes}, node_sets={"bottom": np.flatnonzero(P[:, 2] == 0)})
    surf = mesh.surface()
    parent = surf.point_data["parent_node"]
    assert np.allclose(surf.points, P[parent])
    assert surf.n_points == 26  # 27 grid nodes minus the centre
    assert np.array_equal(parent[surf.node_sets["bottom"]], mesh.node_sets["bottom"])


def test_mesh_deep_copies_and_pickles_with_sets_and_fields():
    """A mesh survives ``copy.deepcopy`` and ``pickle`` (process pools send meshes pickled) with its
    node/element sets and point/cell fields, and the copy stays read-only."""
    import copy
    import pickle

    mesh = Mesh(REG_TET, {"tet4": [[0, 1, 2, 3]]}, node_sets={"a": [3, 1]}, element_sets={"e": [0]},
                point_data={"u": np.arange(12.0).reshape(4, 3)}, cell_data={"k": np.array([7])})
    for other in (copy.deepcopy(mesh), pickle.loads(pickle.dumps(mesh))):
        assert other is not mesh and other.equals(mesh)
        assert other.node_sets["a"].tolist() == [1, 3] and other.element_sets["e"].tolist() == [0]
        assert other.point_data["u"].tolist() == mesh.point_data["u"].tolist()
        assert other.cell_data["k"].tolist() == [7]
        assert not other.points.flags.writeable
        with pytest.raises(TypeError):
            other.node_sets["b"] = np.array([0])
