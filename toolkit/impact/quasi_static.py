"""Quasi-static impact: equilibrium at every load step, Newton's method, no inertia.

Why: the impact paper's ball moves at 20-50 mm/s, about 1 % of the tissue's shear-wave speed
(~2,200 mm/s), so the face is in equilibrium with the ball at every instant and inertia is
negligible (the explicit runs of ``benchmarks/impact_ladder.py`` measure the kinetic energy, even
with mass scaling, as a small share of the internal energy). Explicit central differences must
still resolve the stress waves (many stable steps for tet10 at nu = 0.49, which the ladder
counts); a quasi-static solve takes as few load steps as the nonlinearity allows.

Each load step ``t -> t + h``:

1. **Targets**: prescribed dofs take their imposed displacement (fixed 0, driven ``v t``); the
   free dofs start from the last increment scaled to ``h`` (a linear predictor).
2. **Newton** on ``r(u) = f_int(u) - f_contact(u) = 0`` over the free dofs. ``f_int`` comes from
   every body's material update from the last converged state (finite-strain J2 with its
   return mapping), the tangent from the material's consistent ``dP/dF``
   (:meth:`~toolkit.impact.plasticity.J2Plasticity.tangent`, in closed form) assembled by
   :class:`~toolkit.common.fem.assembly.SparsePattern`, plus the penalty contact's: ``k n n^T``
   normal, ``k_t (I - n n^T)`` for sticking friction and the radial return's consistent
   (unsymmetric) tangent for slipping friction, shared with the master triangle's corners by
   the barycentric weights for a deformable ball. A tangent with slipping contact is solved by
   GMRES (:class:`~toolkit.common.fem.solvers.LinearSolver` with ``symmetric=False``),
   preconditioned by the factorization of a tangent a few iterations old whose contact part is
   brought up to date exactly (the contact tangent is the solver's ``local`` term:
   :mod:`toolkit.common.fem.woodbury`). The consistent tangent keeps Newton fast
   once the skin slides under the ball (on the coarse face with the deformable ball it needs
   far fewer iterations than the symmetric secant ``k_t |t| / |t_trial| (I - n n^T)``). The
   iteration is the shared
   :func:`toolkit.common.fem.newton.newton` with the
   :class:`~toolkit.common.fem.newton.SecantOnDirection` line search (the step along the
   correction where ``r . dx`` vanishes, which stops a correction where a contact engages).
   A slave whose slip direction reverses between two corrections is linearized on
   the stick piece of the Coulomb law (:meth:`StepContact.linearize`). The contact laws are
   those of the explicit path (:mod:`toolkit.impact.contact`, same penalties, same Coulomb return mapping);
   the friction state is restored before every trial and kept when the step converges.
3. **Converged** when the free-dof residual is below ``tolerance`` times the force scale (the
   reactions at the prescribed dofs plus the contact force), or when a Newton correction moves
   no dof by more than ``displacement_tolerance`` mm (the corrected state is taken). The
   displacement test matters before and at first touch, when the forces are too small for a
   relative force test. It looks at a solved correction, not at the residual over the tangent's
   diagonal: a stiff ball translating before contact has a large diagonal, so a residual of
   1e-3 N passes that cheaper test while its net force, times the ball's travel, books
   spurious external work (a large energy balance error in the first frame of a coarse run,
   where the solved test leaves a small one).
4. **Adaptive steps**: a step that does not converge in ``max_iterations``, inverts an element
   or breaks the material update is cut in half; one that converges in at most
   ``easy_iterations`` lets the next grow by ``growth`` up to the initial step. Steps end
   exactly at the output frames (:class:`toolkit.common.fem.newton.LoadSteps`).

Energies are booked as in the explicit path (internal work by the trapezoidal rule, plastic
dissipation, contact elastic energy, friction dissipation; external work done by the
reactions at the prescribed dofs and by a rigid ball's imposed motion), with zero kinetic
energy; their balance error measures the load-step size.

Units: mm, s, tonne, N, MPa, mJ.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

from toolkit.common.errors import ConvergenceError
from toolkit.common.fem.assembly import SparsePattern, add_local
from toolkit.common.fem.kinematics import deformation_gradient
from toolkit.common.fem.newton import (
    InadmissibleState,
    LoadSteps,
    NewtonFailed,
    ResidualDecrease,
    SecantOnDirection,
    Trial,
    newton,
)
from toolkit.common.fem.solvers import (
    REUSED_DIRECT_MAX_ENTRIES,
    LinearSolver,
    SolverError,
    estimate_factor_entries,
    rigid_body_modes,
)
from toolkit.impact.contact import RigidSphereContact
from toolkit.impact.explicit import (
    ContactResponse,
    ExplicitModel,
    _frame,
    _internal_forces,
    _Inverted,
    _prescribed,
    _WorkLedger,
)

__all__ = ["QuasiStaticOptions", "StepContact", "ContactLinearization", "ConvergenceError", "run_quasistatic"]

log = logging.getLogger(__name__)

#: the loosest relative residual of a correction's linear solve (QuasiStaticOptions.linear_target)
MAX_LINEAR_TOLERANCE = 0.1

#: line searches of the Newton iterations (:mod:`toolkit.common.fem.newton`)
LINE_SEARCHES = {"secant": SecantOnDirection, "residual": ResidualDecrease}


@dataclass(frozen=True)
class QuasiStaticOptions:
    """Load stepping and Newton controls of :func:`run_quasistatic`. The defaults' reasons are
    measured on the paper face with the deformable ball, 1.8 s at 30 mm/s (docs/solvers.md).

    Attributes
    ----------
    steps : load steps over the duration at the start (the largest step is ``duration / steps``);
        default 36
    tolerance : relative residual (to the reactions plus the contact force) of a converged step;
        default 3e-3
    displacement_tolerance : mm; a Newton correction moving no dof by more than this also ends the
        iterations (with the corrected state); default 1e-4
    max_iterations : Newton iterations before a step is cut; default 25
    easy_iterations : a step converged within this many lets the next grow by ``growth``; default 4
    growth : step growth factor after an easy step (> 1); default 1.5
    min_step : s, the smallest step before :class:`ConvergenceError`; default 1e-5
    solver : linear solver (:data:`toolkit.common.fem.solvers.METHODS`); ``auto`` factorizes up to
        :data:`~toolkit.common.fem.solvers.REUSED_DIRECT_MAX_ENTRIES` (the paper face included),
        with MKL PARDISO where the ``pardiso`` extra is installed, else SuperLU
    linear_tolerance : relative residual of the Krylov solves (an inexact Newton); default 1e-3:
        GMRES leaves the soft modes unsolved at 1e-2 (on the coarse face Newton then needs many
        more iterations; a tighter tolerance saves none)
    linear_target : share of the Newton target left to a correction's linear solve, which stops at
        ``max(linear_tolerance, min(0.1, linear_target * tolerance * scale / |r|))`` (an
        Eisenstat-Walker forcing term); 0: always ``linear_tolerance``; default 0.1: fewer GMRES
        iterations than 0
    line_search : ``"secant"`` (:class:`~toolkit.common.fem.newton.SecantOnDirection`, the zero of
        ``r . dx`` along the correction; default) or ``"residual"``
        (:class:`~toolkit.common.fem.newton.ResidualDecrease`), which cycles at the paper face's
        first touch
    single_precision_factor : float32 factors, used as the Krylov solver's preconditioner
        (``LinearSolver``'s ``single_precision``); default True: less factorization time, the
        same Newton iterations
    factorize_ahead : factorize the tangent on a worker thread and precondition with it this many
        Newton iterations later (``LinearSolver``'s ``factorize_ahead``; 0: only when a reuse
        fails); default 2: the tangent changes over the whole face from one load step to the next
    factorize_ahead_above : no factorization ahead after a solve that needed at most this many
        Krylov iterations (its factor is still nearly exact); default 2
    stick_on_reversal : a slave whose slip direction reversed since the previous correction is
        linearized on the Coulomb law's stick piece (:meth:`StepContact.linearize`); default True:
        fewer Newton iterations
    symmetric_factor : factorize the symmetric part of each tangent by PARDISO's LDL^T, friction's
        skew part taken by the Woodbury correction (``LinearSolver``'s ``symmetric_factor``);
        default True: a faster refactorization than LU's
    correction_threshold : the contact correction leaves dofs whose change is below this fraction
        of the largest to GMRES (:class:`~toolkit.common.fem.woodbury.LocalCorrection`'s
        ``threshold``); default 0.01: fewer GMRES iterations than 0.05 with the symmetric factor
    """

    steps: int = 36
    tolerance: float = 3e-3
    displacement_tolerance: float = 1e-4
    max_iterations: int = 25
    easy_iterations: int = 4
    growth: float = 1.5
    min_step: float = 1e-5
    solver: str = "auto"
    linear_tolerance: float = 1e-3
    linear_target: float = 0.1
    line_search: str = "secant"
    single_precision_factor: bool = True
    factorize_ahead: int = 2
    factorize_ahead_above: int = 2
    stick_on_reversal: bool = True
    symmetric_factor: bool = True
    correction_threshold: float = 0.01

    def __post_init__(self):
        if int(self.steps) < 1 or not 0 < self.tolerance < 1 or int(self.max_iterations) < 1:
            raise ValueError(f"quasi-static options: steps {self.steps} must be >= 1, tolerance {self.tolerance} in "
                             f"(0, 1), max_iterations {self.max_iterations} >= 1")
        if self.line_search not in LINE_SEARCHES:
            raise ValueError(f"quasi-static options: line_search {self.line_search!r} must be one of "
                             f"{sorted(LINE_SEARCHES)}")
        if int(self.factorize_ahead) < 0 or int(self.factorize_ahead_above) < 0:
            raise ValueError(f"quasi-static options: factorize_ahead {self.factorize_ahead} and factorize_ahead_above "
                             f"{self.factorize_ahead_above} must be >= 0")
        if not 0 < self.linear_tolerance < 1:
            raise ValueError(f"quasi-static options: linear_tolerance {self.linear_tolerance} must lie in (0, 1)")
        if not 0 <= self.linear_target < 1:
            raise ValueError(f"quasi-static options: linear_target {self.linear_target} must lie in [0, 1)")
        if not 0 <= self.correction_threshold < 1:
            raise ValueError(f"quasi-static options: correction_threshold {self.correction_threshold} must lie in "
                             "[0, 1)")
        if not self.growth > 1 or not self.min_step > 0:
            raise ValueError(f"quasi-static options: growth {self.growth} must be > 1 and min_step {self.min_step} "
                             "s > 0")


@dataclass(frozen=True, eq=False)
class ContactLinearization:
    """The contact's part of one Newton correction (:meth:`StepContact.linearize`).

    Attributes
    ----------
    tangent : (3n, 3n) N/mm, minus the derivative of the contact forces
    force_shift : (3n,) N, the change of the contact forces when the reversed slaves take their
        trial (stick) friction force; the correction solves ``K dx = -(r - force_shift)``
    directions : (n_slave, 3) unit slip direction of every slipping slave (zero elsewhere), the
        ``previous`` of the next correction
    reversed : slaves linearized on the stick piece
    """

    tangent: sp.csr_matrix
    force_shift: np.ndarray
    directions: np.ndarray
    reversed: int


class StepContact:
    """Penalty contact evaluated at trial states of a load step, with its tangent.

    ``pair`` is a :class:`~toolkit.impact.contact.RigidSphereContact` (then ``centre0`` (3,) mm
    and ``velocity`` (3,) mm/s move the sphere) or a
    :class:`~toolkit.impact.contact.SurfaceContact` on the model's nodes. Every
    :meth:`evaluate` starts from the friction state of the last :meth:`commit`.
    """

    def __init__(self, pair, n_nodes: int, centre0=None, velocity=None):
        self.pair, self.n_nodes = pair, int(n_nodes)
        self.rigid = isinstance(pair, RigidSphereContact)
        if self.rigid and (centre0 is None or velocity is None):
            raise ValueError("a rigid sphere contact needs the sphere's centre0 (mm) and velocity (mm/s)")
        self.centre0 = None if centre0 is None else np.asarray(centre0, float)
        self.velocity = None if velocity is None else np.asarray(velocity, float)
        self._committed = pair.tangential_state
        self._force_on_body, self._centre = np.zeros(3), self.centre0
        self._pending = None

    def evaluate(self, x: np.ndarray, x_start: np.ndarray, t: float, h: float) -> tuple[ContactResponse, sp.csr_matrix]:
        """Contact at positions ``x (n, 3)`` mm at time ``t`` s, the step having started at
        ``x_start`` a step ``h`` s earlier; returns the response and the tangent
        ``(3n, 3n)`` N/mm (minus the derivative of the contact forces)."""
        response, state = self.respond(x, x_start, t, h)
        return response, self._tangent(state)

    def respond(self, x: np.ndarray, x_start: np.ndarray, t: float, h: float):
        """:meth:`evaluate` without the tangent: the response and the pair's
        :class:`~toolkit.impact.contact.ContactStep` (for :meth:`linearize`)."""
        pair = self.pair
        pair.restore(self._committed)
        v = (x - x_start) / h  # the step's mean velocity: v h is the step's displacement increment
        if self.rigid:
            centre = self.centre0 + self.velocity * t
            res = pair.step(x[pair.slaves], v[pair.slaves], centre, self.velocity, h)
            forces = np.zeros_like(x)
            forces[pair.slaves] = res.force
            on_body = res.force.sum(axis=0)
            work = float(0.5 * (on_body + self._force_on_body) @ (centre - self._centre))
            self._pending = (on_body, centre)
        else:
            res = pair.step(x, v, h)
            forces = res.master_force.copy()
            forces[pair.slaves] += res.force
            on_body, work = res.force.sum(axis=0), 0.0
        pen = float(res.penetration.max()) if res.penetration.size else 0.0
        return ContactResponse(forces, res.elastic_energy, res.friction_dissipation, on_body, pen, work), res

    def linearize(self, state, previous: np.ndarray | None = None) -> ContactLinearization:
        """The Newton model of the contact forces at ``state`` (a :meth:`respond` result), given
        the slip directions ``previous (n_slave, 3)`` of the previous Newton correction of the
        same load step (None at the first).

        A slave that slips against the direction it slipped in at the previous correction is
        linearized on the Coulomb law's stick piece: the stick tangent ``k_t (I - n n^T)`` and its
        trial force ``t_trial = t + k_t slip m`` in place of the returned ``t``
        (``force_shift``). Why: with the stick band only ``mu f_n / k_t`` wide (~1 um on the
        paper face, where ``k_t = k_n``), a slave whose true state is stuck or barely slipping
        sees a friction force that is a step function of its position. The slipping tangent
        has no stiffness along the slip, so each correction throws the slave across the band to
        where the soft tissue alone balances the Coulomb limit, the direction reverses and the
        next correction throws it back: a slowly damped two-cycle (on the paper face with the
        deformable ball, Newton iterations spent on one skin node, the residual falling little
        per iteration). The stick piece's model lands it inside the band, where it either sticks
        or slips on consistently."""
        held = np.linalg.norm(state.tangential_force, axis=1)
        directions = np.where(state.slipping[:, None], state.tangential_force, 0.0) \
            / np.where(held > 0, held, 1.0)[:, None]
        shift = np.zeros(3 * self.n_nodes)
        reversed_ = np.zeros(directions.shape[0], dtype=bool)
        if previous is not None and self.pair.friction is not None:
            reversed_ = state.slipping & (np.einsum("ij,ij->i", directions, previous) < 0)
        if reversed_.any():
            ids = np.flatnonzero(reversed_)
            k_t = self.pair.friction.stiffness_ratio * self.pair.penalty[ids]
            delta = (k_t * state.slip[ids])[:, None] * directions[ids]  # trial minus returned force, N
            nodes, coef = self.pair.slaves[ids][:, None], np.ones((ids.size, 1))
            if not self.rigid:  # the reaction on the master triangle's corners
                nodes = np.concatenate([nodes, state.corners[ids]], axis=1)
                coef = np.concatenate([coef, -state.weights[ids]], axis=1)
            for i in range(3):
                shift[i::3] = np.bincount(nodes.ravel(), weights=(coef * delta[:, i:i + 1]).ravel(),
                                          minlength=self.n_nodes)
            state = replace(state, slipping=state.slipping & ~reversed_)
        return ContactLinearization(self._tangent(state), shift, directions, int(reversed_.sum()))

    def commit(self) -> None:
        """Keep the friction state of the last :meth:`evaluate` or :meth:`respond` (its step
        converged)."""
        self._committed = self.pair.tangential_state
        if self._pending is not None:
            self._force_on_body, self._centre = self._pending

    def _tangent(self, res) -> sp.csr_matrix:
        """``k n n^T`` per active slave, plus the Coulomb law's consistent tangent (``k_t (I - n n^T)``
        sticking; slipping, the radial return's derivative, unsymmetric) and, against the rigid
        sphere, the turning of the normal; for a surface, spread over the slave and its
        triangle's corners with weights ``(1, -w1, -w2, -w3)`` (the normal's turning with the
        triangle is left out)."""
        pair = self.pair
        active = np.flatnonzero(res.active)
        size = 3 * self.n_nodes
        if active.size == 0:
            return sp.csr_matrix((size, size))
        n = res.normal[active]
        k = pair.penalty[active]
        nn = n[:, :, None] * n[:, None, :]
        local = k[:, None, None] * nn
        if pair.friction is not None:
            # sticking: k_t (I - n n^T). Slipping: the radial return's consistent tangent
            # r k_t (I - n n^T - m m^T) + mu k m n^T, with r = |t| / |t_trial| and m = t / |t|:
            # no stiffness along the slip, and the Coulomb limit mu |f_n| following the normal
            # force (unsymmetric)
            k_t = pair.friction.stiffness_ratio * k
            held = np.linalg.norm(res.tangential_force[active], axis=1)
            slipping = res.slipping[active]
            ratio = np.divide(held, held + k_t * res.slip[active], out=np.ones_like(held), where=slipping)
            m = np.where(slipping[:, None], res.tangential_force[active], 0.0) / np.where(held > 0, held, 1.0)[:, None]
            local = local + (k_t * ratio)[:, None, None] * (np.eye(3) - nn - m[:, :, None] * m[:, None, :]) \
                + (pair.friction.mu * k)[:, None, None] * m[:, :, None] * n[:, None, :]
        nodes = pair.slaves[active][:, None]
        coef = np.ones((active.size, 1))
        if self.rigid:  # the normal turns with the slave about the centre: -k g / r (I - n n^T), g < 0
            gap = -res.penetration[active]
            local = local + (k * gap / (pair.radius + gap))[:, None, None] * (np.eye(3) - nn)
        else:
            nodes = np.concatenate([nodes, res.corners[active]], axis=1)
            coef = np.concatenate([coef, -res.weights[active]], axis=1)
        m = nodes.shape[1]
        dofs = (3 * nodes[:, :, None] + np.arange(3)).reshape(-1, 3 * m)  # (a, 3m)
        block = (coef[:, :, None, None, None] * coef[:, None, None, :, None]
                 * local[:, None, :, None, :])  # (a, m, 3, m, 3)
        rows = np.broadcast_to(dofs[:, :, None], (active.size, 3 * m, 3 * m))
        cols = np.broadcast_to(dofs[:, None, :], (active.size, 3 * m, 3 * m))
        return sp.csr_matrix((block.ravel(), (rows.ravel(), cols.ravel())), shape=(size, size))


class _Newton:
    """The pieces every Newton iteration of a run shares: prescribed dofs, the sparse pattern
    and the linear solver (whose factorization later systems reuse as a preconditioner)."""

    def __init__(self, model: ExplicitModel, contact: StepContact | None, options: QuasiStaticOptions):
        self.model, self.contact, self.options = model, contact, options
        n = model.points.shape[0]
        self.prescribed, self.rates = _prescribed(model)
        self.free = np.ones(3 * n, dtype=bool)
        self.free[self.prescribed] = False
        self.pattern = SparsePattern([b.kin.conn + b.offset for b in model.bodies], n)
        # later systems are solved by CG (GMRES while friction slips) preconditioned with the last
        # factorization, to options.linear_tolerance or looser (the forcing term of
        # options.linear_target: an inexact Newton)
        entries = estimate_factor_entries(self.pattern.node_graph(), 3)
        self.solver = LinearSolver(options.solver, factor_entries=entries, rtol=options.linear_tolerance,
                                   reuse_rtol=options.linear_tolerance, direct_max_entries=REUSED_DIRECT_MAX_ENTRIES,
                                   single_precision=options.single_precision_factor, timed_budget=False,
                                   factorize_ahead=options.factorize_ahead, direct="pardiso",
                                   factorize_ahead_above=options.factorize_ahead_above,
                                   symmetric_factor=options.symmetric_factor,
                                   correction_threshold=options.correction_threshold)
        self.modes = rigid_body_modes(model.points)
        self.solves = 0
        self.reversals = 0  # slaves linearized on the stick piece (StepContact.linearize)

    def forces(self, u: np.ndarray, states: list, x_start: np.ndarray, t: float, h: float):
        """Internal forces, contact (response, :class:`~toolkit.impact.contact.ContactStep` or
        None) and the free-dof residual at ``u``."""
        try:
            internal = _internal_forces(self.model, u, states)
        except _Inverted as exc:
            raise InadmissibleState(f"{exc.body} element {exc.element} inverted") from None
        if self.contact is None:
            contact = ContactResponse(np.zeros_like(u), 0.0, 0.0, np.zeros(3), 0.0)
            state = None
        else:
            contact, state = self.contact.respond(self.model.points + u, x_start, t, h)
        r = (internal.force - contact.forces).reshape(-1).copy()
        r[~self.free] = 0.0
        return internal, contact, state, r

    def force_scale(self, internal, contact: ContactResponse) -> float:
        """N, the force a residual is judged against: the reactions at the prescribed dofs plus
        the contact force."""
        return float(np.linalg.norm((internal.force - contact.forces).reshape(-1)[self.prescribed])
                     + np.linalg.norm(contact.forces))

    def tangent(self, u: np.ndarray, states: list, contact: ContactLinearization | None,
                updates: list | None = None) -> tuple[sp.csr_matrix, bool, sp.csr_matrix | None]:
        """The constrained tangent ``(3n, 3n)`` N/mm at ``u`` (material and ``contact``), whether
        it is symmetric (no slipping contact), and its contact part (None without contact): the
        few dofs whose entries change most between iterations, which the linear solver corrects
        for exactly when it reuses an older factorization (its ``local``). ``updates``: every
        body's material update at ``u`` (from the residual), whose tangent a material with
        ``tangent_of`` (:meth:`~toolkit.impact.plasticity.J2Plasticity.tangent_of`) makes
        without updating again."""
        blocks = []
        for i, (b, st) in enumerate(zip(self.model.bodies, states)):
            E, Q = b.kin.weight.shape
            update = None if updates is None else updates[i]
            try:
                if update is not None and getattr(update, "return_mapping", None) is not None \
                        and hasattr(b.material, "tangent_of"):
                    A = b.material.tangent_of(update)
                else:
                    F = deformation_gradient(b.kin, u[b.offset:b.offset + b.n_nodes])
                    _, A = b.material.tangent(F.reshape(-1, 3, 3), st)
            except FloatingPointError as exc:
                raise NewtonFailed(f"{b.name}: {exc}") from None
            blocks.append((b.kin.grad, b.kin.weight, A.reshape(E, Q, 3, 3, 3, 3)))
        K = self.pattern.constrain(self.pattern.assemble_tangent(blocks, symmetric=True), self.prescribed, copy=False)
        k_contact = None if contact is None else contact.tangent
        if k_contact is not None and k_contact.nnz:
            k_contact = k_contact.tocoo()
            keep = self.free[k_contact.row] & self.free[k_contact.col]
            k_contact = sp.csr_matrix((k_contact.data[keep], (k_contact.row[keep], k_contact.col[keep])),
                                      shape=K.shape)
            skew = abs(k_contact - k_contact.T)
            symmetric = skew.nnz == 0 or skew.max() <= 1e-12 * abs(k_contact).max()
            return add_local(K, k_contact), symmetric, k_contact
        return K, True, None

    def solve_step(self, u: np.ndarray, states: list, guess: np.ndarray, t: float, h: float):
        """Equilibrium at ``t`` from the converged ``u`` (``guess`` sets the free dofs' start)
        by :func:`~toolkit.common.fem.newton.newton` with ``options.line_search``; returns
        ``(u_new, internal, contact, iterations)`` or raises
        :class:`~toolkit.common.fem.newton.NewtonFailed`."""
        opt = self.options
        x_start = self.model.points + u

        def evaluate(x):
            internal, contact, state, r = self.forces(x, states, x_start, t, h)
            return Trial(x, r, float(np.linalg.norm(r)), (internal, contact, state))

        def converged(trial):
            scale = self.force_scale(*trial.data[:2])
            log.debug("t = %.5g s: residual %.3g N (scale %.3g N) at node %d", t, trial.norm, scale,
                      int(np.argmax(np.abs(trial.residual))) // 3)
            return trial.norm <= opt.tolerance * scale or trial.norm < 1e-9

        previous = None  # the slip directions at the last correction

        def correction(trial):
            nonlocal previous
            rhs, contact = -trial.residual, None
            if trial.data[2] is not None:
                contact = self.contact.linearize(trial.data[2], previous if opt.stick_on_reversal else None)
                previous = contact.directions
                self.reversals += contact.reversed
                if contact.reversed:
                    rhs = rhs + np.where(self.free, contact.force_shift, 0.0)
            K, symmetric, local = self.tangent(trial.x, states, contact, trial.data[0].updates)
            rtol, norm = None, float(np.linalg.norm(rhs))
            if opt.linear_target > 0 and norm > 0:  # the forcing term (QuasiStaticOptions.linear_target)
                target = opt.linear_target * opt.tolerance * self.force_scale(*trial.data[:2])
                rtol = min(MAX_LINEAR_TOLERANCE, max(opt.linear_tolerance, target / norm))
            try:
                du, _ = self.solver.solve(K, rhs, near_nullspace=self.modes, symmetric=symmetric, local=local,
                                          rtol=rtol)
            except SolverError as exc:
                raise NewtonFailed(f"linear solve failed: {exc}") from None
            self.solves += 1
            return du.reshape(-1, 3)

        def negligible(trial, du):
            return np.abs(du).max() <= opt.displacement_tolerance

        x = guess.copy()
        x.reshape(-1)[self.prescribed] = self.rates * t
        try:
            start = evaluate(x)
        except InadmissibleState as exc:
            raise NewtonFailed(str(exc)) from None
        search = LINE_SEARCHES[opt.line_search]()
        result = newton(start, evaluate, correction, converged, negligible, search, opt.max_iterations)
        internal, contact, _ = result.trial.data
        return result.trial.x, internal, contact, result.iterations


def run_quasistatic(model: ExplicitModel, contact: StepContact | None, duration: float, n_frames: int,
                    options: QuasiStaticOptions = QuasiStaticOptions(), on_frame: Callable | None = None,
                    progress: bool = False, initial_guess: Callable | None = None) -> tuple[list, dict]:
    """Quasi-static equilibrium path of ``model`` over ``duration`` s with ``n_frames`` frames
    (t > 0), the same :class:`~toolkit.impact.explicit.Frame` output as
    :func:`~toolkit.impact.explicit.run_explicit` (``model.mass``, ``model.dt`` and
    ``model.contact`` are not used; ``contact`` is the step contact). Raises
    :class:`ConvergenceError` when a step fails at ``options.min_step``.

    Each load step's Newton iterations start from the previous step's increment scaled to the
    new step; with ``initial_guess``, a callable ``t -> (m, 3)`` mm displacement of the first
    ``m`` nodes at time ``t`` s (a surrogate's prediction, say), they start from it on those
    nodes instead, and from the previous step's increment again when Newton fails from it
    (``stats["guess_failures"]``) before the step is cut.
    """
    from tqdm.auto import tqdm

    h_max = duration / options.steps
    steps = LoadSteps(np.linspace(0.0, duration, n_frames + 1)[1:], max_step=h_max,
                      min_step=min(options.min_step, h_max), growth=options.growth,
                      easy_iterations=options.easy_iterations)
    solver = _Newton(model, contact, options)
    n = model.points.shape[0]
    states = [b.material.initial_state(b.kin.n_points) for b in model.bodies]
    u = np.zeros((n, 3))
    last_increment, last_step = np.zeros((n, 3)), None
    internal, contact_now, _, _ = solver.forces(u, states, model.points, 0.0, duration)
    ledger = _WorkLedger(solver.prescribed)  # no kinetic energy
    frames = []
    stats = {"steps": 0, "iterations": 0, "cuts": 0, "max_contact_force_n": 0.0, "max_penetration_mm": 0.0,
             "guess_failures": 0}
    bar = tqdm(total=n_frames, desc="frames (quasi-static)", disable=not progress, leave=False)
    t0 = time.perf_counter()
    try:
        while not steps.done:
            t, t_new = steps.next()
            step = t_new - t
            guess = u + (step / last_step) * last_increment if last_step else u.copy()
            try:
                if initial_guess is not None:
                    u_new, internal_new, contact_new, its = _solve_from_guess(solver, u, states, guess,
                                                                              initial_guess(t_new), t_new, step, stats)
                else:
                    u_new, internal_new, contact_new, its = solver.solve_step(u, states, guess, t_new, step)
            except NewtonFailed as exc:
                log.info("t = %.4g s: step %.3g s cut (%s)", t_new, step, exc)
                if not steps.cut():
                    raise ConvergenceError(f"load step {step:.3g} s failed ({exc}) and the next would be below "
                                           f"min_step {options.min_step:g} s; try more load steps or a smaller "
                                           "tolerance", time=t_new) from None
                continue
            if contact is not None:  # the friction state of the accepted iterate (a line search may have tried others)
                contact_new, _ = contact.respond(model.points + u_new, model.points + u, t_new, step)
                contact.commit()
            ledger.record_work(u_new - u, internal, internal_new, contact_new)
            last_increment, last_step = u_new - u, step
            u, internal, contact_now = u_new, internal_new, contact_new
            states = internal.states
            stats["steps"] += 1
            stats["iterations"] += its
            stats["max_contact_force_n"] = max(stats["max_contact_force_n"],
                                               float(np.linalg.norm(contact_now.force_on_face)))
            stats["max_penetration_mm"] = max(stats["max_penetration_mm"], float(contact_now.max_penetration))
            if steps.accept(its) is None:
                continue
            frame, bodies_fields = _frame(model, t_new, u, internal, ledger.energies, contact_now)
            frames.append(frame)
            if on_frame is not None:
                on_frame(frame, bodies_fields)
            bar.update(1)
    finally:
        solver.solver.close()  # no background factorization outlives the run
    bar.close()
    stats["wall_time_s"] = time.perf_counter() - t0
    stats["dt_s"] = duration / max(stats["steps"], 1)
    stats["cuts"] = steps.cuts
    stats["linear_solves"] = solver.solves
    stats["reversed_slips"] = solver.reversals  # slaves linearized on the stick piece
    stats["factorizations"] = solver.solver.factorizations
    stats["background_factorizations"] = solver.solver.background_factorizations
    stats["factorization_wait_s"] = solver.solver.waited_s  # the solves' wait for the worker
    stats["krylov_iterations"] = solver.solver.krylov_iterations  # GMRES or CG, over all linear solves
    stats["correction_columns"] = solver.solver.correction_columns  # back-solves of the contact corrections
    stats["refactorizations"] = solver.solver.refactorizations  # PARDISO factors made without a new analysis
    stats["energy_error"] = frames[-1].energies.balance_error if frames else 0.0
    stats["max_energy_error"] = max((f.energies.balance_error for f in frames if f.energies.external > 1e-12),
                                    default=0.0)
    return frames, stats


def _solve_from_guess(solver: _Newton, u: np.ndarray, states: list, predictor: np.ndarray, given: np.ndarray,
                      t: float, h: float, stats: dict):
    """One load step started from ``given`` ``(m, 3)`` mm on the first ``m`` nodes (``predictor``
    on the others), then, if Newton fails from there, from ``predictor`` alone (counted in
    ``stats["guess_failures"]``; the iterations returned are the second attempt's)."""
    guess = predictor.copy()
    guess[:given.shape[0]] = given
    try:
        return solver.solve_step(u, states, guess, t, h)
    except NewtonFailed as exc:
        log.info("t = %.4g s: Newton failed from the initial guess (%s); from the previous increment", t, exc)
        stats["guess_failures"] += 1
        return solver.solve_step(u, states, predictor, t, h)
