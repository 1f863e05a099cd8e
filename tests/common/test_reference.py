"""Reference elements: shape functions, gradients, quadrature and faces against closed
forms. float64; reference coordinates are dimensionless."""

from math import factorial

import numpy as np
import pytest

from toolkit.common.fem import REFERENCE_ELEMENTS, WEDGE_VTK_ORDER, reference_element

ALL = list(REFERENCE_ELEMENTS)
VOLUME = [n for n, r in REFERENCE_ELEMENTS.items() if r.dim == 3]
#: exact measure of each reference cell: [-1,1]^3, triangle x [-1,1], unit simplices, [-1,1]^2
MEASURE = {"hex8": 8.0, "wedge6": 1.0, "tet4": 1 / 6, "tet10": 1 / 6, "tri3": 0.5, "quad4": 4.0}


def _inside(ref, n, rng):
    """``n`` random points inside the reference cell of ``ref``."""
    if ref.name in ("hex8", "quad4"):
        return rng.uniform(-1, 1, (n, ref.dim))
    bary = rng.dirichlet(np.ones(3 if ref.name in ("wedge6", "tri3") else 4), n)
    simplex = bary[:, 1:]
    if ref.name == "wedge6":
        return np.column_stack([simplex, rng.uniform(-1, 1, n)])
    return simplex


@pytest.mark.parametrize("name", ALL)
def test_shape_functions_interpolate_and_reproduce_linear_fields(name):
    """Lagrange property N_a(x_b) = delta_ab; partition of unity sum_a N_a = 1 (gradients
    sum to 0); completeness sum_a x_a N_a(xi) = xi, the property behind the patch test."""
    ref = reference_element(name)
    rng = np.random.default_rng(0)
    xi = _inside(ref, 50, rng)
    assert np.abs(ref.shape(ref.nodes) - np.eye(ref.n_nodes)).max() < 1e-14
    N, G = ref.shape(xi), ref.gradient(xi)
    assert N.shape == (50, ref.n_nodes) and G.shape == (50, ref.n_nodes, ref.dim)
    assert np.abs(N.sum(axis=1) - 1).max() < 1e-14
    assert np.abs(G.sum(axis=1)).max() < 1e-14
    assert np.abs(N @ ref.nodes - xi).max() < 1e-14
    assert np.abs(np.einsum("qak,aj->qjk", G, ref.nodes) - np.eye(ref.dim)).max() < 1e-14


@pytest.mark.parametrize("name", ALL)
def test_gradients_match_finite_differences(name):
    """dN/dxi against central differences (h = 1e-6: truncation of quadratic functions
    is zero, round-off ~1e-10)."""
    ref = reference_element(name)
    xi = _inside(ref, 20, np.random.default_rng(1))
    h = 1e-6
    fd = np.stack([(ref.shape(xi + h * e) - ref.shape(xi - h * e)) / (2 * h) for e in np.eye(ref.dim)], axis=-1)
    assert np.abs(ref.gradient(xi) - fd).max() < 1e-9


def _exact_monomial(name, powers):
    """Exact integral of prod xi_k^p_k over the reference cell."""
    def line(p):
        return 0.0 if p % 2 else 2.0 / (p + 1)

    def simplex(ps):
        return np.prod([factorial(p) for p in ps]) / factorial(sum(ps) + len(ps))

    if name in ("hex8", "quad4"):
        return np.prod([line(p) for p in powers])
    if name == "wedge6":
        return simplex(powers[:2]) * line(powers[2])
    return simplex(powers)


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("order", [1, 2, 3, 4, 5])
def test_quadrature_is_exact_for_polynomials_of_its_order(name, order):
    """A rule of order p integrates every monomial of total degree <= p exactly
    (1e-14), and its weights, all positive, sum to the reference measure."""
    ref = reference_element(name)
    x, w = ref.quadrature(order)
    assert np.all(w > 0)
    assert w.sum() == pytest.approx(MEASURE[name], rel=1e-14)
    grids = np.meshgrid(*[np.arange(order + 1)] * ref.dim, indexing="ij")
    powers = np.stack([g.ravel() for g in grids], axis=1)
    for p in powers[powers.sum(axis=1) <= order]:
        value = np.sum(w * np.prod(x ** p, axis=1))
        assert value == pytest.approx(_exact_monomial(name, p), abs=1e-14), p


def test_static_rules_are_the_classical_ones():
    """The rules the static assembly uses: 2x2x2 Gauss (hex8), the centroid (tet4), the
    4-point degree-2 rule (tet10) and 3-point triangle x 2-point Gauss (wedge6)."""
    assert reference_element("hex8").quadrature(2)[0].shape == (8, 3)
    assert reference_element("tet4").quadrature(1)[0].tolist() == [[0.25, 0.25, 0.25]]
    x, _ = reference_element("tet10").quadrature(2)
    a = (5 - np.sqrt(5)) / 20
    assert x.shape == (4, 3) and np.isclose(np.sort(x, axis=None)[0], a)
    x, _ = reference_element("wedge6").quadrature(2)
    assert x.shape == (6, 3) and np.allclose(np.unique(np.abs(x[:, 2])), 1 / np.sqrt(3))


