"""Boundary types of the face nodes: read from the phantom's node sets, the sliding
models, the explicit one-hot encoding and the k-nearest-neighbour label transfer."""

import numpy as np
import pytest

from toolkit.common.meshes.mesh import Mesh
from toolkit.common.phantoms.phantom import FaceShape, face_hex
from toolkit.static.boundary import (
    BoundaryConditions,
    BoundaryError,
    NodeType,
    knn_labels,
)

LIP_FACE_SETS = ("upper_lip_face", "lower_lip_face")


@pytest.fixture(scope="module")
def phantom():
    return face_hex("coarse")


@pytest.fixture(scope="module")
def bc(phantom):
    return BoundaryConditions.from_mesh(phantom.mesh, phantom.segments)


def _without_lip_faces(mesh: Mesh) -> Mesh:
    sets = {k: v for k, v in mesh.node_sets.items() if k not in LIP_FACE_SETS}
    return Mesh(mesh.points, dict(mesh.cells), node_sets=sets)


def test_types_and_segments_follow_the_node_sets(phantom, bc):
    """Every node of a boundary set gets that set's type (the sets are disjoint, so the
    counts equal the set sizes and the rest is free); attached nodes belong to their
    segment (maxilla -> lefort, mandible -> distal) and every mucosa node to the segment
    of its ``mucosa_<segment>`` set, the bone it slides on."""
    sets = phantom.mesh.node_sets
    assert bc.n_nodes == phantom.mesh.n_points
    for kind, name in ((NodeType.FIXED, "fixed"), (NodeType.MUCOSA_SLIDING, "mucosa_sliding"),
                       (NodeType.LIP_SLIDING, "lip_sliding")):
        np.testing.assert_array_equal(bc.nodes(kind), sets[name])
    np.testing.assert_array_equal(bc.nodes(NodeType.MOVING), np.union1d(sets["maxilla"], sets["mandible"]))
    n_typed = sum(sets[s].size for s in ("fixed", "maxilla", "mandible", "mucosa_sliding", "lip_sliding"))
    assert bc.nodes(NodeType.FREE).size == phantom.mesh.n_points - n_typed
    np.testing.assert_array_equal(bc.segment_nodes(NodeType.MOVING, "lefort"), sets["maxilla"])
    np.testing.assert_array_equal(bc.segment_nodes(NodeType.MOVING, "distal"), sets["mandible"])
    for name in bc.segment_names:
        np.testing.assert_array_equal(bc.segment_nodes(NodeType.MUCOSA_SLIDING, name), sets[f"mucosa_{name}"])
    assert np.all(bc.segment[bc.nodes(NodeType.FIXED)] == -1)
    assert np.all(bc.segment[bc.nodes(NodeType.FREE)] == -1)


def test_lip_pairs_are_coincident_upper_and_lower_nodes(phantom, bc):
    """The closed mouth slit duplicates its nodes: upper_lip[i] (on the upper-lip face, a
    slave in the contact) and lower_lip[i] (its master) are the two copies of one point
    (distance 0), every lip-sliding node is in exactly one pair, and no node is its own
    partner."""
    sets = phantom.mesh.node_sets
    P = phantom.mesh.points
    assert bc.upper_lip.size == bc.lower_lip.size > 0
    np.testing.assert_array_equal(P[bc.upper_lip], P[bc.lower_lip])
    assert np.all(bc.upper_lip != bc.lower_lip)
    assert np.isin(bc.upper_lip, sets["upper_lip_face"]).all()
    assert np.isin(bc.lower_lip, sets["lower_lip_face"]).all()
    np.testing.assert_array_equal(np.sort(np.concatenate([bc.upper_lip, bc.lower_lip])), sets["lip_sliding"])


def test_lip_pairs_by_proximity_with_open_mouth():
    """Without the lip-face sets, lip nodes within the 0.2 mm threshold are paired by
    proximity and the higher node of a pair is the upper lip. With the mouth slightly open
    (0.1 mm gap at the skin) the upper copy is the higher one: the pairs equal those of
    the face sets."""
    ph = face_hex("coarse", FaceShape(mouth_open=0.1))
    ref = BoundaryConditions.from_mesh(ph.mesh, ph.segments)
    prox = BoundaryConditions.from_mesh(_without_lip_faces(ph.mesh), ph.segments)
    assert np.all(ph.mesh.points[prox.upper_lip, 2] >= ph.mesh.points[prox.lower_lip, 2])
    assert sorted(zip(prox.upper_lip.tolist(), prox.lower_lip.tolist())) == \
        sorted(zip(ref.upper_lip.tolist(), ref.lower_lip.tolist()))


