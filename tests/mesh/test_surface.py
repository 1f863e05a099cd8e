"""Tissue-surface repair: each defect a segmentation export holds is repaired or refused by name."""

import numpy as np
import pytest

from toolkit.common import face_hex, write
from toolkit.common.meshes.mesh import Mesh
from toolkit.mesh.surface import SurfaceError, closed_surface, read_tissue_surface, tissue_surface_of


@pytest.fixture(scope="module")
def surface() -> Mesh:
    return tissue_surface_of(face_hex("coarse").mesh)


def _volume(s: Mesh) -> float:
    x = s.points[s.cells["tri3"]]
    return float(np.einsum("ij,ij->i", x[:, 0], np.cross(x[:, 1], x[:, 2])).sum() / 6.0)


def _closed(s: Mesh) -> bool:
    t = s.cells["tri3"]
    e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    return bool(np.all(np.unique(e, axis=0, return_counts=True)[1] == 2))


def test_phantom_boundary_is_a_closed_sphere(surface):
    t = surface.cells["tri3"]
    edges = np.unique(np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1), axis=0)
    assert surface.n_points - len(edges) + len(t) == 2  # Euler characteristic of a sphere: mouth closed
    assert _closed(surface) and _volume(surface) > 0


def test_clean_surface_is_unchanged(surface):
    out, rep = closed_surface(surface.points, surface.cells["tri3"])
    assert not rep.changed
    assert np.allclose(out.points, surface.points) and np.array_equal(out.cells["tri3"], surface.cells["tri3"])


def test_stl_soup_duplicates_and_flips_are_repaired(surface):
    rng = np.random.default_rng(0)
    t = surface.cells["tri3"]
    soup = surface.points[t].reshape(-1, 3)  # every corner separate, as STL stores them
    tris = np.arange(soup.shape[0]).reshape(-1, 3)
    flip = rng.random(len(tris)) < 0.05
    tris[flip] = tris[flip][:, [0, 2, 1]]
    tris = np.vstack([tris, tris[:7]])  # duplicated triangles
    out, rep = closed_surface(soup, tris)
    assert rep.merged_vertices == soup.shape[0] - surface.n_points
    assert rep.duplicate_triangles == 7 and rep.flipped_triangles == int(flip.sum())
    assert _closed(out) and _volume(out) == pytest.approx(_volume(surface), rel=1e-12)


def test_small_holes_are_closed_large_ones_refused(surface):
    t = surface.cells["tri3"]
    centre = surface.points[t].mean(axis=1)
    far = np.argsort(np.linalg.norm(centre - centre[0], axis=1))
    holed = np.delete(t, far[:3], axis=0)  # a hole of three triangles
    out, rep = closed_surface(surface.points, holed)
    assert rep.filled_holes == 1 and _closed(out)
    assert _volume(out) == pytest.approx(_volume(surface), rel=0.01)
    big = np.delete(t, far[:60], axis=0)
    with pytest.raises(SurfaceError, match=r"is open: a hole bounded by \d+ edges .* --max-hole-edges"):
        closed_surface(surface.points, big, max_hole_edges=10)


def test_internal_membrane_and_floating_piece_are_dropped(surface):
    t = surface.cells["tri3"]
    n = surface.n_points
    inner = surface.points.mean(axis=0) + np.array([[0, 0, 0], [5.0, 0, 0], [0, 5.0, 0]])
    pts = np.vstack([surface.points, inner])
    membrane = np.vstack([t, [[n, n + 1, n + 2], [n, n + 2, n + 1]]])  # a coincident opposite pair
    out, rep = closed_surface(pts, membrane)
    assert rep.internal_triangles == 2 and out.n_points == n and _closed(out)
    island_pts = np.vstack([surface.points, surface.points[:4] + 500.0])
    island = np.vstack([t, np.array([[n, n + 1, n + 2], [n, n + 3, n + 1], [n + 1, n + 3, n + 2], [n, n + 2, n + 3]])])
    out, rep = closed_surface(island_pts, island)
    assert rep.dropped_pieces == 1 and out.n_points == n


def test_non_manifold_edge_is_refused_with_its_place(surface):
    t = surface.cells["tri3"]
    a, b = t[0, 0], t[0, 1]
    pts = np.vstack([surface.points, surface.points[a] + [0, 0, 5.0]])
    fin = np.vstack([t, [[a, b, surface.n_points]]])
    with pytest.raises(SurfaceError, match=r"shared by more than two triangles .* near \("):
        closed_surface(pts, fin)


def test_surface_in_metres_is_refused_then_read_with_units(tmp_path, surface):
    path = tmp_path / "tissue.stl"
    write_stl = Mesh(surface.points / 1000.0, {"tri3": surface.cells["tri3"]})
    import meshio

    meshio.write(path, meshio.Mesh(write_stl.points, [("triangle", write_stl.cells["tri3"])]))
    from toolkit.common.meshes.io import UnitsError

    with pytest.raises(UnitsError, match="metres.*--units m"):
        read_tissue_surface(path)
    out, rep = read_tissue_surface(path, units="m")
    assert _closed(out) and _volume(out) == pytest.approx(_volume(surface), rel=1e-6)


def test_empty_and_garbage_files_name_the_file(tmp_path):
    empty = tmp_path / "empty.stl"
    empty.write_bytes(b"")
    with pytest.raises(Exception, match="empty.stl"):
        read_tissue_surface(empty)
    junk = tmp_path / "junk.ply"
    junk.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(Exception, match="junk.ply"):
        read_tissue_surface(junk)
    _ = write  # the writer stays importable for VTU round trips


def test_two_holes_touching_at_a_vertex_are_closed(surface):
    """A vertex where two holes meet has two rim edges leaving it (a pinch)."""
    t = surface.cells["tri3"]
    v = int(t[0, 0])
    around = np.flatnonzero((t == v).any(axis=1))
    # two triangles around v that share no edge: v's rim then runs through v twice
    a = around[0]
    b = next(k for k in around[1:] if np.intersect1d(t[a], t[k]).size == 1)
    out, rep = closed_surface(surface.points, np.delete(t, [a, b], axis=0))
    assert _closed(out) and rep.filled_holes >= 1
