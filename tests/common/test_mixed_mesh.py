"""Meshes that mix hexahedra, wedges and tetrahedra: blocks, global element numbering,
wedge quality, and boundaries across conforming interfaces of different cell types.
Units mm."""

import numpy as np
import pytest

from toolkit.common.meshes.convert import to_skfem
from toolkit.common.meshes.mesh import InvertedElementError, Mesh, MeshError
from toolkit.common.meshes.topology import triangulated_boundary, wedges_from_hexes
from toolkit.common.phantoms.mixed_bar import mixed_bar

#: right prism on an equilateral triangle of side 2 mm, height 3 mm, Abaqus C3D6 order
_S = np.sqrt(3.0)
PRISM = np.array([[0, 0, 0], [2, 0, 0], [1, _S, 0], [0, 0, 3], [2, 0, 3], [1, _S, 3]], float)


def _wedge(points):
    return Mesh(points, {"wedge6": [np.arange(6)]})


def test_ideal_wedge_has_scaled_jacobian_one_and_mirror_minus_one():
    """The right prism on an equilateral triangle is the ideal wedge (SJ = 1, whatever its
    height); swapping its two triangles mirrors it (SJ = -1)."""
    assert _wedge(PRISM).scaled_jacobian() == pytest.approx([1.0], rel=1e-14)
    tall = PRISM * [1, 1, 5]
    assert _wedge(tall).scaled_jacobian() == pytest.approx([1.0], rel=1e-14)
    mirrored = Mesh(PRISM, {"wedge6": [[3, 4, 5, 0, 1, 2]]})
    assert mirrored.scaled_jacobian() == pytest.approx([-1.0], rel=1e-14)


@pytest.mark.parametrize("angle", [10.0, 30.0, 60.0])
def test_sheared_and_right_angled_wedges(angle):
    """Tilting the prism edges by an angle a: every corner's unit edge vectors span
    sin 60 cos a, so SJ = cos a. A right isosceles base (the wedges of a cut cube) has
    its worst corners at 45 degrees: SJ = sin 45 / sin 60."""
    a = np.deg2rad(angle)
    tilted = PRISM.copy()
    tilted[3:, 0] += 3 * np.tan(a)
    assert _wedge(tilted).scaled_jacobian()[0] == pytest.approx(np.cos(a), rel=1e-12)
    right = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1]], float)
    assert _wedge(right).scaled_jacobian()[0] == pytest.approx(np.sin(np.pi / 4) / np.sin(np.pi / 3), rel=1e-12)


def test_blocks_number_elements_globally():
    """Blocks in order hex8, wedge6, tet4; each block's elements are its global indices, an
    element set may span blocks and splits into each block's local indices."""
    m = mixed_bar(1)
    blocks = m.volume_blocks
    assert [b.ctype for b in blocks] == ["hex8", "wedge6", "tet4"] == list(m.volume_types)
    assert [b.offset for b in blocks] == [0, 16, 48] and m.n_volume_cells == m.n_cells == 96
    assert np.array_equal(np.concatenate([b.elements for b in blocks]), np.arange(96))
    upper = m.element_set("upper")
    parts = [b.local(upper) for b in blocks]
    assert all(p.size for p in parts)  # the set spans all three blocks
    assert np.array_equal(np.concatenate([b.offset + p for b, p in zip(blocks, parts)]), upper)


def test_single_type_accessors_name_the_types_of_a_mixed_mesh():
    m = mixed_bar(1)
    with pytest.raises(MeshError, match=r"volume cell types \['hex8', 'wedge6', 'tet4'\].*volume_blocks"):
        _ = m.volume_type
    with pytest.raises(MeshError, match=r"tri3, .* quad4 faces .*boundary_face_blocks"):
        m.boundary_faces()
    assert _wedge(PRISM).volume_type == "wedge6"


def test_check_names_an_inverted_wedge_by_global_index():
    """An inverted wedge in the middle block is reported with its type and global index."""
    m = mixed_bar(1)
    cells = dict(m.cells)
    wedges = cells["wedge6"].copy()
    wedges[3] = wedges[3][[3, 4, 5, 0, 1, 2]]
    cells["wedge6"] = wedges
    bad = Mesh(m.points, cells)
    assert bad.scaled_jacobian()[16 + 3] < 0
    with pytest.raises(InvertedElementError, match=r"hex8/wedge6/tet4 elements .* worst: wedge6 element 19") as info:
        bad.check()
    assert info.value.elements.tolist() == [19]


def test_mixed_boundary_is_closed_and_outward():
    """The bar (L-section: a 10 x 10 mm square with a 5 x 5 mm flange, 40 mm long) has
    hexahedra beside wedges (quad interface) and tetrahedra on the wedges (triangle
    interface). Its boundary faces are exactly the outer surface: area 50 mm x 40 mm of
    perimeter plus the two 125 mm^2 ends (an interface face left over would add area);
    the surface is closed and consistently oriented (every directed edge once, its reverse
    once); and outward (divergence theorem: 1/3 sum x . n dA = the volume 5000 mm^3)."""
    m = mixed_bar(1)
    blocks = m.boundary_face_blocks()
    assert set(blocks) == {"tri3", "quad4"}
    tris = triangulated_boundary(m.cells)
    x = m.points[tris]
    area = 0.5 * np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    assert np.linalg.norm(area, axis=1).sum() == pytest.approx(50 * 40 + 2 * 125, rel=1e-12)
    assert np.einsum("fi,fi->", x.mean(axis=1), area) / 3 == pytest.approx(5000.0, rel=1e-12)
    directed = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    keys = set(map(tuple, directed.tolist()))
    assert len(keys) == len(directed) and keys == set(map(tuple, directed[:, ::-1].tolist()))


def test_mixed_surface_mesh_has_both_face_types():
    m = mixed_bar(1)
    surf = m.surface()
    assert list(surf.cells) == ["tri3", "quad4"]
    parent = surf.point_data["parent_node"]
    assert np.allclose(surf.points, m.points[parent])
    assert np.array_equal(parent[surf.node_sets["end0"]], m.node_sets["end0"])
    assert surf.n_points == m.n_points - 7  # the 7 nodes inside the bar


def test_wedge_split_orients_and_keeps_volume():
    """Two wedges per hexahedron fill it (volumes by 6-point quadrature add up to the
    sheared cube's 1 mm^3); a left-handed corner table is flipped to positive wedges."""
    corners = np.arange(8).reshape(2, 2, 2)[None]
    P = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
    P[:, 0] += 0.3 * P[:, 2]
    w = wedges_from_hexes(corners, P)
    assert w.shape == (2, 6)
    assert (_wedge_volumes(P, w) > 0).all() and _wedge_volumes(P, w).sum() == pytest.approx(1.0, rel=1e-12)
    mirrored = corners.transpose(0, 2, 1, 3)  # swap local i and j: a left-handed frame
    w2 = wedges_from_hexes(mirrored, P)
    assert (_wedge_volumes(P, w2) > 0).all()


def _wedge_volumes(P, wedges):
    from toolkit.common.fem import reference_element

    ref = reference_element("wedge6")
    xi, wt = ref.quadrature(2)
    J = np.einsum("eai,qak->eqik", P[wedges], ref.gradient(xi))
    return np.linalg.det(J) @ wt


def test_skfem_conversion_refuses_wedges_by_name():
    """scikit-fem reads no meshio wedges: the conversion says so instead of failing inside skfem."""
    with pytest.raises(MeshError, match=r"not 'wedge6'"):
        to_skfem(_wedge(PRISM))