def test_lip_pairs_by_proximity_with_closed_mouth(phantom, bc):
    """Without the lip-face sets, on the closed mouth (coincident copies) the upper lip of a
    pair must still be the copy used by the upper-lip elements (the node's own side, as for
    the mucosa): the pairs must equal those given by the face sets."""
    prox = BoundaryConditions.from_mesh(_without_lip_faces(phantom.mesh), phantom.segments)
    assert sorted(zip(prox.upper_lip.tolist(), prox.lower_lip.tolist())) == \
        sorted(zip(bc.upper_lip.tolist(), bc.lower_lip.tolist()))


def test_overlapping_sets_raise_naming_both(phantom):
    """A node can have one boundary type: a fixed node also listed as mucosa is refused,
    the error naming both sets."""
    mesh = phantom.mesh
    clash = mesh.node_sets["fixed"][:2]
    bad = mesh.with_node_sets(mucosa_sliding=np.concatenate([mesh.node_sets["mucosa_sliding"], clash]))
    with pytest.raises(BoundaryError, match=r"'fixed' and 'mucosa_sliding' share 2 nodes"):
        BoundaryConditions.from_mesh(bad, phantom.segments)
    bad = mesh.with_node_sets(mandible=np.concatenate([mesh.node_sets["mandible"], mesh.node_sets["maxilla"][:1]]))
    with pytest.raises(BoundaryError, match=r"'maxilla' and 'mandible'"):
        BoundaryConditions.from_mesh(bad, phantom.segments)


def test_fewer_than_three_fixed_or_moving_nodes_raise(phantom):
    """With fewer than 3 fixed/moving nodes the face could translate and rotate freely
    (rigid-body modes, a singular stiffness): refused before any solve."""
    P = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    cube = Mesh(P, {"hex8": [np.arange(8)]}, node_sets={"fixed": [0, 1]})
    with pytest.raises(BoundaryError, match="only 2 fixed/moving nodes"):
        BoundaryConditions.from_mesh(cube, {})
    with pytest.raises(BoundaryError, match="only 0"):
        BoundaryConditions(np.zeros(8), np.full(8, -1), (), np.zeros(0, np.int64), np.zeros(0, np.int64))
    # three fixed nodes are enough
    assert BoundaryConditions.from_mesh(cube.with_node_sets(fixed=[0, 1, 2]), {}).nodes(NodeType.FIXED).size == 3


def test_sliding_models(bc):
    """'none' (the lip-sliding paper's method 1): mucosa attached to its segment, i.e. moving with the
    same segment, lips free; 'mucosa': lips free, mucosa kept; 'mucosa+lip': unchanged."""
    mucosa = bc.nodes(NodeType.MUCOSA_SLIDING)
    lips = bc.nodes(NodeType.LIP_SLIDING)
    none = bc.with_sliding("none")
    assert np.all(none.types[mucosa] == NodeType.MOVING)
    np.testing.assert_array_equal(none.segment[mucosa], bc.segment[mucosa])
    assert np.all(none.types[lips] == NodeType.FREE)
    assert none.upper_lip.size == none.lower_lip.size == 0
    assert none.nodes(NodeType.MUCOSA_SLIDING).size == none.nodes(NodeType.LIP_SLIDING).size == 0
    muc = bc.with_sliding("mucosa")
    np.testing.assert_array_equal(muc.nodes(NodeType.MUCOSA_SLIDING), mucosa)
    assert np.all(muc.types[lips] == NodeType.FREE) and muc.upper_lip.size == 0
    full = bc.with_sliding("mucosa+lip")
    np.testing.assert_array_equal(full.types, bc.types)
    np.testing.assert_array_equal(full.upper_lip, bc.upper_lip)
    with pytest.raises(ValueError, match="sliding must be"):
        bc.with_sliding("lips")


def test_one_hot_encoding(bc):
    """The PointNet++ paper's explicit encoding (free, moving, fixed): one 1 per row; sliding nodes
    (mucosa, lips) are not prescribed, so they count as free."""
    oh = bc.one_hot()
    assert oh.shape == (bc.n_nodes, 3)
    np.testing.assert_array_equal(oh.sum(axis=1), 1.0)
    assert set(np.unique(oh)) == {0.0, 1.0}
    expected = np.select([bc.types == NodeType.MOVING, bc.types == NodeType.FIXED], [1, 2], 0)
    np.testing.assert_array_equal(oh.argmax(axis=1), expected)
    sliding = np.isin(bc.types, (NodeType.MUCOSA_SLIDING, NodeType.LIP_SLIDING))
    assert sliding.any() and np.all(oh[sliding, 0] == 1.0)


