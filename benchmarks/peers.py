"""The toolkit's static solve beside peer finite-element codes on the same face problem.

One problem for every code: a face meshed by ``toolkit mesh`` (:func:`toolkit.mesh.mesh_face`) in
quadratic tetrahedra (tet10, straight edges), one homogeneous isotropic material (the toolkit's
tissue, :class:`~toolkit.common.fem.materials.LinearElastic`: E 0.003 MPa, nu 0.47, in every element:
``material_assignment("linear", mesh)`` would make the lip muscle transversely isotropic), the face's FIXED
nodes held and its MOVING (bone) nodes carried by the first of 3 increments of a plan's rigid
motions, every other node free: a pure Dirichlet problem, no sliding constraints, no ties. Sizes:

- ``7``, ``3.5``: the paper phantom's surfaces (:func:`toolkit.mesh.phantom.phantom_surfaces`)
  meshed at 7 and 3.5 mm, loaded by the phantom's default bimaxillary plan;
- ``ct``: the head CT in ``tests/data/headsq`` (:func:`toolkit.mesh.ct.ct_surfaces`) meshed at
  3 mm, loaded by ``benchmarks/real_ct.py``'s mandibular advance (distal segment 5 mm anterior,
  proximal segments following about their condyles).

Each mesh and its prescribed displacements are made once and kept in ``benchmarks/work/peers/``.
Every code integrates on the toolkit's 4-point tet10 rule, which is exact for the stiffness of
straight-edged quadratic tetrahedra, so all solve the same discrete system.

Codes and methods, each run in a fresh single-threaded process (its peak resident memory is its own):

- ``toolkit`` ``amg``: :class:`~toolkit.static.StaticProblem`'s assembly, the prescribed dofs
  eliminated by :meth:`~toolkit.static.Constraints.reduction`, and its solver for tet10
  (:class:`~toolkit.common.fem.solvers.LinearSolver` ``amg``: CG on smoothed aggregation with the
  rigid-body modes, coarsened first to the corner nodes); ``setup_s`` is its first solve less a
  second one on the same hierarchy, which is ``solve_s``;
- ``scikit-fem``: ``MeshTet2`` from the tet10 cells (``skfem.io.meshio.from_meshio``),
  ``Basis(mesh, ElementVector(ElementTetP2()), intorder=2)``,
  ``asm(linear_elasticity(*lame_parameters(E, nu)))`` and ``condense``; ``superlu``: SciPy's
  SuperLU (what ``skfem.solve`` calls through ``spsolve``, timed here as ``splu`` and its solve),
  ``amg-cg``: ``skfem.solve`` with ``solver_iter_pcg`` preconditioned by pyamg's smoothed
  aggregation with the rigid-body modes (``aspreconditioner()``, as scikit-fem's example 9);
- ``ngsolve``: the corner tetrahedra as a Netgen mesh, ``VectorH1(order=2)`` (hierarchical P2 on
  straight edges: the same space), the prescribed vertex and edge dofs taken out of its free dofs;
  ``sparsecholesky``: its sparse Cholesky factorization; ``bddc-cg``: its CG preconditioned by BDDC
  with the vertex dofs as wirebasket (``wb_withedges=False``: the default wirebasket of a P2 space
  holds every dof, a direct solve) and a sparse Cholesky coarse solve. BDDC is set up while the
  form assembles: ``setup_s`` is that assembly less a plain one. Nodal values come from the
  coefficients (a vertex's own; a mid-node's its ends' mean plus the edge bubble's share);
- ``sfepy``: the corner tetrahedra (``Mesh.from_data``, ``3_4``), a ``vector`` field of
  ``approx_order=2``, ``dw_lin_elastic`` on an order-2 ``Integral`` and an ``EssentialBC`` on a region
  of the prescribed vertices and edges, solved by ``Problem.solve`` with its ``nls.newton`` (one
  iteration); ``direct``: ``ls.scipy_direct`` (SuperLU: scikit-umfpack is not installed),
  ``pyamg-cg``: ``ls.pyamg`` smoothed aggregation with the rigid-body modes (``method:B``),
  CG-accelerated. ``assemble_s`` is its Newton's matrix and residual time (the residual twice: the
  right-hand side and the convergence check), ``setup_s`` the factorization or the hierarchy (timed
  inside its solver), ``solve_s`` the rest of its solve time.

Iterative methods stop at a relative residual of 1e-9 (the toolkit's default). Per run: nodes,
free dofs, seconds to assemble the reduced system (``assemble_s``), to factorize or set up the
preconditioner (``setup_s``), to solve (``solve_s``) and the three together (``total_s``),
iterations, peak resident memory (``peak_rss_mib``) and ``rel_diff``,
``||u - u_toolkit|| / ||u_toolkit||`` over the mesh's nodes. A code's nodes are matched to the
toolkit's element by element, not by position: the phantom's lip slit holds pairs of nodes at one
position. A run that exceeds ``--timeout`` minutes or ``--memory`` GiB is stopped and recorded as
failed. The SuperLU runs are skipped above ``--superlu-max-dofs`` free dofs (200,000: at 178k dofs
each took 6 to 7 GiB and 6 min on a 2-core Intel Xeon, and its fill grows faster than the dofs).

The ``neo-hookean`` problem (on ``--neo-hookean-sizes``) is one load step of the toolkit's
compressible Neo-Hookean solid, ``W = mu/2 (I1 - 3) - mu ln J + lam/2 (ln J)^2``
(:class:`~toolkit.common.fem.materials.NeoHookean`, the same E and nu), on the same mesh and
prescribed displacements: ``StaticProblem.solve`` (Newton with an energy line search, AMG-CG
solves) beside NGSolve's ``Variation`` of the same energy density and its ``solvers.Newton``
(sparse Cholesky), each Newton started from the linear response (the tangent at rest). Only
``solve_s`` (the whole solve, assembly included) and ``iterations`` (Newton's, the linear
predictor counted as one) are given.

Writes ``benchmarks/results/peers.csv`` with its provenance sidecar; a rerun skips the rows the
table holds (``--fresh`` runs the selected ones again, ``--retry-failed`` the ones not ``ok``).

Usage::

    python benchmarks/peers.py                                    # every size, code and problem
    python benchmarks/peers.py --sizes 7 --codes toolkit ngsolve
    python benchmarks/peers.py --sizes 7 3.5 --problems linear --timeout 10
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, ROOT, WORK, read_sidecar, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/mesh/", "toolkit/static/", "toolkit/common/fem/", "toolkit/common/meshes/",
            "toolkit/common/phantoms/", "toolkit/common/analysis/surface_distance.py", "toolkit/common/papers.py")

HEADSQ = ROOT / "tests" / "data" / "headsq" / "quarter.nhdr"
CACHE = WORK / "peers"
SIZES = ("7", "3.5", "ct")
PROBLEMS = ("linear", "neo-hookean")
#: (code, method) of each problem, in the order they run
RUNS = {
    "linear": (("toolkit", "amg"), ("scikit-fem", "superlu"), ("scikit-fem", "amg-cg"),
               ("ngsolve", "sparsecholesky"), ("ngsolve", "bddc-cg"), ("sfepy", "direct"), ("sfepy", "pyamg-cg")),
    "neo-hookean": (("toolkit", "amg"), ("ngsolve", "sparsecholesky")),
}
CODES = ("toolkit", "scikit-fem", "ngsolve", "sfepy")
#: the runs that factorize with SciPy's SuperLU (COLAMD ordering)
SUPERLU = (("scikit-fem", "superlu"), ("sfepy", "direct"))
DISTRIBUTION = {"toolkit": "facial-biomech-toolkit", "scikit-fem": "scikit-fem", "ngsolve": "ngsolve",
                "sfepy": "sfepy"}
RTOL = 1e-9
#: the toolkit's tet10 edges (corner pairs of mid-edge nodes 4..9, VTK order)
TET10_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])


# ------------------------------------------------------------------ the problem
def _phantom_face(size_mm: float):
    """The paper phantom's surfaces meshed by ``toolkit mesh`` at ``size_mm`` (tet10) and the first
    of 3 increments of the phantom's default plan on its bony segments."""
    from toolkit.common.phantoms.phantom import face_hex
    from toolkit.mesh import mesh_face
    from toolkit.mesh.phantom import phantom_surfaces
    from toolkit.static import load_case

    surfaces = phantom_surfaces(face_hex("paper"))
    face = mesh_face(surfaces.tissue, surfaces.bones, surfaces.commissures, size_mm=size_mm, order=2)
    bones = {k: v for k, v in face.bones.items() if k != "skull"}
    case = load_case(face.mesh, plan=load_case(resolution="paper").plan, bones=bones)
    return face.mesh, case.segments, case.plan.increments(3)[0]


