"""Mesh files and conversions: round trips that keep every set and field."""

import meshio
import numpy as np
import pytest

from toolkit.common.meshes import convert, io
from toolkit.common.meshes.convert import skfem_node_map
from toolkit.common.phantoms.mixed_bar import mixed_bar
from toolkit.common.phantoms.phantom import ball, face_hex, face_tet


def _mixed():
    """hex8 + wedge6 + tet4 blocks, distorted, with fields and an element set spanning blocks."""
    m = mixed_bar(1, jitter=0.3, seed=0)
    rng = np.random.default_rng(0)
    return m.with_point_data(displacement=rng.normal(size=(m.n_points, 3))).with_cell_data(
        stress=rng.normal(size=(m.n_cells,)), fibre_direction=rng.normal(size=(m.n_cells, 3)))


@pytest.fixture(scope="module")
def meshes():
    return {
        "hex8": face_hex("coarse").mesh,
        "tet4": face_tet("coarse", 1),
        "tet10": face_tet("coarse", 2),
        "ball": ball(resolution="coarse", order=2),
        "mixed": _mixed(),
    }


@pytest.mark.parametrize("kind", ["hex8", "tet4", "tet10", "ball", "mixed"])
@pytest.mark.parametrize("suffix", [".vtu", ".xdmf", ".inp"])
def test_file_round_trip_keeps_sets(tmp_path, meshes, kind, suffix):
    """VTU/XDMF keep everything; Abaqus keeps geometry and all node/element sets. The
    mixed mesh (hex8, wedge6, tet4 blocks) keeps its blocks, node orders (VTU permutes
    wedges to VTK's order and back) and the element set that spans the three blocks."""
    mesh = meshes[kind]
    path = io.write(tmp_path / f"m{suffix}", mesh)
    back = io.read(path)
    expected = mesh.without_fields() if suffix == ".inp" else mesh
    assert back.equals(expected)


def test_abaqus_file_from_elsewhere_reads_like_a_phantom(tmp_path):
    """A hand-written Abaqus deck (1-based ids, GENERATE ranges, upper-case names) reads
    into the same container, sets included."""
    text = """*HEADING
two tets
*NODE
1, 0., 0., 0.
2, 10., 0., 0.
3, 0., 10., 0.
4, 0., 0., 10.
5, 10., 10., 10.
*ELEMENT, TYPE=C3D4, ELSET=SOFT
1, 1, 2, 3, 4
2, 2, 3, 4, 5
*NSET, NSET=FIXED, GENERATE
1, 3, 1
*NSET, NSET=skin
4, 5
*ELSET, ELSET=lip_muscle
2
"""
    path = tmp_path / "real.inp"
    path.write_text(text)
    m = io.read(path, require_node_sets=["FIXED", "skin"], require_element_sets=["lip_muscle"])
    assert m.volume_type == "tet4" and m.n_points == 5
    assert m.node_sets["FIXED"].tolist() == [0, 1, 2]
    assert m.node_sets["skin"].tolist() == [3, 4]
    assert m.element_sets["lip_muscle"].tolist() == [1]
    assert m.element_sets["SOFT"].tolist() == [0, 1]
    m.check()
    with pytest.raises(KeyError, match=r"lacks the sets \['mucosa_sliding'\].*node sets \['FIXED', 'skin'\]"):
        io.read(path, require_node_sets=["mucosa_sliding"])


def test_units_that_look_like_metres_are_refused(tmp_path, meshes):
    mesh = meshes["hex8"]
    metres = mesh.with_points(mesh.points / 1000.0)
    path = io.write(tmp_path / "metres.vtu", metres)
    with pytest.raises(io.UnitsError, match=r"0\.1\d* units across: that looks like metres"):
        io.read(path)
    back = io.read(path, units="m")
    assert np.allclose(back.points, mesh.points)
    huge = io.write(tmp_path / "um.vtu", mesh.with_points(mesh.points * 1000.0))
    with pytest.raises(io.UnitsError, match="micrometres"):
        io.read(huge)


def test_unknown_format_and_missing_file(tmp_path, meshes):
    with pytest.raises(ValueError,
                       match=r"unknown mesh format '\.stl'.*expected one of \['\.inp', '\.vtu', '\.xdmf'\]"):
        io.write(tmp_path / "m.stl", meshes["hex8"])
    with pytest.raises(FileNotFoundError, match="nope.vtu"):
        io.read(tmp_path / "nope.vtu")
    ok = io.write(tmp_path / "ok.vtu", meshes["hex8"])
    with pytest.raises(ValueError, match="unknown units 'inch'"):
        io.read(ok, units="inch")


