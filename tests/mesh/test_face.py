"""``toolkit.mesh``: the mouth cut, the labelling rules and the whole pipeline on the coarse phantom's
surfaces (the round trip's small version; ``benchmarks/own_face.py`` runs it at paper size)."""

from pathlib import Path

import numpy as np
import pytest

from toolkit.common import face_hex, read
from toolkit.common.meshes.topology import boundary_faces
from toolkit.mesh import DEFAULT
from toolkit.mesh.face import FaceInputError, dihedral_angles, mesh_face
from toolkit.mesh.mouth import MouthError, cut_mouth
from toolkit.mesh.rules import RulesError, read_rules
from toolkit.mesh.surface import tissue_surface_of

BACKEND = DEFAULT


@pytest.fixture(scope="module")
def phantom():
    return face_hex("coarse")


@pytest.fixture(scope="module")
def inputs(phantom):
    m = phantom.mesh
    skin = np.zeros(m.n_points, bool)
    skin[m.node_sets["skin"]] = True
    lip = m.node_sets["upper_lip_face"]
    p = m.points[lip[skin[lip]]]
    commissures = np.stack([p[np.argmax(p[:, 0])], p[np.argmin(p[:, 0])]])
    bones = {k: s.surface for k, s in phantom.segments.items()}
    return tissue_surface_of(m), bones, commissures


@pytest.fixture(scope="module")
def face(inputs):
    surface, bones, commissures = inputs
    return mesh_face(surface, bones, commissures, size_mm=10.0, order=2, backend=BACKEND)


def test_dihedral_angles_of_the_regular_tetrahedron():
    p = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    assert np.allclose(dihedral_angles(p, np.array([[0, 1, 2, 3]])), np.degrees(np.arccos(1 / 3)))


def test_mesh_is_quadratic_valid_and_labelled(face, inputs):
    m = face.mesh
    assert m.volume_type == "tet10" and m.scaled_jacobian().min() > 0
    sets = m.node_sets
    for name in ("fixed", "maxilla", "mandible", "mucosa_sliding", "mucosa_lefort", "mucosa_distal", "skin", "bone",
                 "lip_sliding", "upper_lip_face", "lower_lip_face"):
        assert sets[name].size > 0, name
    # the simulation's types are disjoint
    typed = np.concatenate([sets["fixed"], sets["maxilla"], sets["mandible"], sets["mucosa_sliding"],
                            sets["lip_sliding"]])
    assert np.unique(typed).size == typed.size
    # every bone-side node lies on (here: exactly on) a bone
    assert face.report["bone_offset_mm"]["max"] < 0.5
    # the volume is the tissue surface's (the mesher keeps the surface within its tolerance)
    x = m.points[m.volume_cells[:, :4]]
    vol = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0]).sum() / 6
    s = inputs[0].points[inputs[0].cells["tri3"]]
    enclosed = np.einsum("ij,ij->i", s[:, 0], np.cross(s[:, 1], s[:, 2])).sum() / 6
    assert vol == pytest.approx(enclosed, rel=0.01)


def test_lip_faces_pair_up_at_coincident_points(face, inputs):
    m = face.mesh
    up, low = m.node_sets["upper_lip_face"], m.node_sets["lower_lip_face"]
    assert up.size == low.size and np.intersect1d(up, low).size == 0
    assert np.abs(m.points[up] - m.points[low]).max() == 0.0
    # every element holding an upper face's node lies above the slit plane (through the
    # commissures, containing the anterior axis), every one holding a lower face's node below
    c = inputs[2]
    normal = np.cross(c[1] - c[0], [0.0, 1.0, 0.0])
    normal *= np.sign(normal[2]) / np.linalg.norm(normal)
    cells = m.volume_cells
    side = (m.points[cells[:, :4]].mean(axis=1) - c[0]) @ normal
    for nodes, sign in ((up, 1), (low, -1)):
        has = np.isin(cells, nodes).any(axis=1)
        assert has.any() and np.all(np.sign(side[has]) == sign)


