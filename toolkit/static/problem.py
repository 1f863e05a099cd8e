"""Static finite-element solves of the face (any mix of hex8, wedge6, tet4, tet10 blocks).

:class:`StaticProblem` holds one configuration of a mesh with its materials and
solves it under :class:`~toolkit.static.constraints.Constraints`:

- linear materials (isotropic, transversely isotropic): one SPD solve;
- Neo-Hookean: Newton's method with the consistent tangent, a backtracking line
  search on the total energy (which also refuses steps that invert an element),
  and automatic load sub-stepping when Newton does not converge.

:func:`solve_with_lip_contact` adds the lip-sliding paper's lip sliding: master-slave pairs across
the mouth slit may not interpenetrate craniocaudally but slide freely otherwise,
found by an active-set iteration (release pairs in tension, add pairs that
penetrate).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np
import scipy.sparse as sp

from toolkit.common.errors import ConvergenceError
from toolkit.common.fem.assembly import SparsePattern
from toolkit.common.fem.coarse import corner_interpolation, reduced_coarse_space
from toolkit.common.fem.newton import ArmijoOnMerit, InadmissibleState, LoadSteps, NewtonFailed, Trial, newton
from toolkit.common.fem.solvers import LinearSolver, SolveInfo, estimate_factor_entries, rigid_body_modes
from toolkit.common.meshes.mesh import Mesh
from toolkit.static.constraints import Constraints
from toolkit.static.stiffness import (
    MaterialAssignment,
    kinematics,
    linear_stiffness,
    neo_hookean_energy,
    neo_hookean_system,
)

__all__ = ["StaticProblem", "Solution", "ConvergenceError", "solve_with_lip_contact", "ContactResult"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Solution:
    """Result of one constrained solve.

    Attributes
    ----------
    displacement : (n, 3) mm, from the problem's configuration
    residual : (3n,) N — ``K u`` (linear) or internal force (Neo-Hookean): the constraint
        (reaction) forces, zero at free dofs up to the solver tolerance
    solves : list of SolveInfo — one per linear solve
    newton_iterations : int (0 for linear)
    """

    displacement: np.ndarray
    residual: np.ndarray
    solves: list = field(default_factory=list)
    newton_iterations: int = 0


class StaticProblem:
    """A mesh configuration, its materials and a linear solver, ready to solve.

    Parameters
    ----------
    mesh : Mesh with one or several volume blocks (hex8 and wedge6 with mean dilatation;
        tet4, tet10); element sets of ``materials`` may span blocks
    materials : MaterialAssignment (all linear, or all Neo-Hookean)
    solver : ``auto``, ``superlu``, ``pardiso``, ``amg`` or ``cholmod`` (see :mod:`toolkit.common.fem.solvers`)
    pattern : a SparsePattern of the same topology to reuse
    rtol : Newton stops when the free-dof residual falls below ``rtol`` times the
        largest nodal force (reactions included)
    orderings : system size -> fill-reducing ordering, shared with the problems of the other
        steps on the same mesh (:class:`~toolkit.common.fem.solvers.LinearSolver`)
    """

    def __init__(self, mesh: Mesh, materials: MaterialAssignment, solver: str = "auto",
                 pattern: SparsePattern | None = None, rtol: float = 1e-8, orderings: dict | None = None):
        self.rtol = rtol
        self.mesh = mesh
        self.materials = materials
        self.solver = solver
        self.kin = kinematics(mesh)
        bad = self.kin.inverted_elements()
        if bad.size:
            raise ConvergenceError(f"{bad.size} elements have a non-positive Jacobian at a Gauss point "
                                   f"(first: {bad[:5].tolist()}); the configuration is inverted")
        self.pattern = pattern or SparsePattern(self.kin.conns, mesh.n_points)
        self.linear = materials.is_linear
        self.groups = materials.groups(mesh)
        self._K = None
        self._modes = rigid_body_modes(mesh.points)
        entries = estimate_factor_entries(self.pattern.node_graph()) if solver == "auto" else None
        # a linear material's systems differ only by their reduction (lip pairs tied, the mucosa
        # constrained), for which a stored AMG hierarchy preconditions worse than a new one
        self.linear_solver = LinearSolver(solver, factor_entries=entries, orderings=orderings,
                                          reuse_hierarchy=not self.linear)
        # a quadratic mesh's corner nodes: the first coarsening of AMG (p-multigrid)
        self._corners = corner_interpolation(mesh.cells, mesh.n_points) if solver in ("amg", "auto") else None
        # force of a unit strain on a typical element face, N: the yardstick for round-off
        moduli = [getattr(m, "E", None) or getattr(m, "E_fibre", 0.0) for _, m in self.groups]
        self.force_scale = max(moduli) * float(np.mean(self.kin.volume)) ** (2.0 / 3.0)

    @property
    def stiffness(self):
        """Small-strain stiffness (N/mm), assembled once (linear materials)."""
        if self._K is None:
            D, lam = self.materials.voigt(self.mesh)
            self._K = linear_stiffness(self.kin, D, lam, self.pattern)
        return self._K

    def solve_reduced(self, T, A, b, x0=None) -> tuple[np.ndarray, SolveInfo]:
        """Solve ``A v = b`` for a system reduced by ``T`` ((3n, m) sparse: ``u = T v``; ``A``
        (m, m) sparse, usually ``T^T K T``; ``b`` (m,)) with this problem's solver, which
        keeps its factorization or AMG hierarchy for the next system of the same matrix; the
        rigid-body modes and a quadratic mesh's corner nodes are reduced by ``T`` for AMG."""
        # columns no constraint leaves free (tie slaves kept so that every system of a step
        # has the same size, see Constraints.reduction) get a unit equation: their value is 0
        d = A.diagonal()
        idle = d == 0
        if idle.any():
            A = A + sp.diags(np.where(idle, float(d[~idle].mean()) if (~idle).any() else 1.0, 0.0))
        modes = T.T @ self._modes if self.solver in ("amg", "auto") else None
        coarse = None if self._corners is None else partial(reduced_coarse_space, self._corners, T, self.mesh.points)
        return self.linear_solver.solve(A, b, near_nullspace=modes, x0=x0, coarse_space=coarse)

    def solve(self, constraints: Constraints, u_start: np.ndarray | None = None) -> Solution:
        """Equilibrium under ``constraints``; ``u_start (n, 3)`` starts Newton."""
        T, u0 = constraints.reduction()
        if self.linear:
            K = self.stiffness
            A = reduced_matrix(K, T)
            v, info = self.solve_reduced(T, A, -(T.T @ (K @ u0)), x0=self._reduced_guess(T, u0, u_start))
            u = T @ v + u0
            return Solution(u.reshape(-1, 3), K @ u, [info], 0)
        return self._newton(T, u0, u_start)

    @staticmethod
    def _reduced_guess(T, u0, u_start) -> np.ndarray | None:
        """The reduced variables nearest ``u_start`` (n, 3) mm: its projection onto ``T``'s
        columns, each scaled by its squared norm (None without a start). An iterative solve of a
        lip-contact iteration starts there, from the iteration before it."""
        if u_start is None:
            return None
        scale = np.asarray(T.multiply(T).sum(axis=0)).ravel()
        return (T.T @ (np.asarray(u_start, dtype=float).reshape(-1) - u0)) / np.maximum(scale, 1e-300)

    # ----------------------------------------------------------------- Newton
    def _newton(self, T, u0, u_start, max_iter: int = 25, max_substeps: int = 6) -> Solution:
        """Newton from ``u_start`` to the prescribed ``u0``, cutting the prescribed increment
        in half (load sub-steps, at most ``max_substeps`` halvings deep) when a step does not
        converge."""
        n = self.mesh.n_points
        u_prev = np.zeros(3 * n) if u_start is None else np.asarray(u_start, float).reshape(-1)
        # the previous state's constrained part; sub-steps move it linearly to u0
        start_u0 = u_prev - T @ (T.T @ (u_prev - u0))
        solves, total_iter = [], 0
        steps = LoadSteps([1.0], max_step=1.0, min_step=0.5 ** max_substeps)
        while not steps.done:
            _, target = steps.next()
            u0_k = start_u0 + target * (u0 - start_u0)
            try:
                v, iters, infos = self._newton_fixed(T, u0_k, u_prev, max_iter)
            except NewtonFailed as exc:
                if not steps.cut():
                    raise ConvergenceError(str(exc), exc.iteration, exc.residual) from None
                log.info("Newton failed; sub-stepping the prescribed displacements (step %.3g)", steps.step)
                continue
            solves += infos
            total_iter += iters
            u_prev = T @ v + u0_k
            steps.accept(iters)
        f, _ = neo_hookean_system(self.kin, u_prev.reshape(-1, 3), self.groups, self.pattern, tangent=False)
        return Solution(u_prev.reshape(-1, 3), f, solves, total_iter)

    def _newton_fixed(self, T, u0, u_prev, max_iter):
        """Newton (:func:`~toolkit.common.fem.newton.newton`, Armijo line search on the total
        energy) with fixed prescribed part ``u0``, starting from the tangent predictor at the
        previous equilibrium ``u_prev`` (the linearised response to the new ``u0``); returns
        the free unknowns, the iterations (the predictor counts as one) and the solves."""
        infos = []

        def evaluate(v):
            # forces and tangent in one pass: the material returns dP/dF with P anyway, and a
            # trial is usually accepted, so its tangent serves the next correction (the tangent
            # adds less to the pass than a separate pass for it would cost)
            u = T @ v + u0
            E = neo_hookean_energy(self.kin, u.reshape(-1, 3), self.groups)
            if not np.isfinite(E):
                raise InadmissibleState("an element is inverted")
            f, K = neo_hookean_system(self.kin, u.reshape(-1, 3), self.groups, self.pattern)
            return Trial(v, T.T @ f, E, (u, f, K))

        def correction(trial):
            dv, info = self.solve_reduced(T, reduced_matrix(trial.data[2], T), -trial.residual)
            infos.append(info)
            return dv

        def converged(trial):
            return trial.norm <= self.rtol * max(np.abs(trial.data[1]).max(), 1e-30)

        def negligible(trial, dv):
            # a stress-free equilibrium has only round-off forces, which no relative force test
            # can beat: stop when the Newton correction itself is negligible
            return np.abs(dv).max() <= 1e-10 * max(np.abs(trial.data[0]).max(), 1e-3)

        def stalled(trial):  # the energy cannot resolve the step: the round-off limit
            return trial.norm <= 1e-5 * max(np.abs(trial.data[1]).max(), self.force_scale)

        f, K = neo_hookean_system(self.kin, u_prev.reshape(-1, 3), self.groups, self.pattern)
        A = reduced_matrix(K, T)
        v, info = self.solve_reduced(T, A, -(T.T @ (f + K @ (u0 - u_prev))))
        infos.append(info)
        try:
            start = evaluate(v)
        except InadmissibleState:  # the predictor inverts elements: fall back to the previous free state
            try:
                start = evaluate(T.T @ (u_prev - u0))
            except InadmissibleState:
                raise NewtonFailed("the prescribed displacements invert elements; a smaller step is needed", 0,
                                   None) from None
        search = ArmijoOnMerit(merit_resolution=1e-12 * self.force_scale)
        result = newton(start, evaluate, correction, converged, negligible, search, max_iter, stalled)
        return result.trial.x, result.iterations + 1, infos


