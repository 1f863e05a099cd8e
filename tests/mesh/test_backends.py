"""The tetrahedral meshers fill a closed surface with positively oriented tetrahedra of the
enclosed volume: on a 20 mm cube (planar faces, so every mesher can reproduce it exactly) the
mesh volume is the cube's 8000 mm^3 within 2 %, every tetrahedron has a positive Jacobian and the
mesh's boundary is a closed, edge-manifold surface. A backend not installed is skipped."""

import numpy as np
import pytest

from toolkit.common.errors import ToolkitError
from toolkit.common.meshes.quality import scaled_jacobian
from toolkit.mesh.backends import BACKENDS, Backend, MeshingError, available, tetrahedralize

EDGE_MM = 20.0


def _cube():
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float) * EDGE_MM
    quads = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])
    return corners, np.vstack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])


def _boundary(tets):
    faces = tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3)
    _, index, counts = np.unique(np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True)
    return faces[index[counts == 1]]


@pytest.mark.parametrize("backend", list(BACKENDS))
def test_cube_volume_orientation_and_closed_boundary(backend):
    if not available()[backend]:
        pytest.skip(f"{BACKENDS[backend].module} is not installed ({BACKENDS[backend].install})")
    points, triangles = _cube()
    p, t = tetrahedralize(points, triangles, 5.0, backend=backend)
    x = p[t]
    volume = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0]) / 6.0
    assert volume.sum() == pytest.approx(EDGE_MM**3, rel=0.02)
    assert (scaled_jacobian("tet4", x) > 0).all()
    assert np.array_equal(np.unique(t), np.arange(len(p)))  # compacted: every point in a tetrahedron
    faces = _boundary(t)
    directed = faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    assert len(np.unique(directed, axis=0)) == len(directed)  # each edge once per direction: closed, manifold
    assert np.array_equal(np.unique(directed, axis=0), np.unique(directed[:, ::-1], axis=0))
    assert len(t) > 20  # the size was honoured (a 5 mm mesh of a 20 mm cube is not its 5 or 6 corner tets)


def test_missing_backend_names_the_install_command(monkeypatch):
    monkeypatch.setitem(BACKENDS, "gmsh", Backend("gmsh", "no_such_mesher_module", "Gmsh", "GPL-2.0-or-later",
                                                  "pip install 'facial-biomech-toolkit[mesh-gpl]'"))
    points, triangles = _cube()
    with pytest.raises(MeshingError, match=r"not installed.*\[mesh-gpl\].*backend='ftetwild'"):
        tetrahedralize(points, triangles, 5.0, backend="gmsh")


@pytest.mark.parametrize("kwargs, match", [
    ({"backend": "netgen"}, "unknown meshing backend 'netgen'"),
    ({"size_mm": 0.0}, "size_mm = 0.0"),
    ({"triangles": np.zeros((12, 4), dtype=int)}, r"triangles has shape \(12, 4\)"),
    ({"triangles": np.full((12, 3), 8)}, "refer to vertex 8"),
])
def test_bad_input_is_refused_before_meshing(kwargs, match):
    points, triangles = _cube()
    args = {"points": points, "triangles": triangles, "size_mm": 5.0, **kwargs}
    with pytest.raises(MeshingError, match=match) as info:
        tetrahedralize(**args)
    assert isinstance(info.value, ToolkitError)


@pytest.mark.parametrize("backend", list(BACKENDS))
def test_read_only_input_is_meshed(backend):
    """Surfaces from a :class:`~toolkit.common.meshes.mesh.Mesh` hold read-only arrays."""
    if not available()[backend]:
        pytest.skip(f"{BACKENDS[backend].module} is not installed ({BACKENDS[backend].install})")
    points, triangles = _cube()
    points.flags.writeable = triangles.flags.writeable = False
    p, t = tetrahedralize(points, triangles, 10.0, backend=backend)
    assert len(t) >= 5 and (scaled_jacobian("tet4", p[t]) > 0).all()


def test_gmsh_refuses_an_open_surface_before_meshing():
    """Gmsh ends the process on an open surface; the check before it names the open edges."""
    if not available()["gmsh"]:
        pytest.skip(f"gmsh is not installed ({BACKENDS['gmsh'].install})")
    points, triangles = _cube()
    with pytest.raises(MeshingError, match=r"needs a closed surface: 3 edges .*open: 3.*backend='ftetwild'"):
        tetrahedralize(points, triangles[1:], 5.0, backend="gmsh")


@pytest.mark.parametrize("during", [False, True], ids=["after", "during"])
def test_ctrl_c_reaches_python_after_and_during_meshing(during, monkeypatch):
    """fTetWild replaces the SIGINT handler with the default one, which would end the process
    silently. After a meshing a Ctrl-C is Python's ``KeyboardInterrupt``; one arriving during it
    (here raised from inside the mesher call, deterministically) is held until the mesher returns
    and then raised."""
    import signal


    if not available()["ftetwild"]:
        pytest.skip("pytetwild is not installed")
    # Python's own handler, as in a foreground process (a test run started in the background
    # inherits an ignored SIGINT)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        _mesh_then_ctrl_c(during, monkeypatch)
    finally:
        signal.signal(signal.SIGINT, previous)


def _mesh_then_ctrl_c(during: bool, monkeypatch) -> None:
    import signal

    from toolkit.mesh import backends

    if during:
        mesher = backends._RUNNERS["ftetwild"]

        def interrupted_mesher(*args):
            out = mesher(*args)
            signal.raise_signal(signal.SIGINT)  # pending: SIGINT is blocked in the mesher call
            return out

        monkeypatch.setitem(backends._RUNNERS, "ftetwild", interrupted_mesher)
        with pytest.raises(KeyboardInterrupt):
            tetrahedralize(*_cube(), 5.0, backend="ftetwild")
    else:
        tetrahedralize(*_cube(), 5.0, backend="ftetwild")
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