def test_labels_agree_with_the_phantom(face, phantom):
    """Share of labelled nodes whose nearest phantom node carries the same set."""
    from scipy.spatial import cKDTree

    ph = phantom.mesh
    tree = cKDTree(ph.points)
    for name, goal in (("bone", 0.95), ("skin", 0.75), ("mucosa_sliding", 0.6), ("fixed", 0.6)):
        ids = face.mesh.node_sets[name]
        _, near = tree.query(face.mesh.points[ids])
        mask = np.zeros(ph.n_points, bool)
        mask[ph.node_sets[name]] = True
        assert mask[near].mean() >= goal, (name, mask[near].mean())
    # the lip muscle: our elements whose nearest phantom element is in the phantom's set, and the
    # share of the phantom's set so reached. The coarse phantom's set is whole elements ~10 mm tall
    # whose centroids lie within 18 mm of the mouth, so it reaches up to 23 mm where the rule stops
    # at 18: recall 0.69-0.73 here (0.97 against the paper phantom, precision 0.98)
    lip = np.zeros(ph.n_volume_cells, bool)
    lip[ph.element_sets["lip_muscle"]] = True
    centroids = ph.points[ph.volume_cells].mean(axis=1)
    ours = np.zeros(face.mesh.n_volume_cells, bool)
    ours[face.mesh.element_sets["lip_muscle"]] = True
    x = face.mesh.points[face.mesh.volume_cells[:, :4]].mean(axis=1)
    near = cKDTree(centroids).query(x)[1]
    precision, recall = lip[near][ours].mean(), ours[lip[near]].mean()
    assert precision >= 0.85 and recall >= 0.6, (precision, recall)


def test_written_mesh_reads_back_with_its_sets(face, tmp_path):
    written = face.write(tmp_path / "face.vtu", image=False)
    back = read(written["mesh"])
    assert back.volume_type == "tet10" and back.n_points == face.mesh.n_points
    for name, ids in face.mesh.node_sets.items():
        assert np.array_equal(np.sort(back.node_sets[name]), np.sort(ids)), name
    import json

    report = json.loads(written["labels"].read_text())
    assert report["node_sets"]["fixed"] == face.mesh.node_sets["fixed"].size
    assert set(report["seconds"]) == {"read_repair", "mesh", "mouth", "label", "order", "quality"}


def test_no_commissures_means_no_lip_sliding(inputs):
    surface, bones, _ = inputs
    face = mesh_face(surface, bones, size_mm=12.0, order=1, backend=BACKEND)
    assert "lip_sliding" not in face.mesh.node_sets and "no lip sliding" in face.report["mouth"]["status"]


def test_mouth_cut_refuses_points_that_are_not_commissures(inputs):
    surface, bones, c = inputs
    from toolkit.mesh.backends import tetrahedralize

    p, t = tetrahedralize(surface.points, surface.cells["tri3"], 10.0, backend=BACKEND)
    with pytest.raises(MouthError, match="30-70 mm apart"):
        cut_mouth(p, t, [c[0], c[0] + 1.0])
    with pytest.raises(MouthError, match="side by side"):
        cut_mouth(p, t, [c[0], c[0] + [0, 40.0, 0]])
    with pytest.raises(MouthError, match="no face of the mesh lies on the mouth slit"):
        cut_mouth(p, t, c + [0, 0, 500.0])
    slit = cut_mouth(p, t, c)
    inner = np.setdiff1d(np.arange(len(p)), np.unique(boundary_faces("tet4", t)))
    assert not np.isin(slit.upper, inner).all()  # the slit opens onto the surface


def test_bad_inputs_are_refused_before_meshing(inputs, tmp_path):
    surface, bones, c = inputs
    with pytest.raises(FaceInputError, match="unknown bone segments"):
        mesh_face(surface, {"jaw": bones["distal"]})
    with pytest.raises(FaceInputError, match="--size"):
        mesh_face(surface, bones, size_mm=0.01)
    with pytest.raises(FaceInputError, match="--order"):
        mesh_face(surface, bones, order=3)
    far = {"distal": bones["distal"].translated(np.array([0, 0, 300.0]))}
    with pytest.raises(FaceInputError, match="lies .* mm from the tissue surface"):
        mesh_face(surface, far)


def test_a_segment_ruled_to_carry_a_strip_is_refused_by_its_share(face, inputs, tmp_path):
    """Rules that give the distal mandible only the tissue within 0.2 degrees of the midline (a
    strip of its front, 0.032-0.034 of the tissue on the bone at 5 mm in repeated meshings; the
    area minimum switched off) fail the labelling on the share it carries, naming the segment and
    both keys; the default rules' segments carry well above it."""
    for name in ("lefort", "distal"):
        assert face.report["segments"][name]["carried_share"] > 0.2
    surface, bones, commissures = inputs
    path = tmp_path / "rules.toml"
    path.write_text('min_carried_mm2 = 0\n[segments.distal]\nattach = "anterior"\nanterior_deg = 0.2\n')
    with pytest.raises(FaceInputError, match=r"segment distal .*a share of 0\.0[0-4]\d.*min_carried_share"):
        mesh_face(surface, bones, commissures, size_mm=5.0, order=1, backend=BACKEND, rules=path)