def test_write_is_atomic(tmp_path, meshes, monkeypatch):
    """A write that fails midway leaves the previous file intact and no temporary behind."""
    path = io.write(tmp_path / "m.vtu", meshes["tet4"])
    before = path.read_bytes()

    def boom(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(meshio, "write", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        io.write(path, meshes["hex8"])
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.vtu"]


def test_time_series_round_trip_and_meshio_interop(tmp_path, meshes):
    mesh = meshes["tet10"]
    rng = np.random.default_rng(0)
    times = np.array([0.0, 0.1, 0.25])
    u = rng.normal(size=(3, mesh.n_points, 3))
    vm = rng.random((3, mesh.n_points))
    path = io.write_time_series(tmp_path / "series.xdmf", mesh, times, {"displacement": u, "von_mises": vm})
    ts = io.read_time_series(path)
    assert ts.mesh.equals(mesh)
    assert np.array_equal(ts.times, times)
    assert np.array_equal(ts.point_data["displacement"], u) and np.array_equal(ts.point_data["von_mises"], vm)
    with meshio.xdmf.TimeSeriesReader(path) as reader:  # standard XDMF, as ParaView reads it
        points, cells = reader.read_points_cells()
        t, pdata, _ = reader.read_data(2)
    assert cells[0].type == "tetra10" and np.allclose(points, mesh.points)
    assert t == pytest.approx(0.25) and np.allclose(pdata["displacement"], u[2])


def test_time_series_of_a_mixed_mesh_reads_back_with_meshio_and_toolkit(tmp_path):
    """A hex8 + wedge6 + tet4 mesh is one XDMF Mixed topology: meshio reads the same points,
    cells (block by block) and point data as read_time_series; the node and element sets come
    back too."""
    from toolkit.common.phantoms.mixed_bar import mixed_bar

    mesh = mixed_bar()
    assert list(mesh.cells) == ["hex8", "wedge6", "tet4"]
    rng = np.random.default_rng(1)
    times = np.array([0.0, 1.0, 2.0])
    u = rng.normal(size=(3, mesh.n_points, 3))
    path = io.write_time_series(tmp_path / "mixed.xdmf", mesh, times, {"displacement": u})
    ts = io.read_time_series(path)
    assert ts.mesh.equals(mesh) and np.array_equal(ts.times, times)
    assert np.array_equal(ts.point_data["displacement"], u)
    assert ts.mesh.node_sets.keys() == mesh.node_sets.keys() and ts.mesh.element_sets.keys() == mesh.element_sets.keys()
    with meshio.xdmf.TimeSeriesReader(path) as reader:
        points, cells = reader.read_points_cells()
        frames = [reader.read_data(k) for k in range(3)]
    assert np.array_equal(points, mesh.points)
    assert [c.type for c in cells] == ["hexahedron", "wedge", "tetra"]
    for block, (ctype, conn) in zip(cells, mesh.cells.items(), strict=True):
        assert np.array_equal(block.data, conn), ctype
    for k, (t, pdata, _) in enumerate(frames):
        assert t == pytest.approx(times[k]) and np.array_equal(pdata["displacement"], u[k])


def test_time_series_resumes_after_interruption(tmp_path, meshes):
    """Frames written before an interruption stay readable; resume appends after them."""
    mesh = meshes["tet4"]
    path = tmp_path / "run.xdmf"
    w = io.TimeSeriesWriter(path, mesh)
    for k in range(3):
        w.append(0.1 * k, displacement=np.full((mesh.n_points, 3), k, float))
    w.h5.flush()  # simulate a crash: no close()
    assert io.read_time_series(path).times.size == 3
    w.close()
    with io.TimeSeriesWriter(path, mesh, resume=True) as w2:
        assert len(w2) == 3
        w2.append(0.3, displacement=np.full((mesh.n_points, 3), 3, float))
        with pytest.raises(ValueError, match="frame times must increase"):
            w2.append(0.3, displacement=np.zeros((mesh.n_points, 3)))
        with pytest.raises(ValueError, match="NaN"):
            w2.append(0.5, displacement=np.full((mesh.n_points, 3), np.nan))
    ts = io.read_time_series(path)
    assert np.allclose(ts.times, [0, 0.1, 0.2, 0.3])
    assert np.allclose(ts.point_data["displacement"][:, 0, 0], [0, 1, 2, 3])


@pytest.mark.parametrize("kind", ["hex8", "tet4", "tet10", "ball", "mixed"])
def test_pyvista_round_trip(meshes, kind):
    pytest.importorskip("pyvista")
    mesh = meshes[kind]
    assert convert.from_pyvista(convert.to_pyvista(mesh)).equals(mesh)
    assert convert.from_meshio(convert.to_meshio(mesh)).equals(mesh)


def test_abaqus_mixed_deck_from_elsewhere(tmp_path):
    """A hand-written deck with a C3D8 brick, a C3D6 wedge on its side and a C3D4 on the
    wedge's top triangle (1-based ids, an element set listing elements of all three
    blocks): blocks come back in file order with global element numbers, all positive."""
    text = """*NODE
1, 0., 0., 0.
2, 10., 0., 0.
3, 10., 10., 0.
4, 0., 10., 0.
5, 0., 0., 10.
6, 10., 0., 10.
7, 10., 10., 10.
8, 0., 10., 10.
9, 20., 0., 0.
10, 20., 0., 10.
11, 15., 0., 20.
*ELEMENT, TYPE=C3D8
1, 1, 2, 3, 4, 5, 6, 7, 8
*ELEMENT, TYPE=C3D6
2, 2, 9, 3, 6, 10, 7
*ELEMENT, TYPE=C3D4
3, 6, 10, 7, 11
*NSET, NSET=bottom
1, 2, 3, 4, 9
*ELSET, ELSET=all
1, 2, 3
"""
    path = tmp_path / "mixed.inp"
    path.write_text(text)
    m = io.read(path)
    assert list(m.cells) == ["hex8", "wedge6", "tet4"]
    assert m.cells["wedge6"].tolist() == [[1, 8, 2, 5, 9, 6]]
    assert m.element_sets["all"].tolist() == [0, 1, 2]
    assert (m.scaled_jacobian() > 0).all()
    assert m.check() is m


def test_pyvista_wedges_face_outward(meshes):
    """VTK's wedge has the opposite node order: after the permutation the surface VTK
    extracts from the mixed mesh is the mesh's own boundary with outward normals (the
    divergence theorem over VTK's faces gives the volume, +5000 mm^3 for the straight
    bar). VTK 9.7's own cell volume and quality filters still report such wedges as
    negative, i.e. they assume the other order; its faces, which rendering uses, agree
    with the documented order used here."""
    pytest.importorskip("pyvista")
    grid = convert.to_pyvista(mixed_bar(1))
    assert set(np.unique(grid.celltypes)) == {10, 12, 13}
    surf = grid.extract_surface(algorithm="dataset_surface").triangulate()
    tris = surf.faces.reshape(-1, 4)[:, 1:]
    x = np.asarray(surf.points)[tris]
    area = 0.5 * np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    assert np.einsum("fi,fi->", x.mean(axis=1), area) / 3 == pytest.approx(5000.0, rel=1e-12)


def test_pyvista_interleaved_types_are_grouped():
    """A VTK grid whose hexahedra and wedges alternate (as meshers write them) becomes one
    block per type, in order of first appearance and VTK order within a type; cell data
    and element sets follow the cells."""
    pv = pytest.importorskip("pyvista")
    m = mixed_bar(1)
    grid = convert.to_pyvista(m)
    vtk_perm = np.array([0, 16, 1, 17, 2, 18] + list(range(3, 16)) + list(range(19, 96)))
    cells = [grid.get_cell(int(i)) for i in vtk_perm]
    conn = np.concatenate([[c.n_points, *c.point_ids] for c in cells])
    mixed = pv.UnstructuredGrid(conn, np.asarray(grid.celltypes)[vtk_perm], grid.points)
    mixed.cell_data["id"] = vtk_perm
    mixed.cell_data["elset:upper"] = np.isin(vtk_perm, m.element_set("upper")).astype(np.uint8)
    back = convert.from_pyvista(mixed)
    assert list(back.cells) == ["hex8", "wedge6", "tet4"]
    assert np.array_equal(back.cell_data["id"], np.arange(96))
    assert all(np.array_equal(back.cells[t], m.cells[t]) for t in m.cells)
    assert np.array_equal(back.element_set("upper"), m.element_set("upper"))


@pytest.mark.parametrize("kind", ["hex8", "tet4", "tet10"])
def test_skfem_round_trip_and_volume(meshes, kind):
    """scikit-fem sees the same nodes (identity map for phantoms), the same element sets,
    and integrates the same volume as the straight-sided tetrahedra/hexahedra."""
    import skfem

    mesh = meshes[kind]
    sk = convert.to_skfem(mesh)
    node_map = skfem_node_map(mesh, sk)
    assert np.array_equal(node_map, np.arange(mesh.n_points))
    assert np.allclose(sk.doflocs.T, mesh.points)
    back = convert.from_skfem(sk, node_sets=dict(mesh.node_sets), cell_data=dict(mesh.cell_data))
    assert back.equals(mesh)
    elem = {"hex8": skfem.ElementHex1(), "tet4": skfem.ElementTetP1(), "tet10": skfem.ElementTetP2()}[kind]
    basis = skfem.Basis(sk, elem)
    volume = skfem.Functional(lambda w: 1.0 + 0 * w.x[0]).assemble(basis)
    assert volume == pytest.approx(_reference_volume(mesh), rel=1e-10)
    assert set(sk.subdomains) == set(mesh.element_sets)


def _reference_volume(mesh):
    """Exact volume: straight tetrahedra by the triple product; trilinear hexahedra by
    2x2x2 Gauss quadrature of det J (exact: det J is quadratic in each coordinate)."""
    x = mesh.points[mesh.volume_cells]
    if mesh.volume_type != "hex8":
        x = x[:, :4]
        return np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0]).sum() / 6
    ref = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    g = 0.5 + np.array([-1, 1]) / (2 * np.sqrt(3))
    total = 0.0
    for a in g:
        for b in g:
            for c in g:
                q = np.array([a, b, c])
                # dN/dxi for N = prod(r q + (1 - r)(1 - q)) over the three directions
                f = ref * q + (1 - ref) * (1 - q)  # (8, 3)
                s = 2 * ref - 1
                dN = np.stack([s[:, k] * np.prod(np.delete(f, k, axis=1), axis=1) for k in range(3)], axis=1)
                J = np.einsum("eai,ak->eik", x, dN)
                total += np.linalg.det(J).sum() / 8.0
    return total