def reduced_matrix(K: sp.spmatrix, T: sp.spmatrix) -> sp.csr_matrix:
    """``T^T K T`` in CSR, ``K`` (N, N) CSR and ``T`` (N, m), without converting ``K`` to another
    format (``T.T @ K`` would convert it to CSC, a costly copy of a large face's matrix)."""
    T = sp.csr_matrix(T)
    return (T.T.tocsr() @ (sp.csr_matrix(K) @ T)).tocsr()


@dataclass(frozen=True, eq=False)
class ContactResult:
    """A solve with lip contact.

    Attributes
    ----------
    solution : Solution
    active : (k,) bool — candidate pairs tied at the end
    gaps : (k,) mm — craniocaudal gap (upper minus lower) of every candidate pair after the solve
    iterations : active-set iterations
    """

    solution: Solution
    active: np.ndarray
    gaps: np.ndarray
    iterations: int

    @property
    def max_penetration(self) -> float:
        """Largest craniocaudal interpenetration over the candidate pairs, mm (0 if none)."""
        return float(max(0.0, -self.gaps.min())) if self.gaps.size else 0.0


def solve_with_lip_contact(problem: StaticProblem, constraints: Constraints, upper: np.ndarray,
                           lower: np.ndarray, threshold: float = 0.2, axis: int = 2,
                           max_iter: int = 20, tol: float = 1e-6, u_start=None,
                           active: np.ndarray | None = None) -> ContactResult:
    """Solve with master-slave lip pairs (upper = slave, lower = master) in an active set.

    Pairs start active when their craniocaudal gap is within ``threshold`` mm (the
    lip-sliding paper's collision detection), or as ``active`` ((k,) bool, the set a solve
    before this one settled on) says; a pair is released when its tie pulls (tension) and
    (re)activated when its lips would interpenetrate by more than ``tol`` mm. Each iteration's
    solve starts from the one before it (``u_start`` (n, 3) mm for the first).
    """
    x = problem.mesh.points
    upper, lower = np.asarray(upper, np.int64), np.asarray(lower, np.int64)
    gap0 = x[upper, axis] - x[lower, axis]
    if active is None:
        active = gap0 <= threshold
    elif np.shape(active) != gap0.shape:
        raise ValueError(f"active has shape {np.shape(active)}; expected ({gap0.size},), one per lip pair")
    active = np.asarray(active, dtype=bool)
    history = set()
    sol = None
    solves, newton = [], 0
    for it in range(1, max_iter + 1):
        c = replace(constraints, tie_slaves=upper[active], tie_masters=lower[active], tie_offsets=-gap0[active],
                    tie_axis=axis)
        sol = problem.solve(c, u_start=u_start if sol is None else sol.displacement)
        solves += sol.solves
        newton += sol.newton_iterations
        u = sol.displacement
        gaps = gap0 + u[upper, axis] - u[lower, axis]
        force = c.forces(sol.residual)["tie"]
        fscale = max(np.abs(sol.residual).max(), 1e-30)
        release = np.zeros_like(active)
        release[np.flatnonzero(active)] = force < -1e-8 * fscale
        add = ~active & (gaps < -tol)
        if not release.any() and not add.any():
            return ContactResult(replace(sol, solves=solves, newton_iterations=newton), active, gaps, it)
        new_active = (active & ~release) | add
        key = new_active.tobytes()
        if key in history:  # cycling: keep the pairs that penetrate tied
            new_active = active | add
        history.add(key)
        active = new_active
    raise ConvergenceError(f"lip contact active set did not settle in {max_iter} iterations", max_iter)
