"""A real head CT (``tests/data/headsq``, VTK's sample data) through ``toolkit ct``: the volume
read, its axes found from the anatomy whatever the storage order, the surfaces closed and where
anatomy puts them, the command's files and its refusals, and the labelled mesh."""

import json
from pathlib import Path

import numpy as np
import pytest

from toolkit.cli import main
from toolkit.mesh.ct import SEGMENT_NAMES, CTRules, ct_surfaces
from toolkit.mesh.volume import Volume, VolumeError, read_volume

HEADSQ = Path(__file__).resolve().parents[1] / "data" / "headsq" / "quarter.nhdr"


@pytest.fixture(scope="module")
def volume():
    return read_volume(HEADSQ)


@pytest.fixture(scope="module")
def surfaces(volume):
    return ct_surfaces(volume)


def _euler(mesh) -> int:
    tris = mesh.cells["tri3"]
    edges = np.unique(np.sort(tris[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    return mesh.n_points - len(edges) + len(tris)


def _edge_uses(tris) -> np.ndarray:
    e = np.sort(tris[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(e, axis=0, return_counts=True)[1]


def test_the_detached_header_reads_the_slices_as_one_volume(volume):
    assert volume.shape == (64, 64, 93) and volume.values.dtype == np.int16
    assert volume.spacing.tolist() == [3.2, 3.2, 1.5] and volume.handedness == "left"
    first = np.fromfile(HEADSQ.parent / "quarter.1", dtype="<i2").reshape(64, 64)
    assert np.array_equal(volume.values[:, :, 0], first.T)  # index 0 varies fastest in the file


@pytest.mark.parametrize("encoding", ["raw", "gzip"])
def test_an_attached_header_round_trips(volume, tmp_path, encoding):
    import gzip

    data = np.ascontiguousarray(volume.values.transpose(2, 1, 0)).astype(">i2").tobytes()
    header = (f"NRRD0004\ntype: short\ndimension: 3\nsizes: 64 64 93\nendian: big\nencoding: {encoding}\n"
              "space directions: (3.2,0,0) (0,3.2,0) (0,0,1.5)\nspace: left-posterior-superior\n\n")
    path = tmp_path / "head.nrrd"
    path.write_bytes(header.encode() + (gzip.compress(data) if encoding == "gzip" else data))
    again = read_volume(path)
    assert np.array_equal(again.values, volume.values) and again.spacing == pytest.approx(volume.spacing)
    assert again.handedness == "right"


@pytest.mark.parametrize("flip, swap, space, expected", [
    ((), False, "3D-left-handed", "LPI"),
    ((1,), False, "3D-right-handed", "LAI"),
    ((1, 2), False, "3D-left-handed", "LAS"),
    ((), True, "3D-right-handed", "PLI"),
])
def test_the_axes_are_found_from_the_anatomy_in_any_storage_order(volume, flip, swap, space, expected):
    """The same head stored mirrored or with its in-plane axes exchanged (the header's handedness
    following, as a scanner's would): the anatomy gives the axes, and the surfaces are the same."""
    from toolkit.mesh import ct_anatomy

    values = volume.values
    for a in flip:
        values = np.flip(values, axis=a)
    if swap:
        values = values.transpose(1, 0, 2)
    stored = Volume(values, volume.spacing, space=space)
    axis, sign, evidence = ct_anatomy.orientation(stored.values, stored.spacing, stored.handedness, CTRules())
    assert evidence["axes"] == expected


def test_a_stored_mirror_gives_the_same_surfaces(volume, surfaces):
    mirrored = ct_surfaces(Volume(np.flip(volume.values, axis=1), volume.spacing, space="3D-right-handed"))
    assert mirrored.report["axes"]["axes"] == "LAI"
    for name, bone in surfaces.bones.items():
        assert mirrored.bones[name].points.mean(axis=0) == pytest.approx(bone.points.mean(axis=0), abs=0.5), name
    assert mirrored.tissue.bounds == pytest.approx(surfaces.tissue.bounds, abs=0.5)


def test_the_tissue_is_one_closed_outward_surface(surfaces):
    tissue = surfaces.tissue
    assert (_edge_uses(tissue.cells["tri3"]) == 2).all()  # closed and manifold
    assert _euler(tissue) == 2  # one piece without handles: the mouth closed
    x = tissue.points[tissue.cells["tri3"]]
    volume_mm3 = np.einsum("ij,ij->i", x[:, 0], np.cross(x[:, 1], x[:, 2])).sum() / 6.0
    assert 100e3 < volume_mm3 < 500e3  # a lower face's soft tissue: a few hundred cm^3, outward normals
    assert surfaces.commissures is None and "closed" in surfaces.report["mouth"]["status"]


def test_the_bones_lie_behind_the_skin_against_the_tissue(surfaces):
    """Every segment is there, none inside the tissue, the jaws' outer surfaces against its inner
    surface, and the skin in front of every bone."""
    import pyvista as pv

    t = surfaces.tissue.cells["tri3"]
    tissue = pv.PolyData(surfaces.tissue.points, np.hstack([np.full((len(t), 1), 3), t]))
    for name in SEGMENT_NAMES:
        bone = surfaces.bones[name]
        assert len(bone.cells["tri3"]) > 500, name
        d = pv.PolyData(bone.points).compute_implicit_distance(tissue)["implicit_distance"]
        assert d.min() > -1.0, name  # no bone inside the soft tissue
        if name in ("lefort", "distal"):
            assert np.mean(np.abs(d) < 1.0) > 0.25, name  # the tissue lies on the jaws
        assert bone.points[:, 1].max() < surfaces.tissue.points[:, 1].max(), name


def test_the_landmarks_are_where_anatomy_puts_them(surfaces):
    m = {k: np.array(v) for k, v in surfaces.report["landmarks_mm"].items()}
    nose, chin, menton = m["nose_tip"], m["chin"], m["menton"]
    assert nose[2] > 15.0 and chin[2] < -15.0 and nose[2] - chin[2] > 40.0  # chin well below the nose
    assert nose[1] > 0.0 and chin[1] > menton[1] + 5.0  # the nose in front of the teeth, soft chin over the bone
    assert abs(nose[0]) < 8.0 and abs(chin[0]) < 8.0  # on the midline
    left, right = m["condyle_left"], m["condyle_right"]
    assert left[0] > 35.0 and right[0] < -35.0 and abs(left[0] + right[0]) < 6.0  # symmetric, left at x > 0
    assert left[1] < -50.0 and left[2] > 20.0  # behind the teeth, above the occlusal plane
    centre = {k: b.points.mean(axis=0) for k, b in surfaces.bones.items()}
    assert centre["lefort"][2] > 0 > centre["distal"][2]  # the occlusal plane between the jaws
    assert centre["distal"][1] > max(centre["proximal_left"][1], centre["proximal_right"][1])
    pitch = surfaces.report["occlusal_plane"]["pitch_deg"]
    assert 10.0 < pitch < 40.0  # headsq's head lies flexed: the occlusal plane steep in the volume


def test_the_command_writes_the_surfaces_and_the_next_command(tmp_path, capsys):
    out = tmp_path / "surfaces"
    assert main(["ct", "--volume", str(HEADSQ), "--out", str(out)]) == 0
    for name in ("tissue", *SEGMENT_NAMES):
        assert (out / f"{name}.stl").stat().st_size > 10_000, name
    report = json.loads((out / "ct.json").read_text())
    assert report["axes"]["axes"] == "LPI" and report["surfaces"]["tissue"]["triangles"] > 1000
    text = capsys.readouterr().out
    assert "landmarks" in text and "osteotomy" in text
    assert f"next: toolkit mesh --tissue {out / 'tissue.stl'} --bone lefort={out / 'lefort.stl'}" in text


@pytest.mark.parametrize("make, extra, match", [
    (lambda d: d / "missing.nhdr", [], "missing.nhdr"),
    (lambda d: (d / "notes.nhdr").write_text("hello\n") and d / "notes.nhdr", [], "NRRD"),
    (lambda d: HEADSQ, ["--skin", "5000"], "skin threshold 5000"),
    (lambda d: HEADSQ, ["--bone", "20000"], "bone threshold 20000"),
    (lambda d: HEADSQ, ["--axes", "LPX"], "three letters"),
])
def test_bad_input_is_refused_before_segmenting(tmp_path, capsys, monkeypatch, make, extra, match):
    import toolkit.mesh.ct as ct

    def segmented(*args, **kwargs):
        raise AssertionError("segmentation ran")

    monkeypatch.setattr(ct, "ct_surfaces", segmented)
    assert main(["ct", "--volume", str(make(tmp_path)), "--out", str(tmp_path / "out"), *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and match in err, err
    assert not (tmp_path / "out").exists()


def test_an_unwritable_out_is_refused_first(tmp_path, capsys):
    existing = tmp_path / "file.txt"
    existing.write_text("x")
    for out in ("/proc/x", str(existing)):
        assert main(["ct", "--volume", str(tmp_path / "missing.nhdr"), "--out", out]) == 2
        assert repr(out) in capsys.readouterr().err


def test_no_teeth_or_a_spacing_in_metres_is_refused_with_the_remedy(volume):
    from toolkit.mesh.ct import CTError

    with pytest.raises(CTError, match="teeth threshold"):
        ct_surfaces(volume, CTRules(teeth=5000.0))
    with pytest.raises(VolumeError, match="voxel spacing .*in m or cm"):
        ct_surfaces(Volume(volume.values, volume.spacing / 1000.0))


@pytest.mark.long
def test_the_ct_face_meshes_and_both_moving_segments_carry_tissue(surfaces):
    """End to end: the CT's surfaces meshed by ``mesh_face`` at 8 mm (tet4) label non-empty
    ``maxilla`` and ``mandible`` sets, each carrying more than the 40 mm^2 the mesher asks."""
    from toolkit.mesh import mesh_face

    face = mesh_face(surfaces.tissue, surfaces.bones, surfaces.commissures, size_mm=8.0, order=1)
    sets = face.mesh.node_sets
    assert len(sets["maxilla"]) > 0 and len(sets["mandible"]) > 0
    segments = face.report["segments"]
    assert segments["lefort"]["attached_area_mm2"] > 40 and segments["distal"]["attached_area_mm2"] > 40
    assert face.report["quality"]["min_scaled_jacobian"] > 0