def _divergence_volume(ref, x):
    """Volume by the divergence theorem, V = 1/3 sum over faces of centroid . area vector,
    the faces taken as listed (planar faces; quads split along 0-2)."""
    total = 0.0
    for group in ref.faces:
        tris = [group] if group.shape[1] == 3 else [group[:, [0, 1, 2]], group[:, [0, 2, 3]]]
        for t in tris:
            p = x[t]  # (f, 3, 3)
            area = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
            total += np.einsum("fi,fi->", p.mean(axis=1), area) / 3.0
    return total


@pytest.mark.parametrize("name", VOLUME)
def test_faces_are_outward_and_close_the_cell(name):
    """On the reference cell and on a random positive affine image of it, the listed faces
    enclose the cell's volume with outward normals (divergence theorem: a face turned
    inward would subtract its share); every face edge is met once in each direction, so
    the faces form a closed, consistently oriented surface."""
    ref = reference_element(name)
    rng = np.random.default_rng(2)
    A = np.eye(3) + 0.3 * rng.uniform(-1, 1, (3, 3))
    assert np.linalg.det(A) > 0
    for x, volume in ((ref.nodes, ref.measure), (ref.nodes @ A.T + 5.0, ref.measure * np.linalg.det(A))):
        assert _divergence_volume(ref, x) == pytest.approx(volume, rel=1e-12)
    directed = np.concatenate([np.stack([f, np.roll(f, -1, axis=1)], axis=-1).reshape(-1, 2) for f in ref.faces])
    assert len({tuple(e) for e in directed.tolist()}) == len(directed)
    assert {tuple(e) for e in directed.tolist()} == {tuple(e) for e in directed[:, ::-1].tolist()}
    assert {tuple(sorted(e)) for e in directed.tolist()} == {tuple(sorted(e)) for e in ref.edges.tolist()}


def test_wedge_faces_by_size():
    ref = reference_element("wedge6")
    assert [f.shape for f in ref.faces] == [(2, 3), (3, 4)]
    assert ref.faces_flat is None and reference_element("hex8").faces_flat.shape == (6, 4)


@pytest.mark.parametrize("name", VOLUME)
def test_corner_frames_are_right_handed_edges(name):
    """At every corner the frame's three nodes are the ends of the corner's edges, and
    det[x1 - x0, x2 - x0, x3 - x0] > 0 on the positive reference cell."""
    ref = reference_element(name)
    edges = {tuple(sorted(e)) for e in ref.edges.tolist()}
    for c, frame in zip(ref.corners, ref.corner_frames):
        assert all(tuple(sorted((c, e))) in edges for e in frame)
        assert np.linalg.det(ref.nodes[frame] - ref.nodes[c]) > 0


def test_wedge_node_order_is_abaqus_and_vtk_is_its_permutation():
    """Abaqus C3D6 / gmsh / meshio: the right-hand normal of triangle (0, 1, 2) points into
    the wedge, towards (3, 4, 5). In VTK order (WEDGE_VTK_ORDER) it points out, and the
    permutation is the one meshio applies when writing VTU."""
    from meshio._vtk_common import meshio_to_vtk_order

    x = reference_element("wedge6").nodes
    n = np.cross(x[1] - x[0], x[2] - x[0])
    assert n @ (x[3:].mean(axis=0) - x[:3].mean(axis=0)) > 0
    v = x[WEDGE_VTK_ORDER]
    assert np.cross(v[1] - v[0], v[2] - v[0]) @ (v[3:].mean(axis=0) - v[:3].mean(axis=0)) < 0
    assert np.array_equal(meshio_to_vtk_order("wedge"), WEDGE_VTK_ORDER)


def test_tet10_midside_nodes_sit_on_their_edges():
    ref = reference_element("tet10")
    mid = 0.5 * (ref.nodes[ref.edges[:, 0]] + ref.nodes[ref.edges[:, 1]])
    assert np.allclose(ref.nodes[4:], mid)


def test_records_name_their_formats_and_errors_list_the_types():
    assert {n: (r.meshio, r.vtk_id, r.abaqus[0]) for n, r in REFERENCE_ELEMENTS.items()} == {
        "hex8": ("hexahedron", 12, "C3D8"), "wedge6": ("wedge", 13, "C3D6"), "tet4": ("tetra", 10, "C3D4"),
        "tet10": ("tetra10", 24, "C3D10"), "tri3": ("triangle", 5, "S3"), "quad4": ("quad", 9, "S4")}
    with pytest.raises(KeyError, match=r"unknown cell type 'pyramid5'; expected one of \['hex8'"):
        reference_element("pyramid5")
    with pytest.raises(ValueError, match=r"expected \(Q, 3\)"):
        reference_element("hex8").shape(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="non-negative integer"):
        reference_element("tet4").quadrature(-1)
