"""Tetrahedral meshers behind one call: a closed triangle surface in, tet4 cells out.

:func:`tetrahedralize` fills a closed surface (mm) with linear tetrahedra of a target edge length
through one of the :data:`BACKENDS`, each an optional package imported only when it is used:

==============  ================================  ============================  ===========================
backend         package (mesher)                  licence                       install
==============  ================================  ============================  ===========================
``ftetwild``    ``pytetwild`` (fTetWild)          MPL-2.0 (GMP: LGPL-3)         a dependency
``wildmeshing`` ``wildmeshing`` (fTetWild)        MPL-2.0 (GMP: LGPL-3)         ``pip install wildmeshing``
``tetgen``      ``tetgen`` (TetGen)               AGPL-3.0 (wrapper MIT)        ``[mesh-agpl]``
``gmsh``        ``gmsh`` (Gmsh)                   GPL-2.0-or-later              ``[mesh-gpl]``
==============  ================================  ============================  ===========================

fTetWild builds its mesh inside an envelope of the input (``epsilon``, here 1e-3 of the bounding
box diagonal) and keeps the inside by winding number, so duplicate vertices and faces, small
holes, flipped faces and self-intersections of a segmentation export go in as they are; TetGen
and Gmsh need a closed, consistently oriented surface without self-intersections and keep (TetGen)
or remesh (Gmsh) its triangles. ``benchmarks/meshers.py`` measures them on the phantom's tissue
surface and on damaged copies of it.

Every backend returns tetrahedra of positive orientation (``det[x1 - x0, x2 - x0, x3 - x0] > 0``,
the toolkit's convention) on compacted points (every point belongs to a tetrahedron).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from toolkit.common.errors import ToolkitError

__all__ = ["Backend", "BACKENDS", "DEFAULT", "MeshingError", "tetrahedralize", "available"]


class MeshingError(ToolkitError, RuntimeError):
    """A tetrahedral mesher failed, is not installed, or was given input it cannot mesh."""


@dataclass(frozen=True)
class Backend:
    """A mesher: the module it needs, its licence and how to install it."""

    name: str
    module: str  #: the module imported to use it
    mesher: str  #: the meshing library inside
    licence: str  #: licence of the mesher (and of the Python wrapper when it differs)
    install: str  #: the command that installs it


BACKENDS = {b.name: b for b in (
    Backend("ftetwild", "pytetwild", "fTetWild", "MPL-2.0 (bundled GMP: LGPL-3.0)",
            "pip install pytetwild (a dependency of the toolkit)"),
    Backend("wildmeshing", "wildmeshing", "fTetWild", "MPL-2.0 (bundled GMP: LGPL-3.0)",
            "pip install wildmeshing"),
    Backend("tetgen", "tetgen", "TetGen", "AGPL-3.0 (TetGen; the Python wrapper is MIT)",
            "pip install 'facial-biomech-toolkit[mesh-agpl]'"),
    Backend("gmsh", "gmsh", "Gmsh", "GPL-2.0-or-later", "pip install 'facial-biomech-toolkit[mesh-gpl]'"),
)}
DEFAULT = "ftetwild"


def available() -> dict[str, bool]:
    """``{backend: installed}`` for every backend, without importing any."""
    from importlib.util import find_spec

    return {name: find_spec(b.module) is not None for name, b in BACKENDS.items()}


def tetrahedralize(points, triangles, size_mm: float, backend: str = DEFAULT, *, threads: int = 1
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Fill a closed triangle surface with tetrahedra of edge length about ``size_mm``.

    Parameters
    ----------
    points : (n, 3) float, mm — surface vertices
    triangles : (m, 3) int — surface triangles (indices into ``points``)
    size_mm : target tetrahedron edge length, mm
    backend : one of :data:`BACKENDS`
    threads : threads the mesher may use (fTetWild)

    The mesher runs in a temporary working directory (fTetWild and TetGen write scratch files
    into the current one), so two calls must not run in two threads at once.

    Returns
    -------
    points : (N, 3) float, mm
    tets : (T, 4) int64, positively oriented, every point used

    Raises
    ------
    MeshingError
        The backend is unknown or not installed, the input is not a triangle surface, or the
        mesher failed (the message names the backend and what to try).
    """
    if backend not in BACKENDS:
        raise MeshingError(f"unknown meshing backend {backend!r}; expected one of {list(BACKENDS)}")
    p, t = _as_surface(points, triangles)
    size = float(size_mm)
    if not np.isfinite(size) or size <= 0:
        raise MeshingError(f"size_mm = {size_mm!r}; expected a positive element edge length in mm")
    threads = int(threads)
    if threads < 0:
        raise MeshingError(f"threads = {threads}; expected 0 (all cores) or a positive count")
    spec = BACKENDS[backend]
    try:
        module = __import__(spec.module)
    except ImportError as exc:
        raise MeshingError(f"meshing backend {backend!r} needs the package {spec.module!r} ({spec.mesher}, "
                           f"{spec.licence}), which is not installed ({exc}); install it with "
                           f"{spec.install}, or choose another backend: {_others(backend)}") from None
    try:
        with _scratch_directory(), _python_keeps_ctrl_c():
            out_p, out_t = _RUNNERS[backend](module, p, t, size, threads)
    except MeshingError:
        raise
    except Exception as exc:  # the meshers raise RuntimeError, ValueError or their own classes
        raise MeshingError(f"meshing backend {backend!r} ({spec.mesher}) failed on a surface of {len(p)} "
                           f"vertices and {len(t)} triangles at size {size:g} mm: {type(exc).__name__}: "
                           f"{str(exc).rstrip('. ')}. "
                           f"Repair the surface (close holes, merge duplicate vertices, orient the faces "
                           f"outwards, remove self-intersections) or try another backend: "
                           f"{_others(backend)}") from exc
    return _finish(out_p, out_t, backend)