def test_knn_labels_majority_vote_hand_computed():
    """Majority of the k nearest labelled points, ties to the smallest label, voters
    beyond max_distance ignored, nodes with no voter get ``default`` (0 unless given).
    Labelled points on the x axis at 0, 1, 2, 3, 4 with labels 0, 0, 1, 1, 1."""
    lab_pts = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0]])
    labels = np.array([0, 0, 1, 1, 1])
    q = np.array([[0.1, 0, 0],   # voters at 0, 1, 2 -> 0, 0, 1 -> 0
                  [1.9, 0, 0],   # voters at 2, 1, 3 -> 1, 0, 1 -> 1
                  [3.9, 0, 0]])  # voters at 4, 3, 2 -> 1 -> 1
    np.testing.assert_array_equal(knn_labels(q, lab_pts, labels, k=3), [0, 1, 1])
    # k = 2 at 1.4: voters at 1 (label 0) and 2 (label 1): a tie, the smallest label wins
    np.testing.assert_array_equal(knn_labels(np.array([[1.4, 0, 0]]), lab_pts, labels, k=2), [0])
    # k = 3 at 0.4 with max_distance 0.7: only the voter at 0 (d 0.4) and 1 (d 0.6) count -> 0;
    # at 4.5 with max_distance 0.7: only the voter at 4 counts -> 1
    np.testing.assert_array_equal(
        knn_labels(np.array([[0.4, 0, 0], [4.5, 0, 0]]), lab_pts, labels, k=3, max_distance=0.7), [0, 1])
    # far from everything: default (0 unless given)
    far = np.array([[50.0, 0, 0]])
    np.testing.assert_array_equal(knn_labels(far, lab_pts, labels, k=3, max_distance=5.0), [0])
    np.testing.assert_array_equal(knn_labels(far, lab_pts, labels, k=3, max_distance=5.0, default=4), [4])
    # without max_distance every node is labelled by its neighbours, however far
    np.testing.assert_array_equal(knn_labels(far, lab_pts, labels, k=3), [1])
    # k larger than the labelled set is clipped to it
    np.testing.assert_array_equal(knn_labels(q, lab_pts, labels, k=50), [1, 1, 1])


def test_knn_labels_transfers_phantom_types_to_itself(phantom, bc):
    """The PointNet++ paper's transfer of types from a labelled mesh: labelling the phantom's own
    nodes from themselves with k = 1 (each node is its own nearest neighbour at distance 0;
    coincident lip copies share a type) gives back the types exactly."""
    P = phantom.mesh.points
    np.testing.assert_array_equal(knn_labels(P, P, bc.types, k=1), bc.types)


# ------------------------------------------------------------- release bands
def _two_segment_block(h: float):
    """A 40 x 10 x 10 mm hex block whose bottom face is attached to ``lefort`` for x < 20 and to
    ``distal`` from x = 20 on (node spacing ``h`` mm), with a fixed top face."""
    from toolkit.common.phantoms.phantom import BoneSegment, block

    n = round(40 / h)
    mesh = block([np.linspace(0, 40, n + 1), np.linspace(0, 10, round(10 / h) + 1), np.linspace(0, 10, 3)])
    x, z = mesh.points[:, 0], mesh.points[:, 2]
    bottom = np.flatnonzero(z == 0)
    mesh = mesh.with_node_sets(bone=bottom, maxilla=bottom[x[bottom] < 20 - 1e-9],
                               mandible=bottom[x[bottom] >= 20 - 1e-9], fixed=np.flatnonzero(z == 10))
    surface = Mesh(np.zeros((3, 3)) + np.eye(3), {"tri3": np.array([[0, 1, 2]])})
    segments = {"lefort": BoneSegment("lefort", surface, np.zeros(3), "maxilla"),
                "distal": BoneSegment("distal", surface, np.zeros(3), "mandible")}
    return mesh, segments


@pytest.mark.parametrize("h", [2.0, 1.0, 0.5])
def test_release_band_has_the_same_width_at_every_mesh_size(h):
    """Nodes closer than width/2 (through the tissue) to a node with another driver are
    freed: along the bottom face, every node less than 5 mm from the other side's nearest
    node. With spacing h the freed nodes span between 10 - 3h and 10 - h mm (grid rounding
    at both ends), centred on the border between the last lefort node (20 - h) and the
    first distal one (20) within h: the band is 10 mm wide whatever the mesh size. The
    fixed top face keeps its nodes; width 0 frees nothing."""
    mesh, segments = _two_segment_block(h)
    bc = BoundaryConditions.from_mesh(mesh, segments)
    assert bc.with_release_bands(mesh, 0.0) is bc
    out = bc.with_release_bands(mesh, 10.0)
    x = mesh.points[out.released, 0]
    assert np.all(mesh.points[out.released, 2] == 0)
    assert 10.0 - 3 * h - 1e-9 <= x.max() - x.min() <= 10.0 - h + 1e-9
    assert abs(0.5 * (x.max() + x.min()) - (20.0 - 0.5 * h)) <= h
    assert np.all(out.types[out.released] == NodeType.FREE) and np.all(out.segment[out.released] == -1)
    assert out.nodes(NodeType.FIXED).size == bc.nodes(NodeType.FIXED).size
    with pytest.raises(ValueError, match="release width = -1.0 mm"):
        bc.with_release_bands(mesh, -1.0)


