"""Labels that hold on damaged segmentations (paper phantom's surfaces, one 7 mm tet4 mesh): the
bone surfaces' winding decides nothing, and flipped patches, an osteotomy kerf, holes, pieces and
another resolution keep every node set within 10 % of the clean surfaces' on the same mesh.
``benchmarks/segmentation_damage.py`` remeshes each damaged face and runs the default plan."""

import numpy as np
import pytest

from toolkit.common.mesh import Mesh
from toolkit.common.phantom import face_hex
from toolkit.mesh.damage import DAMAGE, damaged, flipped_in_patches, remeshed
from toolkit.mesh.face import mesh_face
from toolkit.mesh.labels import label_nodes
from toolkit.mesh.phantom import phantom_surfaces
from toolkit.mesh.rules import read_rules

#: sets smaller than this are compared to within two nodes (10 % of a handful is less than one)
SMALL = 20


@pytest.fixture(scope="module")
def surfaces():
    return phantom_surfaces(face_hex("paper"))


@pytest.fixture(scope="module")
def face(surfaces):
    return mesh_face(surfaces.tissue, surfaces.bones, None, size_mm=7.0, order=1)


def _labels(face, bones):
    m = face.mesh
    return label_nodes(m.points, m.volume_cells, bones, read_rules()).node_sets


@pytest.fixture(scope="module")
def damaged_bones(surfaces):
    """kind -> the damaged bones (a kerf refines the bones first: made once)."""
    kinds = [k for k in DAMAGE if k not in ("off_bone", "all")]
    return {k: damaged(surfaces.tissue, surfaces.bones, k, np.random.default_rng(0))[1] for k in kinds}


@pytest.fixture(scope="module")
def clean(face, surfaces):
    return _labels(face, surfaces.bones)


def test_the_winding_of_the_bones_decides_nothing(face, surfaces, clean):
    """Every bone reversed, and every other triangle of every bone reversed: the same sets exactly."""
    reversed_all = {k: Mesh(b.points, {"tri3": b.cells["tri3"][:, ::-1]}) for k, b in surfaces.bones.items()}
    mixed = {}
    for k, b in surfaces.bones.items():
        t = b.cells["tri3"].copy()
        t[::2] = t[::2, ::-1]
        mixed[k] = Mesh(b.points, {"tri3": t})
    for bones in (reversed_all, mixed):
        got = _labels(face, bones)
        assert got.keys() == clean.keys()
        for name in clean:
            np.testing.assert_array_equal(got[name], clean[name], err_msg=name)


@pytest.mark.parametrize("kind", [k for k in DAMAGE if k not in ("off_bone", "all")])
def test_damaged_bones_keep_every_set_within_ten_percent(face, clean, damaged_bones, kind):
    got = _labels(face, damaged_bones[kind])
    for name, ids in clean.items():
        n, m = ids.size, got[name].size
        if n >= SMALL:
            assert abs(m - n) <= 0.1 * n, f"{kind}: {name} has {m} nodes, clean {n}"
        else:
            assert abs(m - n) <= 2, f"{kind}: {name} has {m} nodes, clean {n}"


def test_the_damage_is_what_it_says(surfaces, damaged_bones):
    rng = np.random.default_rng(1)
    bone = surfaces.bones["distal"]
    flipped = flipped_in_patches(bone, 0.3, rng)
    share = np.mean(np.any(flipped.cells["tri3"] != bone.cells["tri3"], axis=1))
    assert 0.3 <= share <= 0.5
    finer = remeshed(bone, 4.0)
    assert finer.cells["tri3"].shape[0] == 4 * bone.cells["tri3"].shape[0]
    cut = damaged_bones["kerf"]  # a 1 mm kerf
    from toolkit.common.surface_distance import closest_points

    gap = closest_points(cut["lefort"].points, cut["distal"].points, cut["distal"].cells["tri3"]).distance.min()
    assert gap >= 0.5 - 1e-9


def test_a_tissue_off_the_bone_is_still_labelled(surfaces):
    """The tissue's bone side 0-5 mm off the bone (coarse 10 mm mesh): both moving segments carry
    tissue, and the tissue lying on each bone is within 20 % of the clean face's (the mesher's own
    run-to-run spread at this size is about 10 %)."""
    tissue, bones = damaged(surfaces.tissue, surfaces.bones, "off_bone", np.random.default_rng(0))
    off = mesh_face(tissue, bones, None, size_mm=10.0, order=1).report["segments"]
    ref = mesh_face(surfaces.tissue, surfaces.bones, None, size_mm=10.0, order=1).report["segments"]
    for name in ("lefort", "distal"):
        assert off[name]["attached_area_mm2"] >= read_rules().min_carried_mm2
        assert off[name]["facing_area_mm2"] == pytest.approx(ref[name]["facing_area_mm2"], rel=0.2)