# ----------------------------------------------------------------------------------------------
# input and output


def _others(backend: str) -> str:
    return ", ".join(f"backend={b!r}" for b in BACKENDS if b != backend)


def _as_surface(points, triangles) -> tuple[np.ndarray, np.ndarray]:
    p = np.array(points, dtype=np.float64, order="C")  # a writable copy: the meshers refuse read-only arrays
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 4:
        raise MeshingError(f"points has shape {p.shape}; expected (n >= 4, 3) vertex coordinates in mm")
    if not np.isfinite(p).all():
        raise MeshingError(f"{int((~np.isfinite(p).all(axis=1)).sum())} surface vertices have NaN/inf "
                           f"coordinates; expected finite coordinates in mm")
    t = np.asarray(triangles)
    if t.ndim != 2 or t.shape[1] != 3 or len(t) < 4 or not np.issubdtype(t.dtype, np.integer):
        raise MeshingError(f"triangles has shape {t.shape} and dtype {t.dtype}; expected (m >= 4, 3) integer "
                           f"vertex indices (split quads into two triangles)")
    t = np.array(t, dtype=np.int64, order="C")
    if t.min() < 0 or t.max() >= len(p):
        raise MeshingError(f"triangles refer to vertex {int(t.max() if t.max() >= len(p) else t.min())}; "
                           f"the surface has {len(p)} vertices (valid 0..{len(p) - 1})")
    return p, t