def _ct_face(size_mm: float = 3.0):
    """The head CT's face meshed by ``toolkit mesh`` at ``size_mm`` (tet10) and the first of 3
    increments of ``benchmarks/real_ct.py``'s mandibular advance."""
    from real_ct import plans

    from toolkit.mesh import mesh_face
    from toolkit.mesh.ct import ct_surfaces
    from toolkit.static import load_case

    surfaces = ct_surfaces(HEADSQ)
    marks = surfaces.report["landmarks_mm"]
    face = mesh_face(surfaces.tissue, surfaces.bones, surfaces.commissures, size_mm=size_mm, order=2)
    condyles = np.array([marks["condyle_left"], marks["condyle_right"]])
    bones = {k: v for k, v in face.bones.items() if k != "skull"}
    case = load_case(face.mesh, plan=plans(face, condyles)["advance"], bones=bones)
    return face.mesh, case.segments, case.plan.increments(3)[0]


def problem_arrays(size: str) -> dict:
    """The mesh and Dirichlet data of ``size`` (``7``, ``3.5`` mm phantom, ``ct``), meshed once and
    kept in ``benchmarks/work/peers/<size>.npz``: ``points (n, 3)`` mm, ``cells (e, 10)`` tet10
    (VTK node order), ``prescribed (p,)`` node indices (FIXED, then MOVING) and ``values (p, 3)``
    mm, their displacements."""
    path = CACHE / f"{size}.npz"
    if not path.exists():
        from static_solvers import dirichlet

        from toolkit.static.boundary import BoundaryConditions

        mesh, segments, plan = _ct_face() if size == "ct" else _phantom_face(float(size))
        if set(mesh.cells) != {"tet10"}:
            raise ValueError(f"expected a tet10 mesh, got blocks {sorted(mesh.cells)}")
        nodes, values = dirichlet(mesh, BoundaryConditions.from_mesh(mesh, segments), plan)
        CACHE.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.stem}.{os.getpid()}.npz")
        np.savez(tmp, points=mesh.points, cells=mesh.cells["tet10"], prescribed=nodes, values=values)
        tmp.replace(path)
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def _corner_mesh(data: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The corner nodes ``(c,)`` (toolkit indices), their points ``(c, 3)`` mm and the tetrahedra
    ``(e, 4)`` in corner numbering, for the codes that make P2 on a linear mesh."""
    corners = np.unique(data["cells"][:, :4])
    renumber = np.full(data["points"].shape[0], -1)
    renumber[corners] = np.arange(corners.size)
    return corners, data["points"][corners], renumber[data["cells"][:, :4]]


def _edge_midnodes(data: dict, edges: np.ndarray) -> np.ndarray:
    """The toolkit's mid-edge node of each edge ``(k, 2)`` (corner numbering of :func:`_corner_mesh`)."""
    corners, _, tets = _corner_mesh(data)
    n = corners.size
    a, b = tets[:, TET10_EDGES[:, 0]].ravel(), tets[:, TET10_EDGES[:, 1]].ravel()
    keys, first = np.unique(np.minimum(a, b) * n + np.maximum(a, b), return_index=True)
    wanted = edges.min(axis=1) * n + edges.max(axis=1)
    pos = np.minimum(np.searchsorted(keys, wanted), keys.size - 1)
    if not np.array_equal(keys[pos], wanted):
        raise ValueError(f"{np.count_nonzero(keys[pos] != wanted)} edges are not edges of the tet10 mesh")
    return data["cells"][:, 4:].ravel()[first[pos]]


def _nearest(points: np.ndarray, at: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Index into ``points (m, 3)`` of each point ``at (k, 3)`` (mm), which must coincide within ``tol``."""
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(points).query(at)
    if dist.max() > tol:
        raise ValueError(f"{np.count_nonzero(dist > tol)} points have no node within {tol} mm "
                         f"(farthest {dist.max():.3g} mm)")
    return idx


def _scalar_nodes(data: dict, conn: np.ndarray, points: np.ndarray) -> np.ndarray:
    """A code's P2 node ``(n,)`` of each toolkit node, from its element connectivity ``conn (e, 10)``
    (the toolkit's elements, its own local order) and node positions ``points (m, 3)`` mm.

    The local orders are matched on the first element's positions (distinct within an element) and
    checked on every element; the map goes element by element, so nodes that share a position
    (the phantom's lip slit holds such pairs) keep their own counterparts.
    """
    X, cells = data["points"], data["cells"]
    dist = np.linalg.norm(points[conn[0]][:, None, :] - X[cells[0]][None, :, :], axis=2)
    order = np.argmin(dist, axis=1)  # conn's local node k is the toolkit's local node order[k]
    if np.sort(order).tolist() != list(range(10)) or \
            not np.allclose(points[conn], X[cells[:, order]], rtol=0, atol=1e-9):
        raise ValueError("the code's element nodes do not match the tet10 cells in one local order")
    node = np.full(X.shape[0], -1)
    node[cells[:, order]] = conn
    return node


def _rigid_modes(points: np.ndarray) -> np.ndarray:
    """The 6 rigid-body modes ``(3 n, 6)`` of nodes ``(n, 3)``, node-major (the near-nullspace of pyamg);
    the toolkit's ``rigid_body_modes``, here so that a peer's process does not import the toolkit."""
    x = points - points.mean(axis=0)
    B = np.zeros((x.shape[0], 3, 6))
    B[:, 0, 0] = B[:, 1, 1] = B[:, 2, 2] = 1.0
    B[:, 1, 3], B[:, 2, 3] = -x[:, 2], x[:, 1]
    B[:, 0, 4], B[:, 2, 4] = x[:, 2], -x[:, 0]
    B[:, 0, 5], B[:, 1, 5] = -x[:, 1], x[:, 0]
    return B.reshape(-1, 6)


def _lame(E: float, nu: float) -> tuple[float, float]:
    """``(lam, mu)`` MPa, as :func:`toolkit.common.fem.materials.lame`."""
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


class _Stopwatch:
    """CPU and wall seconds of named stages: ``with clock("assemble"): ...``; ``clock.add(stage,
    cpu, wall)`` for a stage timed otherwise. Every run is single-threaded, so its CPU time is the
    wall time it takes on an idle core."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self.wall: dict[str, float] = {}

    def add(self, stage: str, cpu: float, wall: float) -> None:
        self.seconds[stage] = self.seconds.get(stage, 0.0) + cpu
        self.wall[stage] = self.wall.get(stage, 0.0) + wall

    def __call__(self, stage: str):
        clock = self

        class _Stage:
            def __enter__(self):
                self.t0 = time.process_time(), time.perf_counter()

            def __exit__(self, *exc):
                clock.add(stage, time.process_time() - self.t0[0], time.perf_counter() - self.t0[1])

        return _Stage()


def _timed(fun, clock: _Stopwatch, stage: str):
    """``fun`` with its calls' time added to ``clock``'s ``stage``."""
    def wrapped(*args, **kwargs):
        with clock(stage):
            return fun(*args, **kwargs)
    return wrapped


# ------------------------------------------------------------------ the codes
def _toolkit(data: dict, method: str, problem: str, E: float, nu: float) -> tuple[np.ndarray, dict]:
    from toolkit.common.fem.coarse import reduced_coarse_space
    from toolkit.common.fem.materials import LinearElastic, NeoHookean
    from toolkit.common.fem.solvers import LinearSolver
    from toolkit.common.meshes.mesh import Mesh
    from toolkit.static import Constraints, StaticProblem
    from toolkit.static.problem import reduced_matrix
    from toolkit.static.stiffness import MaterialAssignment

    clock = _Stopwatch()
    mesh = Mesh(data["points"], {"tet10": data["cells"]})
    constraints = Constraints(mesh.n_points, data["prescribed"], data["values"])
    if problem == "neo-hookean":
        with clock("solve"):
            sp_ = StaticProblem(mesh, MaterialAssignment(NeoHookean(E, nu)), method)
            solution = sp_.solve(constraints)
        return solution.displacement, {"clock": clock, "iterations": solution.newton_iterations,
                                       "dofs": constraints.reduction()[0].shape[1]}
    with clock("assemble"):
        sp_ = StaticProblem(mesh, MaterialAssignment(LinearElastic(E, nu)), method)
        K = sp_.stiffness
        T, u0 = constraints.reduction()
        A = reduced_matrix(K, T)
        b = -(T.T @ (K @ u0))
    solver = LinearSolver(method, timed_budget=False)
    args = {"near_nullspace": T.T @ sp_._modes,
            "coarse_space": partial(reduced_coarse_space, sp_._corners, T, mesh.points)}
    with clock("setup"):
        x, first = solver.solve(A, b, **args)  # builds the hierarchy, then CG
    with clock("solve"):
        solver.solve(A, b, **args)  # CG on the same hierarchy
    for times in (clock.seconds, clock.wall):  # the first solve less the second
        times["setup"] -= times["solve"]
    return (T @ x + u0).reshape(-1, 3), {"clock": clock, "iterations": first.iterations, "dofs": A.shape[0]}


def _scikit_fem(data: dict, method: str, problem: str, E: float, nu: float) -> tuple[np.ndarray, dict]:
    import meshio
    import scipy.sparse.linalg as spla
    from skfem import Basis, ElementTetP2, ElementVector, asm, condense, solve
    from skfem.io.meshio import from_meshio
    from skfem.models.elasticity import lame_parameters, linear_elasticity
    from skfem.utils import solver_iter_pcg

    clock = _Stopwatch()
    X = data["points"]
    with clock("assemble"):
        mesh = from_meshio(meshio.Mesh(X, [("tetra10", data["cells"])]))
        basis = Basis(mesh, ElementVector(ElementTetP2()), intorder=2)  # the toolkit's 4-point rule
        K = asm(linear_elasticity(*lame_parameters(E, nu)), basis)
    # the vector dofs of each scalar node of the P2 mesh (vertices, then edges), and the node of
    # each toolkit node
    node_dofs = np.vstack([basis.nodal_dofs.T, basis.edge_dofs.T])
    at = _scalar_nodes(data, mesh.dofs.element_dofs.T, mesh.doflocs.T)
    D = node_dofs[at[data["prescribed"]]].ravel()
    x = np.zeros(basis.N)
    x[D] = data["values"].ravel()
    with clock("assemble"):
        A, b, x, interior = condense(K, np.zeros(basis.N), x=x, D=D)
    info = {}
    if method == "superlu":  # skfem.solve's spsolve: SuperLU, COLAMD ordering
        with clock("setup"):
            lu = spla.splu(A.tocsc())
        with clock("solve"):
            x[interior] = lu.solve(b)
    else:
        from pyamg import smoothed_aggregation_solver

        B = _rigid_modes(mesh.doflocs.T)[np.argsort(node_dofs.ravel())][interior]  # modes in dof order
        with clock("setup"):
            M = smoothed_aggregation_solver(A, B=B).aspreconditioner()
        count = [0]

        def callback(_):
            count[0] += 1

        with clock("solve"):
            x[interior] = solve(A, b, solver=solver_iter_pcg(M=M, rtol=RTOL, maxiter=2000, callback=callback))
        info["iterations"] = count[0]
    return x[node_dofs[at]], {"clock": clock, "dofs": A.shape[0], **info}


def _ngsolve_mesh(data: dict):
    """The corner tetrahedra as an NGSolve mesh, and each of its edges' toolkit mid-node."""
    import ngsolve as ng
    from netgen.meshing import FaceDescriptor
    from netgen.meshing import Mesh as NetgenMesh

    corners, points, tets = _corner_mesh(data)
    ngmesh = NetgenMesh(dim=3)
    ngmesh.AddPoints(np.ascontiguousarray(points))
    ngmesh.Add(FaceDescriptor(surfnr=1, domin=1, bc=1))
    ngmesh.AddElements(dim=3, index=1, data=np.ascontiguousarray(tets, dtype=np.int32), base=0)
    mesh = ng.Mesh(ngmesh)
    edges = np.array([[v.nr for v in e.vertices] for e in mesh.edges])
    return mesh, corners, edges, _edge_midnodes(data, edges)


class _Hierarchical:
    """NGSolve's hierarchical P2 coefficients and the toolkit's nodal values: a vertex dof is the
    vertex's value, an edge dof the coefficient of the edge's bubble, the mid-node's value less its
    ends' mean over the bubble's value at the midpoint."""

    def __init__(self, fes, data: dict, corners: np.ndarray, edges: np.ndarray, midnodes: np.ndarray):
        import ngsolve as ng

        scalar = fes.components[0]
        self.n, self.corners, self.edges, self.midnodes = scalar.ndof, corners, edges, midnodes
        self.vdofs = np.array([scalar.GetDofNrs(ng.NodeId(ng.VERTEX, i))[0] for i in range(corners.size)])
        self.edofs = np.array([scalar.GetDofNrs(ng.NodeId(ng.EDGE, i))[0] for i in range(edges.shape[0])])
        probe = ng.GridFunction(scalar)  # the bubble's value at its midpoint, the same on every edge
        probe.vec[:] = 0.0
        probe.vec[int(self.edofs[0])] = 1.0
        X = data["points"]
        self.bubble = probe(fes.mesh(*(0.5 * (X[corners[edges[0, 0]]] + X[corners[edges[0, 1]]]))))

    def _ends(self, u: np.ndarray) -> np.ndarray:
        return 0.5 * (u[self.corners[self.edges[:, 0]]] + u[self.corners[self.edges[:, 1]]])

    def coefficients(self, u: np.ndarray) -> np.ndarray:
        """``(3 n_dof,)`` coefficients (component blocks) of nodal values ``u (n_nodes, 3)``."""
        coef = np.zeros((3, self.n))
        coef[:, self.vdofs] = u[self.corners].T
        coef[:, self.edofs] = ((u[self.midnodes] - self._ends(u)) / self.bubble).T
        return coef.ravel()

    def values(self, coef: np.ndarray, n_nodes: int) -> np.ndarray:
        """Nodal values ``(n_nodes, 3)`` of coefficients ``(3 n_dof,)``."""
        coef = np.asarray(coef).reshape(3, self.n)
        u = np.zeros((n_nodes, 3))
        u[self.corners] = coef[:, self.vdofs].T
        u[self.midnodes] = self._ends(u) + self.bubble * coef[:, self.edofs].T
        return u

    def fix(self, fes, nodes: np.ndarray) -> object:
        """``fes``'s free dofs less those of ``nodes``: the vertex dofs of prescribed corners and
        the edge dofs of prescribed mid-nodes."""
        prescribed = np.zeros(max(self.corners.max(), self.midnodes.max()) + 1, bool)
        prescribed[nodes] = True
        held = np.concatenate([self.vdofs[prescribed[self.corners]], self.edofs[prescribed[self.midnodes]]])
        free = fes.FreeDofs()
        for dof in (held[None, :] + self.n * np.arange(3)[:, None]).ravel():
            free.Clear(int(dof))
        return free


def _ngsolve(data: dict, method: str, problem: str, E: float, nu: float) -> tuple[np.ndarray, dict]:
    import ngsolve as ng

    clock = _Stopwatch()
    X = data["points"]
    lam, mu = _lame(E, nu)
    info = {}
    with clock("assemble"):
        mesh, corners, edges, midnodes = _ngsolve_mesh(data)
        fes = ng.VectorH1(mesh, order=2, **({"wb_withedges": False} if method == "bddc-cg" else {}))
        dofs = _Hierarchical(fes, data, corners, edges, midnodes)
        free = dofs.fix(fes, data["prescribed"])
        given = np.zeros_like(X)
        given[data["prescribed"]] = data["values"]
    u, v = fes.TnT()
    gfu = ng.GridFunction(fes)
    gfu.vec.FV().NumPy()[:] = dofs.coefficients(given)
    rule = ng.dx(intrules=_ngsolve_rule())

    def elastic():
        def strain(w):
            return ng.Sym(ng.Grad(w))

        form = ng.BilinearForm(fes, symmetric=True)
        form += (2 * mu * ng.InnerProduct(strain(u), strain(v))
                 + lam * ng.Trace(strain(u)) * ng.Trace(strain(v))) * rule
        return form

    def direct(form):  # the free dofs' solve of the form's matrix on the prescribed values
        r = gfu.vec.CreateVector()
        r.data = -(form.mat * gfu.vec)
        with clock("setup"):
            inverse = form.mat.Inverse(free, inverse="sparsecholesky")
        with clock("solve"):
            gfu.vec.data += inverse * r

    if problem == "neo-hookean":
        from ngsolve.solvers import Newton

        def energy(w):
            F = ng.Id(3) + ng.Grad(w)
            J = ng.Det(F)
            return mu / 2 * (ng.InnerProduct(F, F) - 3) - mu * ng.log(J) + lam / 2 * ng.log(J) ** 2

        a = ng.BilinearForm(fes, symmetric=True)
        a += ng.Variation(energy(u) * rule)
        newton = _Stopwatch()
        with newton("solve"):
            predictor = elastic()  # the tangent at rest: Newton starts from the linear response, as the toolkit's
            predictor.Assemble()
            direct(predictor)
            del predictor
            status, iterations = Newton(a, gfu, freedofs=free, maxit=50, maxerr=1e-12, inverse="sparsecholesky",
                                        printing=False)
        clock = newton
        if status != 0:
            raise RuntimeError(f"NGSolve's Newton did not converge in {iterations} iterations")
        info["iterations"] = iterations + 1  # the predictor counts as one, as the toolkit counts it
    elif method == "sparsecholesky":
        a = elastic()
        with clock("assemble"):
            a.Assemble()
        direct(a)
    else:
        # BDDC works on the element matrices as they are assembled: the plain assembly is timed
        # first, the preconditioner's setup is the assembly with it less that
        from ngsolve.krylovspace import CGSolver

        a = elastic()
        plain = _Stopwatch()
        with plain("assemble"):
            a.Assemble()
        clock.add("assemble", plain.seconds["assemble"], plain.wall["assemble"])
        a = elastic()
        pre = ng.Preconditioner(a, "bddc", inverse="sparsecholesky")
        with clock("setup"):
            a.Assemble()
        clock.add("setup", -plain.seconds["assemble"], -plain.wall["assemble"])
        r = gfu.vec.CreateVector()
        r.data = -(a.mat * gfu.vec)
        with clock("solve"):
            cg = CGSolver(a.mat, pre.mat, tol=RTOL, maxiter=2000)
            gfu.vec.data += cg * r
        if not cg.residuals[-1] <= RTOL * cg.residuals[0]:
            raise RuntimeError(f"NGSolve's CG did not reach {RTOL} in {cg.iterations} iterations")
        info["iterations"] = cg.iterations
    U = dofs.values(gfu.vec.FV().NumPy(), X.shape[0])
    return U, {"clock": clock, "dofs": sum(free), **info}


def _ngsolve_rule():
    """The toolkit's tet10 rule (4 points, degree 2) as an NGSolve integration rule."""
    import ngsolve as ng

    a = (5.0 - np.sqrt(5.0)) / 20.0
    b = 1.0 - 3.0 * a
    points = [(a, a, a), (b, a, a), (a, b, a), (a, a, b)]
    return {ng.TET: ng.IntegrationRule(points, [1.0 / 24.0] * 4)}


def _sfepy(data: dict, method: str, problem: str, E: float, nu: float) -> tuple[np.ndarray, dict]:
    from sfepy.base.base import IndexedStruct, output
    from sfepy.discrete import Equation, Equations, FieldVariable, Function, Integral, Material, Problem
    from sfepy.discrete.common.region import Region
    from sfepy.discrete.conditions import Conditions, EssentialBC
    from sfepy.discrete.fem import FEDomain, Field, Mesh
    from sfepy.mechanics.matcoefs import stiffness_from_youngpoisson
    from sfepy.solvers.ls import PyAMGSolver, ScipyDirect
    from sfepy.solvers.nls import Newton
    from sfepy.terms import Term

    output.set_output(quiet=True)
    clock = _Stopwatch()
    X = data["points"]
    prescribed = np.zeros(X.shape[0], bool)
    prescribed[data["prescribed"]] = True
    value = np.zeros_like(X)
    value[data["prescribed"]] = data["values"]
    with clock("assemble"):
        corners, points, tets = _corner_mesh(data)
        mesh = Mesh.from_data("face", points, None, [tets], [np.zeros(tets.shape[0], np.int32)], ["3_4"])
        domain = FEDomain("domain", mesh)
        omega = domain.create_region("Omega", "all")
        field = Field.from_args("displacement", np.float64, "vector", omega, approx_order=2)
        # the prescribed vertices, and the edges whose mid-node the toolkit prescribes (an edge
        # region keeps only the vertices of its edges: the vertices are a region of their own)
        cmesh = domain.cmesh
        cmesh.setup_connectivity(1, 0)
        edges = cmesh.get_conn(1, 0).indices.reshape(-1, 2)
        vertices = np.flatnonzero(prescribed[corners])
        bone = {"vertex": Region.from_vertices(vertices, domain, "bone_vertices", kind="vertex"),
                "edge": Region.from_vertices(vertices, domain, "bone_edges", kind="edge")}
        bone["edge"].edges = np.flatnonzero(prescribed[_edge_midnodes(data, edges)])
        for region in bone.values():
            region.finalize()
        u = FieldVariable("u", "unknown", field)
        v = FieldVariable("v", "test", field, primary_var_name="u")
        m = Material("m", D=stiffness_from_youngpoisson(3, E, nu))
        term = Term.new("dw_lin_elastic(m.D, v, u)", Integral("i", order=2), omega, m=m, v=v, u=u)
        given = X[data["prescribed"]]  # no two prescribed nodes share a position

        def bone_motion(ts, coors, **kwargs):
            return data["values"][_nearest(given, coors)]

        motion = Function("bone_motion", bone_motion)
        pb = Problem("face", equations=Equations([Equation("balance", term)]))
        pb.set_bcs(ebcs=Conditions([EssentialBC(f"bone_{k}", r, {"u.all": motion}) for k, r in bone.items()]))
        pb.time_update()
    # the linear solver's calls and, inside them, its factorization or hierarchy; the rest of
    # Problem.solve (matrix, residuals, boundary values) is its assembly
    lin = _Stopwatch()
    base = ScipyDirect if method == "direct" else PyAMGSolver

    class Timed(base):
        def __call__(self, *args, **kwargs):
            with lin("call"):
                return super().__call__(*args, **kwargs)

    if method == "direct":
        ls = Timed({"use_presolve": True, "use_mtx_digest": False})
        ls.presolve = _timed(ls.presolve, lin, "setup")
    else:
        B = _rigid_modes(field.get_coor())[pb.get_variables()["u"].eq_map.eqi]
        ls = Timed({"method": "smoothed_aggregation_solver", "accel": "cg", "eps_r": RTOL, "i_max": 2000,
                    "method:B": B})
        ls.solver = _timed(ls.solver, lin, "setup")
    pb.set_solver(Newton({"i_max": 1, "eps_a": 1e-30, "eps_r": 1e-6}, lin_solver=ls, status=IndexedStruct()))
    whole = _Stopwatch()
    with whole("solve"):
        pb.solve(save_results=False)
    clock.add("assemble", whole.seconds["solve"] - lin.seconds["call"], whole.wall["solve"] - lin.wall["call"])
    clock.add("setup", lin.seconds["setup"], lin.wall["setup"])
    clock.add("solve", lin.seconds["call"] - lin.seconds["setup"], lin.wall["call"] - lin.wall["setup"])
    info = {"iterations": int(getattr(ls, "iter", 0))} if method != "direct" else {}
    U = np.asarray(pb.get_variables()["u"]()).reshape(-1, 3)
    n_free = pb.get_variables()["u"].eq_map.n_eq
    nodes = _scalar_nodes(data, field.econn, field.get_coor())
    return U[nodes], {"clock": clock, "dofs": int(n_free), **info}


ADAPTERS = {"toolkit": _toolkit, "scikit-fem": _scikit_fem, "ngsolve": _ngsolve, "sfepy": _sfepy}


def _u_path(problem: str, size: str, code: str, method: str) -> Path:
    return CACHE / f"u_{problem}_{size}_{code}_{method}.npy"


def worker(problem: str, size: str, code: str, method: str, E: float, nu: float) -> dict:
    """One run in this process: the row (without ``rel_diff``), the displacement saved for the parent."""
    import importlib.metadata

    data = problem_arrays(size)
    U, info = ADAPTERS[code](data, method, problem, E, nu)
    np.save(_u_path(problem, size, code, method), U)
    s, wall = info["clock"].seconds, info["clock"].wall
    return {"version": importlib.metadata.version(DISTRIBUTION[code]), "nodes": data["points"].shape[0],
            "dofs": int(info["dofs"]), "assemble_s": s.get("assemble"), "setup_s": s.get("setup"),
            "solve_s": s.get("solve"), "total_s": sum(s.values()), "wall_s": sum(wall.values()),
            "load_1min": os.getloadavg()[0],
            "iterations": info.get("iterations"),
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "status": "ok"}


# ------------------------------------------------------------------ the runs
def _rss_mib(pid: int) -> float:
    """Resident memory of process ``pid`` and its children, MiB (0 when gone)."""
    total = 0.0
    for p in [pid, *_children(pid)]:
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) / 1024
        except OSError:
            pass
    return total


def _children(pid: int) -> list[int]:
    try:
        kids = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    except OSError:
        return []
    return [int(k) for k in kids]


def _run(problem: str, size: str, code: str, method: str, E: float, nu: float, timeout_s: float,
         memory_mib: float) -> dict:
    """:func:`worker` in a fresh single-threaded process, stopped at ``timeout_s`` or ``memory_mib``."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
           "TOOLKIT_NUM_THREADS": "1"}
    cmd = [sys.executable, __file__, "--worker", problem, size, code, method, repr(E), repr(nu)]
    t0 = time.perf_counter()
    out, err = tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")  # no pipe to fill up
    proc = subprocess.Popen(cmd, stdout=out, stderr=err, text=True, env=env, start_new_session=True)
    peak, reason = 0.0, None
    try:
        while proc.poll() is None:
            time.sleep(0.5)
            peak = max(peak, _rss_mib(proc.pid))
            if time.perf_counter() - t0 > timeout_s:
                reason = f"failed: timeout after {timeout_s / 60:g} min"
            elif peak > memory_mib:
                reason = f"failed: resident memory above {memory_mib / 1024:g} GiB"
            if reason:
                break
    finally:  # also when this process is interrupted or terminated
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    if reason:
        return {"status": reason, "wall_s": time.perf_counter() - t0, "peak_rss_mib": peak}
    out.seek(0)
    err.seek(0)
    lines, errors = out.read().strip().splitlines(), err.read().strip()
    if proc.returncode != 0 or not lines:
        last = errors.splitlines()[-1] if errors else f"exit code {proc.returncode}"
        return {"status": f"failed: {last[:200]}", "peak_rss_mib": peak}
    return json.loads(lines[-1])


def rel_diff(problem: str, size: str, code: str, method: str) -> float | None:
    """``||u - u_toolkit|| / ||u_toolkit||`` over the nodes, None without both displacements."""
    ref, this = _u_path(problem, size, "toolkit", "amg"), _u_path(problem, size, code, method)
    if not (ref.exists() and this.exists()):
        return None
    u_ref = np.load(ref)
    return float(np.linalg.norm(np.load(this) - u_ref) / np.linalg.norm(u_ref))


def _free_dofs_estimate(size: str) -> int:
    """Free dofs of ``size``'s problem, from the cached mesh."""
    data = problem_arrays(size)
    return 3 * (data["points"].shape[0] - data["prescribed"].size)


KEY = ["problem", "size", "code", "method"]
COLUMNS = [*KEY, "version", "nodes", "dofs", "assemble_s", "setup_s", "solve_s", "total_s", "wall_s", "load_1min",
           "iterations", "peak_rss_mib", "rel_diff", "status"]


def main(argv=None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", default=list(SIZES), choices=SIZES,
                    help="meshes: the phantom at 7 or 3.5 mm, the head CT at 3 mm")
    ap.add_argument("--codes", nargs="+", default=list(CODES), choices=CODES)
    ap.add_argument("--problems", nargs="+", default=list(PROBLEMS), choices=PROBLEMS)
    ap.add_argument("--neo-hookean-sizes", nargs="+", default=["7"], choices=SIZES,
                    help="the sizes of the neo-hookean problem")
    ap.add_argument("--timeout", type=float, default=30.0, help="minutes per run")
    ap.add_argument("--memory", type=float, default=15.0, help="GiB of resident memory per run")
    ap.add_argument("--superlu-max-dofs", type=int, default=200_000,
                    help="the SuperLU runs are skipped above this many free dofs")
    ap.add_argument("--fresh", action="store_true",
                    help="run the selected rows (--sizes, --codes, --problems) again if the table holds them")
    ap.add_argument("--retry-failed", action="store_true", help="run again the rows whose status is not ok")
    ap.add_argument("--out", type=Path, default=RESULTS / "peers.csv")
    ap.add_argument("--worker", nargs=6, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        problem, size, code, method, E, nu = args.worker
        print(json.dumps(worker(problem, size, code, method, float(E), float(nu))), flush=True)
        return None

    from toolkit.common.fem.materials import LinearElastic

    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # a terminated run stops its worker too
    tissue = LinearElastic()
    if tissue.nu != 0.47:
        tissue = LinearElastic(tissue.E, 0.47)
    old = pd.read_csv(args.out, dtype={"size": str}).to_dict("records") if args.out.exists() else []

    def key(row: dict) -> tuple:
        return tuple(str(row[k]) for k in KEY)

    done = {key(r) for r in old if not args.retry_failed or r["status"] == "ok"}
    selected = [(p, s, c, m) for p in args.problems for s in args.sizes for c, m in RUNS[p] if c in args.codes
                and (p == "linear" or s in args.neo_hookean_sizes)]
    todo = [k for k in selected if args.fresh or k not in done]
    rows = [r for r in old if key(r) not in set(todo)]  # the table's other rows stay
    for problem, size, code, method in todo:
        problem_arrays(size)  # mesh once, here, not in a timed run
        row = {"problem": problem, "size": size, "code": code, "method": method}
        dofs = _free_dofs_estimate(size)
        if (code, method) in SUPERLU and dofs > args.superlu_max_dofs:
            row.update(dofs=dofs, status=f"skipped: SuperLU above {args.superlu_max_dofs} dofs")
        else:
            print(f"{problem} {size} {code} {method} ...", flush=True)
            row.update(_run(problem, size, code, method, tissue.E, tissue.nu, args.timeout * 60,
                            args.memory * 1024))
        rows.append(row)
        print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
        table = pd.DataFrame(rows).reindex(columns=COLUMNS)
        write_result(args.out, table, sidecar=False)
    for row in rows:
        if row.get("status") == "ok":
            row["rel_diff"] = rel_diff(row["problem"], str(row["size"]), row["code"], row["method"])
    order = {k: i for i, k in enumerate((p, s, c, m) for p in PROBLEMS for s in SIZES for c, m in RUNS[p])}
    rows.sort(key=lambda r: order.get((r["problem"], str(r["size"]), r["code"], r["method"]), len(order)))
    table = pd.DataFrame(rows).reindex(columns=COLUMNS)
    resumed = bool(read_sidecar(args.out)) and len(rows) > len(todo)
    write_result(args.out, table, argv=argv, resumed=resumed,
                 extra={"E_mpa": tissue.E, "nu": tissue.nu, "rtol": RTOL, "timeout_min": args.timeout,
                        "memory_gib": args.memory, "superlu_max_dofs": args.superlu_max_dofs})
    with pd.option_context("display.width", 250, "display.max_columns", 30, "display.float_format", "{:.4g}".format):
        print(table.to_string(index=False))
    print(f"wrote {args.out}")
    return table


if __name__ == "__main__":
    main()
