"""Explicit central-difference dynamics of one or more tetrahedral bodies.

Central differences on a lumped (HRZ) mass:
``v(n+1/2) = v(n-1/2) + dt a(n)``, ``u(n+1) = u(n) + dt v(n+1/2)``, with
``a = M^-1 (f_contact - f_int)`` on free nodes; fixed nodes have zero velocity and
driven nodes the imposed velocity. The stable step is the element eigenvalue bound
(:func:`toolkit.impact.elements.critical_time_step`) times a safety factor; optional
uniform **mass scaling** multiplies every density by ``f`` (steps ``sqrt(f)`` times
longer) and is reported as the added-mass fraction ``f - 1``.

Energy balance (Belytschko, Liu & Moran 2014, 6.2.3), checked every output frame:
``kinetic + internal + contact_elastic + friction_dissipation = external``, where the
internal work holds the stored elastic energy and the plastic dissipation, and the
external work is done by the reactions at driven nodes and by a rigid ball's imposed
motion. A run whose energies, displacements or Jacobians blow up stops with
:class:`InstabilityError` naming the time, the element and a remedy.

Units: mm, s, tonne, N, MPa, mJ (energy).
"""

from __future__ import annotations

import logging
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from toolkit.common.errors import ToolkitError
from toolkit.common.fem.kinematics import BlockKinematics, deformation_gradient, internal_force
from toolkit.common.fem.materials import von_mises

__all__ = ["Body", "ExplicitModel", "Frame", "InstabilityError", "EnergyBalanceWarning", "run_explicit", "Energies",
           "moving_sphere_contact", "ContactResponse"]

log = logging.getLogger(__name__)


class EnergyBalanceWarning(UserWarning):
    """The energy balance of a finished run is off by more than the tolerance."""


class InstabilityError(ToolkitError, RuntimeError):
    """The explicit run became unstable or inverted elements.

    Attributes: ``time`` (s), ``element`` (global element of the body, or None), ``body``, ``suggestion``.
    """

    def __init__(self, message: str, time_s: float, body: str | None, element: int | None, suggestion: str):
        super().__init__(f"t = {time_s:.5g} s: {message}. Suggestion: {suggestion}")
        self.time, self.body, self.element, self.suggestion = time_s, body, element, suggestion


@dataclass(eq=False)
class Body:
    """One deformable body in the explicit model.

    Attributes
    ----------
    name : str
    kin : BlockKinematics (reference configuration)
    material : object with ``update(F (n,3,3), state) -> StressUpdate`` and ``initial_state(n)``
        (see :mod:`toolkit.impact.plasticity`); ``update`` raises ``FloatingPointError`` (with
        the bad point in ``.point``) where ``det F <= 0`` or ``F`` is not finite
    offset : index of the body's first node in the model's global numbering
    n_nodes : nodes of the body
    fixed : (k,) body-local node ids with zero velocity
    driven : (k,) body-local node ids moving at ``drive_velocity`` (3,) mm/s
    dof_nodes, dof_components, dof_velocity : (k,) body-local nodes, components (0-2) and
        imposed velocities (mm/s) of single prescribed components (symmetry planes, rollers)
    """

    name: str
    kin: BlockKinematics
    material: object
    offset: int
    n_nodes: int
    fixed: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    driven: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    drive_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    dof_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    dof_components: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    dof_velocity: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def prescribed_dofs(self) -> tuple[np.ndarray, np.ndarray]:
        """Global flat dofs ``3 node + component`` and their velocities (mm/s)."""
        nodes = [np.repeat(self.fixed, 3), np.repeat(self.driven, 3), np.asarray(self.dof_nodes, np.int64)]
        comps = [np.tile(np.arange(3), self.fixed.size), np.tile(np.arange(3), self.driven.size),
                 np.asarray(self.dof_components, np.int64)]
        vel = [np.zeros(3 * self.fixed.size), np.tile(np.asarray(self.drive_velocity, float), self.driven.size),
               np.asarray(self.dof_velocity, float)]
        dofs = 3 * (np.concatenate(nodes) + self.offset) + np.concatenate(comps)
        return dofs.astype(np.int64), np.concatenate(vel)