def _finish(points, tets, backend: str) -> tuple[np.ndarray, np.ndarray]:
    """Compact the points and orient every tetrahedron positively."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    tets = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    if len(tets) == 0:
        raise MeshingError(f"meshing backend {backend!r} returned no tetrahedra; check that the surface is "
                           f"closed and its faces point outwards, or try another backend: {_others(backend)}")
    used, tets = np.unique(tets, return_inverse=True)
    tets = tets.reshape(-1, 4)
    points = points[used]
    x = points[tets]
    det = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0])
    flip = det < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return points, tets


def _require_closed(p, t, backend: str) -> None:
    """Refuse a surface with an edge not shared by exactly two triangles, naming where."""
    edges = np.sort(t[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    bad = unique[counts != 2]
    if len(bad):
        where = np.round(p[bad[0]].mean(axis=0), 1).tolist()
        raise MeshingError(f"meshing backend {backend!r} needs a closed surface: {len(bad)} edges are not shared by "
                           f"exactly two triangles (open: {int((counts == 1).sum())}, shared by more than two: "
                           f"{int((counts > 2).sum())}; the first at {where} mm). Merge duplicate vertices and "
                           f"close the holes first, or use backend='ftetwild', which meshes such surfaces")


# ----------------------------------------------------------------------------------------------
# the backends: each takes (module, points, triangles, size_mm, threads) -> (points, tets)


def _ftetwild(pytetwild, p, t, size, threads):
    return pytetwild.tetrahedralize(p, t.astype(np.int32), edge_length_abs=size, num_threads=threads,
                                    quiet=True, loglevel=6)


def _wildmeshing(wildmeshing, p, t, size, threads):
    diag = float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
    with _silenced_stdout():  # its C++ core prints its progress whatever the log level
        tetra = wildmeshing.Tetrahedralizer(edge_length_r=size / diag, max_threads=threads, coarsen=False)
        tetra.set_log_level(6)
        tetra.set_mesh(p, t.astype(np.int32))
        tetra.tetrahedralize()
        out_p, out_t = tetra.get_tet_mesh()[:2]
    return out_p, out_t


@contextmanager
def _scratch_directory():
    """Run inside a temporary working directory: fTetWild writes ``__tracked_surface.stl`` and
    TetGen ``_skipped.node``/``.face`` into the current directory, which is the user's. The working
    directory is process-wide: meshing is not to run in two threads at once."""
    import tempfile

    previous = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="toolkit-mesher-") as tmp:
        os.chdir(tmp)
        try:
            yield
        finally:
            os.chdir(previous)


@contextmanager
def _python_keeps_ctrl_c():
    """Keep Python's Ctrl-C handling across a mesher call.

    fTetWild's runtime replaces the process's SIGINT handler with the default one (a SIGINT after a
    pytetwild call ended the process silently instead of raising ``KeyboardInterrupt``). Inside the
    block SIGINT is blocked (a Ctrl-C waits, pending, until the mesher returns: its C++ code cannot
    be stopped midway anyway); on leaving, Python's handler is installed again and then SIGINT is
    unblocked, so a pending Ctrl-C reaches Python. Outside the main thread, or without POSIX
    signal masks, it does nothing."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    handler = signal.getsignal(signal.SIGINT)
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        if handler is not None:
            signal.signal(signal.SIGINT, handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


@contextmanager
def _silenced_stdout():
    """Send file descriptor 1 (C-level prints) to ``/dev/null`` for the duration."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def _tetgen(tetgen, p, t, size, threads):
    # the volume bound: 1.6 regular tetrahedra of edge h (h^3 / (6 sqrt 2) each) gives a mean edge of
    # about h; minratio bounds the radius-edge ratio
    gen = tetgen.TetGen(p, t.astype(np.int32))
    nodes, elems = gen.tetrahedralize(quality=True, minratio=1.5, mindihedral=10.0, fixedvolume=True,
                                      maxvolume=1.6 * size**3 / (6.0 * np.sqrt(2.0)), quiet=True,
                                      nowarning=True)[:2]
    return nodes, elems


def _gmsh(gmsh, p, t, size, threads):
    """Remesh the surface at ``size`` (classified into smooth patches at 40 degrees) and fill it."""
    _require_closed(p, t, "gmsh")  # Gmsh ends the process (a segmentation fault) on an open surface
    if gmsh.isInitialized():
        raise MeshingError("Gmsh is already initialised in this process; backend 'gmsh' runs its own session")
    gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", threads)
        gmsh.model.add("tissue")
        surf = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, surf, np.arange(1, len(p) + 1), p.ravel())
        gmsh.model.mesh.addElementsByType(surf, 2, [], (t + 1).ravel())
        gmsh.model.mesh.classifySurfaces(40.0 * np.pi / 180.0, True, True, np.pi)
        gmsh.model.mesh.createGeometry()
        surfaces = [s for _, s in gmsh.model.getEntities(2)]
        loop = gmsh.model.geo.addSurfaceLoop(surfaces)
        gmsh.model.geo.addVolume([loop])
        gmsh.model.geo.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMin", 0.4 * size)
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.8 * size)  # a mean edge of about ``size``
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
        gmsh.option.setNumber("Mesh.Algorithm3D", 10)  # HXT
        gmsh.option.setNumber("Mesh.Optimize", 1)
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        etypes, _, enodes = gmsh.model.mesh.getElements(3)
        if 4 not in list(etypes):
            raise MeshingError("meshing backend 'gmsh' (Gmsh) made no tetrahedra: the surface may not be closed; "
                               f"repair it or try another backend: {_others('gmsh')}")
        conn = np.asarray(enodes[list(etypes).index(4)], dtype=np.int64).reshape(-1, 4)
        index = np.zeros(int(tags.max()) + 1, dtype=np.int64)
        index[tags.astype(np.int64)] = np.arange(len(tags))
        return np.asarray(coords).reshape(-1, 3), index[conn]
    finally:
        gmsh.finalize()


_RUNNERS = {"ftetwild": _ftetwild, "wildmeshing": _wildmeshing, "tetgen": _tetgen, "gmsh": _gmsh}
