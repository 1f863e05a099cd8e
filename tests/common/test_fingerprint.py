"""The mesh fingerprints: what changes them and what does not."""

import numpy as np

from toolkit.common.meshes.fingerprint import (
    array_fingerprint,
    file_fingerprint,
    mesh_fingerprint,
    points_fingerprint,
    topology_fingerprint,
)

RNG = np.random.default_rng(0)
POINTS = RNG.normal(scale=40.0, size=(200, 3))
CELLS = {"tet4": RNG.integers(0, 200, size=(300, 4))}


def test_points_fingerprint_ignores_the_last_bits_but_not_a_move():
    assert points_fingerprint(POINTS) == points_fingerprint(POINTS * (1 + 1e-15))  # arithmetic noise
    assert points_fingerprint(POINTS) != points_fingerprint(POINTS + [0.001, 0, 0])
    assert points_fingerprint(np.zeros((2, 3))) == points_fingerprint(-np.zeros((2, 3)))


def test_mesh_fingerprint_is_the_topology_not_the_coordinates():
    assert mesh_fingerprint(POINTS, CELLS) == mesh_fingerprint(POINTS * 1.1, CELLS)
    swapped = {"tet4": CELLS["tet4"][:, [1, 0, 2, 3]]}
    assert mesh_fingerprint(POINTS, CELLS) != mesh_fingerprint(POINTS, swapped)
    assert mesh_fingerprint(POINTS, CELLS)["nodes"] == 200
    assert topology_fingerprint(CELLS) != topology_fingerprint({"tet10": CELLS["tet4"]})


def test_array_fingerprint_reads_integers_as_integers():
    types = np.array([0, 1, 3], dtype=np.int8)
    assert array_fingerprint(types) == array_fingerprint(types.astype(np.int64))
    assert array_fingerprint(types) != array_fingerprint(np.array([0, 1, 2]))


def test_file_fingerprint_follows_the_bytes(tmp_path):
    f = tmp_path / "a.stl"
    f.write_bytes(b"solid a\nendsolid a\n")
    before = file_fingerprint(f)
    assert len(before) == 40
    f.write_bytes(b"solid b\nendsolid b\n")
    assert file_fingerprint(f) != before