@dataclass
class Energies:
    """Accumulated energies, mJ."""

    kinetic: float = 0.0
    internal: float = 0.0
    plastic: float = 0.0
    contact_elastic: float = 0.0
    friction: float = 0.0
    external: float = 0.0

    @property
    def balance_error(self) -> float:
        """|kinetic + internal + contact + friction - external| / max(external, kinetic, internal), dimensionless."""
        lhs = self.kinetic + self.internal + self.contact_elastic + self.friction
        scale = max(abs(self.external), self.kinetic, abs(self.internal), 1e-300)
        return abs(lhs - self.external) / scale


@dataclass(frozen=True, eq=False)
class Frame:
    """Output of the first body (the face) at one time: ``time`` s, ``displacement (n, 3)``
    mm, ``von_mises (n,)`` MPa (nodal, volume-weighted from the Gauss points),
    ``equivalent_plastic_strain (n,)``, energies (whole model), contact force on the face
    (3,) N, ``max_penetration`` mm and ``plastic_volume_fraction`` (the share of the face's
    volume, over integration points, whose equivalent plastic strain is > 0)."""

    time: float
    displacement: np.ndarray
    von_mises: np.ndarray
    equivalent_plastic_strain: np.ndarray
    energies: Energies
    contact_force: np.ndarray
    max_penetration: float
    plastic_volume_fraction: float = 0.0


@dataclass(frozen=True, eq=False)
class ContactResponse:
    """What a contact callback returns for one time step.

    Attributes
    ----------
    forces : (n, 3) float, N — contact force on every node of the model
    elastic_energy : float, mJ — energy stored in the penalty springs now
    friction_dissipation : float, mJ — friction work dissipated during this step
    force_on_face : (3,) float, N — total contact force on the face's nodes
    max_penetration : float, mm
    drive_work : float, mJ — work the imposed motion of a rigid ball did on the model during
        this step (0 for a deformable ball, whose driven nodes' reactions count instead)
    """

    forces: np.ndarray
    elastic_energy: float
    friction_dissipation: float
    force_on_face: np.ndarray
    max_penetration: float
    drive_work: float = 0.0


@dataclass(eq=False)
class ExplicitModel:
    """Bodies, masses and contact, ready to integrate.

    ``contact(x, v, t, dt) -> ContactResponse`` (positions and velocities ``(n, 3)`` mm and
    mm/s, time and step s); ``None`` for no contact.
    """

    points: np.ndarray  # (n, 3) reference coordinates, all bodies
    mass: np.ndarray  # (n,) tonne, after mass scaling
    bodies: list
    dt: float
    contact: Callable | None = None
    initial_velocity: np.ndarray | None = None  # (n, 3) mm/s


def moving_sphere_contact(pair, slaves: np.ndarray, centre0: np.ndarray, velocity: np.ndarray) -> Callable:
    """The :class:`ExplicitModel` contact callback of a rigid sphere moving at constant velocity.

    ``pair`` is a :class:`toolkit.impact.contact.RigidSphereContact` on the nodes ``slaves``; the
    sphere's centre is ``centre0 + velocity t`` (mm, mm/s). The work the imposed motion does on the
    body (trapezoidal rule) enters the energy balance as external work.
    """
    centre0, velocity = np.asarray(centre0, float), np.asarray(velocity, float)
    previous = {"force": np.zeros(3), "centre": centre0.copy()}

    def contact(x, v, t, dt):
        centre = centre0 + velocity * t
        res = pair.step(x[slaves], v[slaves], centre, velocity, dt)
        f = np.zeros_like(x)
        f[slaves] = res.force
        on_body = res.force.sum(axis=0)
        work = float(0.5 * (on_body + previous["force"]) @ (centre - previous["centre"]))
        previous["force"], previous["centre"] = on_body, centre
        pen = float(res.penetration.max()) if res.penetration.size else 0.0
        return ContactResponse(f, res.elastic_energy, res.friction_dissipation, on_body, pen, work)

    return contact


def _volume_share(kin: BlockKinematics, mask: np.ndarray) -> float:
    """Share of the body's volume at the integration points where ``mask (E, Q)`` holds."""
    return float(np.sum(kin.weight[mask]) / np.sum(kin.weight))