def test_rules_file_overrides_and_refuses_unknown_keys(tmp_path):
    path = tmp_path / "rules.toml"
    path.write_text('contact_mm = 4.5\n[segments.distal]\ninferior_fraction = 0.5\n[cuts]\nmargin_mm = 2\n')
    rules = read_rules(path)
    assert rules.contact_mm == 4.5 and rules.segments["distal"].inferior_fraction == 0.5
    assert rules.cuts.margin_mm == 2.0 and rules.segments["lefort"].attach == "anterior"
    path.write_text('contact_mn = 4.5\n')
    with pytest.raises(RulesError, match="rules.toml: unknown key 'contact_mn'"):
        read_rules(path)
    path.write_text('[segments.skull]\nattach = "inferior"\n')
    with pytest.raises(RulesError, match="only lefort and distal carry tissue"):
        read_rules(path)
    path.write_text('lip_muscle_lateral = 2\n')
    with pytest.raises(RulesError, match="lip_muscle_lateral = 2.0; expected a fraction"):
        read_rules(path)
    path.write_text('contact_mm = "far"\n')
    with pytest.raises(RulesError, match="contact_mm"):
        read_rules(path)


def test_self_intersecting_tissue_is_meshed_by_the_default_backend(inputs):
    """fTetWild meshes through a self-intersection: the vertices around the thinnest place of
    the tissue pushed 2 mm through the opposite side."""
    from scipy.spatial import cKDTree

    from toolkit.common.analysis.surface_distance import closest_points, vertex_normals
    from toolkit.common.meshes.mesh import Mesh

    surface, bones, _ = inputs
    p = surface.points.copy()
    n = vertex_normals(p, surface.cells["tri3"])
    dist, near = cKDTree(p).query(p, k=64)
    thick = np.where(np.einsum("ij,ikj->ik", n, n[near]) < -0.5, dist, np.inf).min(axis=1)
    v = int(np.argmin(thick))
    patch = np.linalg.norm(p - p[v], axis=1) < 6.0
    p[patch] -= (thick[v] + 2.0) * n[v]
    # the pushed vertices now lie outside the tissue, beyond its other side
    assert closest_points(p[patch], surface.points, surface.cells["tri3"]).distance.max() > 1.0
    broken = Mesh(p, {"tri3": surface.cells["tri3"]})
    face = mesh_face(broken, bones, size_mm=12.0, order=1)
    assert face.mesh.scaled_jacobian().min() > 0 and face.report["nodes"] > 100


def test_meshing_leaves_nothing_in_the_working_directory(inputs, tmp_path, monkeypatch):
    """fTetWild writes __tracked_surface.stl into the current directory: it runs in a scratch one."""
    from toolkit.mesh.backends import tetrahedralize

    monkeypatch.chdir(tmp_path)
    surface = inputs[0]
    tetrahedralize(surface.points, surface.cells["tri3"], 12.0, backend=BACKEND)
    assert list(tmp_path.iterdir()) == [] and Path.cwd() == tmp_path


def test_round_trip_benchmark_carries_sets_to_mid_edge_nodes_as_the_mesher_does(face, phantom):
    """``benchmarks/own_face.py --labels phantom`` extends the carried corner sets to the tet10
    mid-edge nodes with the mesher's rule: applied to the mesher's own corner sets, it gives them back."""
    import importlib.util
    import sys

    benchmarks = Path(__file__).resolve().parents[2] / "benchmarks"
    if str(benchmarks) not in sys.path:
        sys.path.insert(0, str(benchmarks))
    spec = importlib.util.spec_from_file_location("benchmarks_own_face", benchmarks / "own_face.py")
    own_face = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(own_face)
    m = face.mesh
    corners = np.unique(m.volume_cells[:, :4])
    for name in ("fixed", "maxilla", "mandible", "mucosa_lefort", "mucosa_distal", "bone"):
        ids = m.node_sets[name]
        got = own_face._with_mid_edge_nodes(m, np.intersect1d(ids, corners))
        assert np.setdiff1d(ids, corners).size > 0, name
        np.testing.assert_array_equal(got, ids, err_msg=name)
    carried = own_face.phantom_labels(m, phantom.mesh)
    for name in ("maxilla", "mandible", "mucosa_distal"):
        assert np.setdiff1d(carried.node_sets[name], corners).size > 0, name
