"""Bone surfaces from files (STL/OBJ/PLY/...): reading, consistent orientation towards the
soft tissue, and simulations on them equal to those on the phantom's own surfaces."""

import warnings

import meshio
import numpy as np
import pytest

from toolkit.common.meshes.io import write
from toolkit.common.meshes.mesh import Mesh, MeshError
from toolkit.common.meshes.surfaces import orient_surface, read_surface
from toolkit.common.phantoms.phantom import face_hex
from toolkit.static import default_plan, simulate
from toolkit.static.bones import segments_from_files


@pytest.fixture(scope="module")
def phantom():
    return face_hex("coarse")


def _normals(surface: Mesh) -> np.ndarray:
    x = surface.points[surface.cells["tri3"]]
    return np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])


def test_files_give_the_phantom_result(phantom, tmp_path):
    """The phantom's bone surfaces written as STL (half the triangles flipped, as some
    segmentation tools write them) and PLY, read back, oriented and attached to the face
    mesh read from VTU (which keeps the lip muscle's fibre field), give the same surfaces (same
    points, every normal pointing into the soft tissue like the phantom's) and the same simulation: the default plan's
    displacement equals the phantom run's to 1e-9 mm."""
    rng = np.random.default_rng(0)
    files = {}
    for k, (name, seg) in enumerate(phantom.segments.items()):
        tris = seg.surface.cells["tri3"].copy()
        flip = rng.random(len(tris)) < 0.5
        tris[flip] = tris[flip][:, [0, 2, 1]]
        path = tmp_path / f"{name}.{'stl' if k % 2 == 0 else 'ply'}"
        meshio.write(path, meshio.Mesh(seg.surface.points, [("triangle", tris)]))
        files[name] = path
    write(tmp_path / "face.vtu", phantom.mesh)
    from toolkit.common.meshes.io import read

    face = read(tmp_path / "face.vtu")
    segments = segments_from_files(face, files, {n: s.pivot for n, s in phantom.segments.items()})
    for name, seg in segments.items():
        own = phantom.segments[name]
        assert seg.node_set == own.node_set and seg.sliding_set == own.sliding_set
        # same triangles: match by centroid, then compare orientations
        c_own = own.surface.points[own.surface.cells["tri3"]].mean(axis=1)
        c_new = seg.surface.points[seg.surface.cells["tri3"]].mean(axis=1)
        o1, o2 = np.lexsort(c_own.T), np.lexsort(c_new.T)
        np.testing.assert_allclose(c_new[o2], c_own[o1], atol=1e-9)
        assert np.all(np.einsum("ij,ij->i", _normals(seg.surface)[o2], _normals(own.surface)[o1]) > 0), name
    plan = default_plan(phantom)
    ref = simulate(phantom, plan)
    res = simulate(face, plan, segments=segments)
    np.testing.assert_allclose(res.displacement, ref.displacement, rtol=0, atol=1e-9)


def test_reading_polygons_units_and_bad_files(tmp_path):
    """Quads are split into triangles, the duplicated corners of STL merged, a file in cm
    scaled to mm; an unknown format, a missing file, a surface in metres (too small) and a
    non-orientable (Moebius) strip are refused with clear errors."""
    pts = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0], [20, 0, 0], [20, 10, 0]], float)
    meshio.write(tmp_path / "q.obj", meshio.Mesh(pts, [("quad", np.array([[0, 1, 2, 3], [1, 4, 5, 2]]))]))
    s = read_surface(tmp_path / "q.obj")
    assert s.cells["tri3"].shape == (4, 3) and s.n_points == 6
    s_cm = read_surface(tmp_path / "q.obj", units="cm")
    np.testing.assert_allclose(s_cm.extent, 10 * s.extent)
    tris = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])
    meshio.write(tmp_path / "dup.stl", meshio.Mesh(pts, [("triangle", tris)]))
    assert read_surface(tmp_path / "dup.stl").n_points == 6
    with pytest.raises(ValueError, match="unknown surface format '.xyz'"):
        read_surface(tmp_path / "a.xyz")
    with pytest.raises(FileNotFoundError, match="nope.stl"):
        read_surface(tmp_path / "nope.stl")
    meshio.write(tmp_path / "m.stl", meshio.Mesh(pts * 1e-3, [("triangle", tris)]))
    with pytest.raises(MeshError, match="metres"):
        read_surface(tmp_path / "m.stl")
    # Moebius strip: a band of 8 quads whose ends are glued with a half twist
    n = 8
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([np.cos(t), np.sin(t)], axis=1) * 30
    offset = np.stack([np.cos(t / 2) * np.cos(t), np.cos(t / 2) * np.sin(t), np.sin(t / 2)], axis=1) * 5
    p = np.vstack([np.column_stack([ring, np.zeros(n)]) + offset, np.column_stack([ring, np.zeros(n)]) - offset])
    tri = []
    for i in range(n):
        j = (i + 1) % n
        a, b, c, d = i, j, n + j, n + i
        if j == 0:  # the twist: the far end meets the other edge
            b, c = n + j, j
        tri += [[a, b, c], [a, c, d]]
    with pytest.raises(MeshError, match="not orientable"):
        orient_surface(Mesh(p, {"tri3": np.array(tri)}), np.zeros((1, 3)))


def test_cli_runs_a_mesh_with_bone_files(phantom, tmp_path):
    """``toolkit static simulate --mesh face.inp --bone lefort=maxilla.stl --bone
    distal=mandible.stl --plan plan.toml`` runs and writes the reference mesh with the
    displacement (result.vtu) and the post-operative face (postop.vtu), whose points are the
    reference points plus that displacement."""
    from toolkit.cli import main
    from toolkit.common.meshes.io import read

    write(tmp_path / "face.inp", phantom.mesh)
    for name, stem in (("lefort", "maxilla"), ("distal", "mandible")):
        seg = phantom.segments[name].surface
        meshio.write(tmp_path / f"{stem}.stl", meshio.Mesh(seg.points, [("triangle", seg.cells["tri3"])]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        default_plan(phantom).write(tmp_path / "plan.toml")
    out = tmp_path / "out"
    assert main(["static", "simulate", "--mesh", str(tmp_path / "face.inp"), "--bone",
                 f"lefort={tmp_path / 'maxilla.stl'}", "--bone", f"distal={tmp_path / 'mandible.stl'}",
                 "--plan", str(tmp_path / "plan.toml"), "--out", str(out), "--no-preview"]) == 0
    ref, post = read(out / "result.vtu"), read(out / "postop.vtu")
    np.testing.assert_allclose(ref.points, phantom.mesh.points)
    np.testing.assert_allclose(post.points, ref.points + ref.point_data["displacement"], atol=1e-12)
    assert main(["static", "simulate", "--mesh", str(tmp_path / "face.inp"), "--bone", "lefort",
                 "--plan", str(tmp_path / "plan.toml"), "--out", str(out)]) == 2


@pytest.mark.parametrize("suffix", [".stl", ".obj", ".ply", ".off", ".vtu"])
def test_a_corrupt_bone_surface_is_a_mesh_error_naming_the_file(tmp_path, suffix):
    """Random bytes or an empty file as a bone surface: a MeshError naming the file and the format
    expected (meshio's own ``read`` would exit the process on some of them)."""
    bad = tmp_path / f"maxilla{suffix}"
    bad.write_bytes(np.random.default_rng(0).bytes(2000))
    with pytest.raises(MeshError, match=f"maxilla{suffix}"):
        read_surface(bad)
    bad.write_bytes(b"")
    with pytest.raises(MeshError, match="empty"):
        read_surface(bad)