def _to_nodes(kin: BlockKinematics, values: np.ndarray, n_nodes: int) -> np.ndarray:
    """Volume-weighted nodal average of Gauss-point values ``(E, Q)``."""
    elem = (values * kin.weight).sum(axis=1) / kin.volume
    num = np.bincount(kin.conn.ravel(), weights=np.repeat(elem * kin.volume, kin.conn.shape[1]), minlength=n_nodes)
    den = np.bincount(kin.conn.ravel(), weights=np.repeat(kin.volume, kin.conn.shape[1]), minlength=n_nodes)
    return num / np.maximum(den, 1e-300)


@dataclass(frozen=True, eq=False)
class _InternalForces:
    """Internal forces ``(n, 3)`` N and the material response of every body at one instant."""

    force: np.ndarray
    states: list
    cauchy: list  # per body (E*Q, 3, 3) MPa; von Mises is computed at output frames only
    eps_p: list  # per body (E, Q)
    dissipation: float  # mJ, plastic work of the step
    updates: list  # per body, the material's update (a quasi-static tangent may start from it)


def _internal_forces(model: ExplicitModel, u: np.ndarray, states: list) -> _InternalForces:
    """Every body's internal force and new material state at displacement ``u (n, 3)`` mm.
    Raises :class:`_Inverted` where ``det F <= 0``."""
    f = np.zeros_like(model.points)
    new_states, cauchy, eps_p, diss, updates = [], [], [], 0.0, []
    for b, st in zip(model.bodies, states):
        F = deformation_gradient(b.kin, u[b.offset:b.offset + b.n_nodes])
        E, Q = F.shape[:2]
        try:  # the material checks det F > 0 (and NaN) at every point
            upd = b.material.update(F.reshape(-1, 3, 3), st)
        except FloatingPointError as exc:
            point = getattr(exc, "point", None)
            raise _Inverted(b.name, None if point is None else int(point) // Q) from exc
        f[b.offset:b.offset + b.n_nodes] = internal_force(b.kin, upd.first_piola.reshape(E, Q, 3, 3), b.n_nodes)
        new_states.append(upd.state)
        updates.append(upd)
        cauchy.append(upd.cauchy)
        eps_p.append(np.asarray(upd.state.eps_p).reshape(E, Q))
        diss += float(np.sum(np.asarray(upd.dissipation).reshape(E, Q) * b.kin.weight))
    return _InternalForces(f, new_states, cauchy, eps_p, diss, updates)


def _contact(model: ExplicitModel, u: np.ndarray, v: np.ndarray, t: float, dt: float) -> ContactResponse:
    """The model's contact response at ``u``, ``v`` (no contact: zero forces)."""
    if model.contact is None:
        return ContactResponse(np.zeros_like(model.points), 0.0, 0.0, np.zeros(3), 0.0)
    return model.contact(model.points + u, v, t, dt)


def _prescribed(model: ExplicitModel) -> tuple[np.ndarray, np.ndarray]:
    """Flat prescribed dofs of every body and their velocities, mm/s."""
    pres = [b.prescribed_dofs() for b in model.bodies]
    if not pres:
        return np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate([p[0] for p in pres]), np.concatenate([p[1] for p in pres])


class _WorkLedger:
    """Work and energies (mJ) booked step by step with trapezoidal increments: internal work,
    plastic and friction dissipation, contact elastic energy, and the external work of the
    reactions at the ``driven`` (prescribed) flat dofs and of a rigid ball's imposed motion.
    The quasi-static path books only this; :class:`_EnergyLedger` adds the kinetic energy."""

    def __init__(self, driven: np.ndarray, external: float = 0.0):
        self.driven = driven
        self.energies = Energies(external=external)
        self.reaction = np.zeros(driven.size)

    def record_work(self, du: np.ndarray, old: _InternalForces, new: _InternalForces,
                    contact: ContactResponse) -> None:
        """Book the work of one step: displacement increment ``du`` (n, 3) mm."""
        e = self.energies
        e.internal += float(np.sum(du * 0.5 * (old.force + new.force)))
        e.plastic += new.dissipation
        e.friction += contact.friction_dissipation
        e.contact_elastic = contact.elastic_energy
        # work of contact forces on the free nodes is inside the contact energies; the part
        # acting on driven nodes is balanced by their reactions
        reaction = (new.force - contact.forces).reshape(-1)[self.driven]
        e.external += float(np.sum(du.reshape(-1)[self.driven] * 0.5 * (self.reaction + reaction))) + contact.drive_work
        self.reaction = reaction


class _EnergyLedger(_WorkLedger):
    """:class:`_WorkLedger` plus the kinetic energy; the initial kinetic energy counts as work
    put in. Raises :class:`InstabilityError` when the kinetic energy exceeds 100x the work done
    (an unstable step)."""

    def __init__(self, m: np.ndarray, v0: np.ndarray, driven: np.ndarray, drive_v: np.ndarray):
        self.m, self.drive_v = m, drive_v
        self.ke_start = 0.5 * float(np.sum(m * v0**2))
        super().__init__(driven, external=self.ke_start)
        self.scale = 0.0

    def record(self, t: float, dt: float, du: np.ndarray, v_half: np.ndarray, old: _InternalForces,
               new: _InternalForces, contact: ContactResponse) -> None:
        """Book one step: displacement increment ``du``, half-step velocity ``v_half`` (n, 3)."""
        self.record_work(du, old, new, contact)
        e = self.energies
        # velocity at t(n+1) (the half-step velocity plus half a step of the new acceleration),
        # so that the kinetic energy is taken at the same time as the internal energy
        v_full = v_half + 0.5 * dt * (contact.forces - new.force) / self.m
        v_full.reshape(-1)[self.driven] = self.drive_v
        e.kinetic = 0.5 * float(np.sum(self.m * v_full**2))
        self.scale = max(self.scale, abs(e.external), e.internal)
        if e.kinetic > 100.0 * (self.scale + self.ke_start) + 1e-12:
            raise InstabilityError(f"kinetic energy {e.kinetic:.3g} mJ exceeds 100x the work done",
                                   t, None, None, "the time step is unstable: lower the time-step safety factor "
                                   "(Fidelity.safety; command line: --safety) or use the quasi-static integrator "
                                   "(--integrator quasi-static)")


def _frame(model: ExplicitModel, t: float, u: np.ndarray, internal: _InternalForces, energies: Energies,
           contact: ContactResponse) -> tuple[Frame, list]:
    """The output frame at ``t`` (the face's fields) and every body's nodal fields."""
    bodies_fields = []
    for b, sig, epb in zip(model.bodies, internal.cauchy, internal.eps_p):
        bodies_fields.append({
            "displacement": u[b.offset:b.offset + b.n_nodes].copy(),
            "von_mises": _to_nodes(b.kin, von_mises(sig).reshape(epb.shape), b.n_nodes),
            "equivalent_plastic_strain": _to_nodes(b.kin, epb, b.n_nodes),
            "plastic_volume_fraction": float(_volume_share(b.kin, epb > 0.0)),
        })
    face = bodies_fields[0]
    frame = Frame(t, face["displacement"], face["von_mises"], face["equivalent_plastic_strain"],
                  Energies(**energies.__dict__), contact.force_on_face.copy(), float(contact.max_penetration),
                  face["plastic_volume_fraction"])
    return frame, bodies_fields


def run_explicit(model: ExplicitModel, duration: float, n_frames: int, on_frame: Callable | None = None,
                 progress: bool = False, energy_tolerance: float = 0.05) -> tuple[list, dict]:
    """Integrate ``model`` for ``duration`` s, returning ``n_frames`` frames (t > 0) and statistics.

    Central differences (leapfrog): each step takes the half-step velocity from the last
    forces, moves, computes the internal forces and the contact (:func:`_internal_forces`,
    :func:`_contact`), books the energies (:class:`_EnergyLedger`) and writes a frame when
    one is due (:func:`_frame`). ``on_frame(frame, body_fields)`` is called as each frame
    completes (to write it at once). Raises :class:`InstabilityError` on NaN, inverted
    elements or an energy blow-up; warns :class:`EnergyBalanceWarning` when the final
    balance error exceeds ``energy_tolerance``.
    """
    from tqdm.auto import tqdm

    n_steps = int(np.ceil(duration / model.dt - 1e-9))
    dt = duration / n_steps
    frame_steps = set(np.unique(np.round(np.linspace(0, n_steps, n_frames + 1)[1:]).astype(int)).tolist())
    n = model.points.shape[0]
    m = model.mass[:, None]
    u = np.zeros((n, 3))
    v = np.zeros((n, 3)) if model.initial_velocity is None else np.array(model.initial_velocity, dtype=float)
    driven, drive_v = _prescribed(model)
    v.reshape(-1)[driven] = drive_v
    t = 0.0
    try:
        internal = _internal_forces(model, u, [b.material.initial_state(b.kin.n_points) for b in model.bodies])
    except _Inverted as exc:
        raise InstabilityError(f"{exc.body} element {exc.element} is inverted in the initial state", 0.0,
                               exc.body, exc.element, "check the mesh") from None
    contact = _contact(model, u, v, t, dt)
    ledger = _EnergyLedger(m, v, driven, drive_v)
    frames = []
    stats = {"steps": n_steps, "dt_s": dt, "max_contact_force_n": 0.0, "max_penetration_mm": 0.0}
    bar = tqdm(total=n_steps, desc="simulated time (steps)", disable=not progress, leave=False,
               mininterval=1.0)
    t0 = time.perf_counter()
    for step in range(1, n_steps + 1):
        a = (contact.forces - internal.force) / m
        v_new = v + dt * a if step > 1 else v + 0.5 * dt * a
        v_new.reshape(-1)[driven] = drive_v
        du = dt * v_new
        u_new = u + du
        t += dt
        if not np.isfinite(u_new).all():
            raise InstabilityError("displacements became NaN/inf", t, None, None,
                                   "lower the time-step safety factor (--safety) or the mass scaling (--mass-scaling), "
                                   "or use the quasi-static integrator (--integrator quasi-static)")
        try:
            internal_new = _internal_forces(model, u_new, internal.states)
        except _Inverted as exc:
            raise InstabilityError(f"{exc.body} element {exc.element} inverted (det F <= 0)", t, exc.body,
                                   exc.element, "lower the time-step safety factor (Fidelity.safety; command line: "
                                   "--safety), the ball velocity (--velocity) or the mass scaling (--mass-scaling); "
                                   "or use the quasi-static integrator (--integrator quasi-static); or refine the mesh "
                                   "where it inverted") from None
        contact_new = _contact(model, u_new, v_new, t, dt)
        ledger.record(t, dt, du, v_new, internal, internal_new, contact_new)
        stats["max_contact_force_n"] = max(stats["max_contact_force_n"],
                                           float(np.linalg.norm(contact_new.force_on_face)))
        stats["max_penetration_mm"] = max(stats["max_penetration_mm"], float(contact_new.max_penetration))
        u, v, internal, contact = u_new, v_new, internal_new, contact_new
        if step in frame_steps:
            frame, bodies_fields = _frame(model, t, u, internal, ledger.energies, contact)
            frames.append(frame)
            if on_frame is not None:
                on_frame(frame, bodies_fields)
            e = frame.energies
            log.info("t = %.4g s: KE %.3g, internal %.3g, external %.3g mJ, energy error %.2e", t, e.kinetic,
                     e.internal, e.external, e.balance_error)
        bar.update(1)
    bar.close()
    stats["wall_time_s"] = time.perf_counter() - t0
    stats["energy_error"] = frames[-1].energies.balance_error if frames else 0.0
    stats["max_energy_error"] = max((f.energies.balance_error for f in frames
                                     if f.energies.external > 1e-12), default=0.0)
    if stats["energy_error"] > energy_tolerance:
        warnings.warn(f"energy balance error {stats['energy_error']:.2%} exceeds {energy_tolerance:.0%}: the time "
                      f"step or the contact penalty is too coarse for this scene", EnergyBalanceWarning, stacklevel=2)
    return frames, stats


class _Inverted(Exception):
    def __init__(self, body, element):
        self.body, self.element = body, element