def test_a_bone_no_plan_moves_counts_as_fixed():
    """The skull (a segment no plan moves, on which the degloved tissue above the Le Fort I
    cut slides) is as immobile as the fixed nodes: no band between them, but a band where
    it meets a moving segment. On the paper phantom: released nodes lie only near the
    osteotomy lines, the occlusal level between the jaws, the sagittal split and the
    ramus, never deep inside the skull's sliding region."""
    from toolkit.static.plan import SEGMENTS

    ph = face_hex("paper")
    bc = BoundaryConditions.from_mesh(ph.mesh, ph.segments)
    drivers = bc.drivers()
    skull = bc.segment_nodes(NodeType.MUCOSA_SLIDING, "skull")
    assert skull.size and np.all(drivers[skull] == 0) and np.all(drivers[bc.nodes(NodeType.FIXED)] == 0)
    assert all(1 + k in drivers for k, n in enumerate(bc.segment_names) if n in SEGMENTS)
    out = bc.with_release_bands(ph.mesh, 10.0)
    released_skull = np.intersect1d(out.released, skull)
    z = ph.mesh.points[released_skull, 2]
    lefort_cut = ph.mesh.points[ph.mesh.node_sets["maxilla"], 2].max()
    assert released_skull.size and z.max() < lefort_cut + 10.0  # only next to the Le Fort segment


def _two_segment_tet10_block(h: float):
    """:func:`_two_segment_block` as tet10 (straight edges), its sets holding their corners and
    the mid-edge nodes whose two corners they hold."""
    from toolkit.common.meshes.topology import tet10_from_tet4, tet10_mid_edges
    from toolkit.common.phantoms.phantom import block

    hexes, segments = _two_segment_block(h)
    tet4 = block([np.linspace(0, 40, round(40 / h) + 1), np.linspace(0, 10, round(10 / h) + 1),
                  np.linspace(0, 10, 3)], "tet4")
    assert np.array_equal(tet4.points, hexes.points)
    points10, tets10 = tet10_from_tet4(tet4.points, tet4.cells["tet4"])
    mid, a, b = tet10_mid_edges(tets10)
    sets = {}
    for name, ids in hexes.node_sets.items():
        member = np.zeros(points10.shape[0], dtype=bool)
        member[ids] = True
        sets[name] = np.concatenate([ids, mid[member[a] & member[b]]])
    return Mesh(points10, {"tet10": tets10}, node_sets=sets), segments


def test_mid_edge_nodes_are_freed_with_a_corner_of_their_edge():
    """A release band decides node by node: on tet10 it leaves mid-edge nodes attached beside
    freed corners (the bone would bend their edges). After the rule, every bound mid-edge node
    has both corners of its type and segment; nodes bound before whose corners agree stay bound;
    the node sets as read (no band) already agree and are returned as they are, as is a hex mesh."""
    from toolkit.common.meshes.topology import tet10_mid_edges

    mesh, segments = _two_segment_tet10_block(2.0)
    bc = BoundaryConditions.from_mesh(mesh, segments)
    assert bc.with_mid_edges_of_corners(mesh) is bc
    banded = bc.with_release_bands(mesh, 10.0)
    mid, a, b = tet10_mid_edges(mesh.cells["tet10"])
    t, s = banded.types, banded.segment
    mixed = (t[mid] != 0) & ((t[a] != t[mid]) | (t[b] != t[mid]) | (s[a] != s[mid]) | (s[b] != s[mid]))
    assert mixed.sum() > 0  # the band leaves such nodes: the rule has work to do
    out = banded.with_mid_edges_of_corners(mesh)
    t2, s2 = out.types, out.segment
    assert not np.any((t2[mid] != 0) & ((t2[a] != t2[mid]) | (t2[b] != t2[mid]) | (s2[a] != s2[mid])
                                        | (s2[b] != s2[mid])))
    assert np.array_equal(np.flatnonzero(t2 != t), mid[mixed])
    assert np.isin(mid[mixed], out.released).all()
    hexes, hex_segments = _two_segment_block(2.0)
    hex_bc = BoundaryConditions.from_mesh(hexes, hex_segments).with_release_bands(hexes, 10.0)
    assert hex_bc.with_mid_edges_of_corners(hexes) is hex_bc
