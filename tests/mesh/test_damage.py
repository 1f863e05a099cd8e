"""Labels that hold on damaged segmentations (paper phantom's surfaces, its fine tet4 mesh): the
bone surfaces' winding decides nothing, and flipped patches, an osteotomy kerf, holes, pieces,
another resolution and bones standing 0-5 mm off the tissue, one at a time and all together, keep
every node set within 10 % of the clean surfaces' on the same mesh.
``benchmarks/segmentation_damage.py`` remeshes each damaged face and runs the default plan."""

import numpy as np
import pytest

from toolkit.common.meshes.mesh import Mesh
from toolkit.common.phantoms.phantom import face_hex, face_tet
from toolkit.mesh.damage import DAMAGE, damaged, flipped_in_patches, remeshed
from toolkit.mesh.labels import label_nodes
from toolkit.mesh.phantom import phantom_surfaces
from toolkit.mesh.rules import read_rules

#: sets smaller than this are compared to within two nodes (10 % of a handful is less than one)
SMALL = 20


@pytest.fixture(scope="module")
def surfaces():
    return phantom_surfaces(face_hex("paper"))


@pytest.fixture(scope="module")
def face():
    """The phantom's tissue as linear tetrahedra (12,348 nodes): a mesh made the same way every run
    (fTetWild's is not), so that a label that moves is the damage's doing."""
    return face_tet("fine", order=1)


def _labels(mesh, bones):
    return label_nodes(mesh.points, mesh.volume_cells, bones, read_rules()).node_sets


@pytest.fixture(scope="module")
def damaged_bones(surfaces):
    """kind -> the damaged bones (a kerf refines the bones first: made once)."""
    return {k: damaged(surfaces.tissue, surfaces.bones, k, np.random.default_rng(0))[1] for k in DAMAGE}


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


@pytest.mark.long
@pytest.mark.parametrize("kind", DAMAGE)
def test_damaged_bones_keep_every_set_within_ten_percent(face, clean, damaged_bones, kind):
    got = _labels(face, damaged_bones[kind])
    for name, ids in clean.items():
        n, m = ids.size, got[name].size
        if n >= SMALL:
            assert abs(m - n) <= 0.1 * n, f"{kind}: {name} has {m} nodes, clean {n}"
        else:
            assert abs(m - n) <= 2, f"{kind}: {name} has {m} nodes, clean {n}"


def test_the_damage_is_what_it_says(surfaces):
    rng = np.random.default_rng(1)
    bone = surfaces.bones["distal"]
    flipped = flipped_in_patches(bone, 0.3, rng)
    share = np.mean(np.any(flipped.cells["tri3"] != bone.cells["tri3"], axis=1))
    assert 0.3 <= share <= 0.5
    finer = remeshed(bone, 4.0)
    assert finer.cells["tri3"].shape[0] == 4 * bone.cells["tri3"].shape[0]


@pytest.mark.long
def test_a_kerf_leaves_a_gap_between_the_bones(damaged_bones):
    """The 1 mm osteotomy kerf leaves the Le Fort I and the distal bone at least 0.5 mm apart."""
    cut = damaged_bones["kerf"]
    from toolkit.common.analysis.surface_distance import closest_points

    gap = closest_points(cut["lefort"].points, cut["distal"].points, cut["distal"].cells["tri3"]).distance.min()
    assert gap >= 0.5 - 1e-9
