"""Build an impact scene into an explicit model, run it, and write its outputs.

Only what the scene needs is built: a rigid ball has no mesh (contact against the
analytic sphere), an elastic material (no yield table) skips the return mapping, and
contact is searched only once the ball is near the skin.

Outputs (:func:`simulate` with ``out``): ``face.xdmf`` (+ ``.h5``; point data
``displacement`` mm and ``von_mises`` MPa per frame), ``ball.xdmf`` for a deformable ball,
``history.h5`` (times, energies, contact force, penetration), ``summary.json`` (``"status"``:
``"finished"``, ``"failed"`` or ``"interrupted"``) and ``preview.png``. Frames are appended to
the files as the run goes, so a failed or interrupted run keeps its finished frames, readable,
and says so in its ``summary.json``.

A skull-held scene whose ball would crush the tissue against the skull is refused before
anything is computed (:func:`check_travel`).
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from toolkit import __version__
from toolkit.common.errors import AnswerError, ToolkitError
from toolkit.common.fem.kinematics import lumped_mass
from toolkit.common.fem.materials import lame
from toolkit.common.meshes.axes import check_mesh_axes, mesh_to_toolkit
from toolkit.common.meshes.io import TimeSeriesWriter, atomic_path, read
from toolkit.common.meshes.mesh import Mesh
from toolkit.common.meshes.topology import boundary_faces
from toolkit.common.outputs import check_output_dir
from toolkit.common.phantoms.phantom import ball as ball_mesh
from toolkit.common.phantoms.phantom import face_tet
from toolkit.common.plotting import render
from toolkit.common.runtime import count_finished
from toolkit.impact.checks import answer_checks
from toolkit.impact.contact import CoulombFriction, RigidSphereContact, SurfaceContact, penalty_stiffness
from toolkit.impact.elements import critical_time_step, tet_kinematics
from toolkit.impact.explicit import Body, ContactResponse, ExplicitModel, moving_sphere_contact, run_explicit
from toolkit.impact.plasticity import HardeningTable, J2Plasticity
from toolkit.impact.quasi_static import QuasiStaticOptions, StepContact, run_quasistatic
from toolkit.impact.scene import MESH_ORDERS, MaterialSpec, Scene, SceneError, mesh_order

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd

__all__ = ["simulate", "ImpactResult", "build_model", "UnstableTimeStepError", "SceneGeometryWarning", "sweep_travel",
           "face_mesh", "fixed_nodes", "ball_start", "travel_limit", "check_travel", "write_preview", "write_summary",
           "COMPRESSED_TISSUE_FRACTION", "MESH_ORDERS", "mesh_order"]


class UnstableTimeStepError(ToolkitError, ValueError):
    """A requested time step exceeds the stable limit."""


class SceneGeometryWarning(UserWarning):
    """The ball's path over the scene's duration reaches fixed nodes (tissue would be crushed)."""


def _material(spec: MaterialSpec, mass_scaling: float) -> J2Plasticity:
    table = None if spec.yield_table is None else HardeningTable.from_pairs(spec.yield_table)
    return J2Plasticity(spec.E, spec.nu, spec.density * mass_scaling, table)


def _lame(spec: MaterialSpec):
    return lame(spec.E, spec.nu)


@dataclass(eq=False)
class BuiltScene:
    """The pieces :func:`simulate` runs (exposed for tests and notebooks)."""

    model: ExplicitModel
    face: Mesh
    ball: Mesh | None
    ball_centre: np.ndarray
    dt_critical: float
    dt_element: tuple
    added_mass_fraction: float
    fixed_clearance_mm: float = float("inf")  # travel left between the ball's path and the fixed nodes
    contact_pair: RigidSphereContact | SurfaceContact | None = None  # the contact behind model.contact


def build_model(scene: Scene) -> BuiltScene:
    """Meshes, materials, masses, time step and contact for ``scene``: the face, the ball aimed
    at it (:func:`ball_start`, and a warning if its path reaches fixed nodes), each body with
    its lumped masses and stable step, the run's time step, and the contact callback."""
    face = face_mesh(scene)
    fixed = fixed_nodes(scene, face)
    centre0 = ball_start(scene, face.points[face.node_set("skin")])
    check_travel(scene, face)
    clearance = _path_clearance(scene, face.points[fixed], centre0)
    face_body, face_mass, (dt_crit, dt_elem) = _face_body(scene, face, fixed)
    bodies, masses, ball = [face_body], [face_mass], None
    if not scene.ball.rigid:
        ball_body, ball, ball_mass, (dt_ball, el_ball) = _ball_body(scene, centre0, face.n_points)
        bodies.append(ball_body)
        masses.append(ball_mass)
        if dt_ball < dt_crit:
            dt_crit, dt_elem = dt_ball, el_ball
    mass = np.concatenate(masses)
    points = face.points if ball is None else np.vstack([face.points, ball.points])
    dt = _time_step(scene, dt_crit, dt_elem)
    pair = _contact_pair(scene, face, ball, mass, dt_crit)
    model = ExplicitModel(points, mass, bodies, dt, _contact_callback(scene, pair, centre0))
    return BuiltScene(model, face, ball, centre0, dt_crit, dt_elem, scene.fidelity.mass_scaling - 1.0, clearance,
                      pair)


def _path_clearance(scene: Scene, fixed_points: np.ndarray, centre0: np.ndarray) -> float:
    """Travel (mm) left between the end of the ball's path and the first of the fixed nodes at
    ``fixed_points (k, 3)`` mm (negative: the path reaches them, and
    :class:`SceneGeometryWarning` says when)."""
    d = np.asarray(scene.ball.direction, dtype=float)
    travel = scene.ball.velocity * scene.duration
    clearance = float(sweep_travel(fixed_points, centre0, d, scene.ball.radius).min(initial=np.inf)) - travel
    if clearance < 0:
        warnings.warn(f"the ball's path reaches the fixed region after {travel + clearance:.1f} mm of its "
                      f"{travel:.1f} mm travel (t = {(travel + clearance) / scene.ball.velocity:.2f} s): tissue "
                      "will be crushed against fixed nodes and elements may invert; aim higher "
                      "(ball.target_offset), shorten the duration or fix less of the face",
                      SceneGeometryWarning, stacklevel=3)
    return clearance


#: share of the tissue between the ball's first touch and the skull that stays between them at the
#: longest travel :func:`travel_limit` allows. On the coarse skull-held face a tenth keeps the limit
#: short both of where the ball's path meets the bone and of where a 50 mm/s ball inverts an
#: element (explicit, tet4, mass scaling 100).
COMPRESSED_TISSUE_FRACTION = 0.1


def travel_limit(scene: Scene, face: Mesh | None = None) -> float:
    """Longest travel (mm) of the ball from its start that a skull-held face (``face.support =
    "skull"``) can take: the travel after which the ball's path meets a fixed (bone) node, less
    :data:`COMPRESSED_TISSUE_FRACTION` of the tissue between the first touch and that node.
    ``inf`` for a face held only at its band (its path is checked by :func:`build_model`'s
    warning) or a path that never meets the support. ``face``: the scene's face
    (:func:`face_mesh`, built when omitted). Depends on the geometry only, not the velocity."""
    return _support_travel(scene, face)[1]


def _support_travel(scene: Scene, face: Mesh | None) -> tuple[float, float]:
    """(travel after which the ball's path meets the support, :func:`travel_limit`), mm."""
    if scene.face.support != "skull":
        return float("inf"), float("inf")
    face = face_mesh(scene) if face is None else face
    centre0 = ball_start(scene, face.points[face.node_set("skin")])
    d = np.asarray(scene.ball.direction, dtype=float)
    support = float(sweep_travel(face.points[fixed_nodes(scene, face)], centre0, d, scene.ball.radius)
                    .min(initial=np.inf))
    if not np.isfinite(support):
        return support, support
    tissue = max(support - scene.ball.gap, 0.0)  # the ball first touches the skin after `gap` mm
    return support, support - COMPRESSED_TISSUE_FRACTION * tissue


def check_travel(scene: Scene, face: Mesh | None = None) -> None:
    """Refuse (:class:`~toolkit.impact.scene.SceneError`) a skull-held scene whose ball travels
    (velocity x duration) farther than :func:`travel_limit`: the tissue would be crushed against
    the skull and an element would invert mid-run. The message names the longest duration that
    fits at the scene's velocity. ``face``: the scene's face (built when omitted)."""
    support, limit = _support_travel(scene, face)
    v = scene.ball.velocity
    travel = v * scene.duration
    if travel <= limit:
        return
    longest = np.floor(1000.0 * limit / v) / 1000.0
    raise SceneError(
        f"the ball travels {travel:.1f} mm ({v:g} mm/s x {scene.duration:g} s) into a face held by the skull, "
        f"and its path meets the fixed bone nodes after {support:.1f} mm: past {limit:.1f} mm the tissue is "
        f"crushed against the skull and elements invert. The longest duration that fits at {v:g} mm/s is "
        f"{longest:.3f} s: pass --duration {longest:.3f} (Python: Scene.duration), a lower velocity, or hold "
        f"the face by its band (support = \"band\")")


def _face_body(scene: Scene, face: Mesh, fixed: np.ndarray) -> tuple[Body, np.ndarray, tuple]:
    """The face body (the ``fixed`` nodes held), its lumped masses (n,) tonne and ``(stable
    step s, ("face", element))``."""
    ms = scene.fidelity.mass_scaling
    kin = tet_kinematics(face)
    body = Body("face", kin, _material(scene.face.material, ms), 0, face.n_points, fixed=fixed)
    mass = lumped_mass(kin, scene.face.material.density * ms, face.n_points)
    lam, mu = _lame(scene.face.material)
    dt, element, _ = critical_time_step(kin, lam, mu, scene.face.material.density * ms)
    return body, mass, (dt, ("face", element))


def _ball_body(scene: Scene, centre0: np.ndarray, offset: int) -> tuple[Body, Mesh, np.ndarray, tuple]:
    """The deformable ball at ``centre0``: its body (the back, beyond ``driven_fraction`` of the
    radius, driven at the ball's velocity; the front free), mesh, masses and stable step."""

    ms, R = scene.fidelity.mass_scaling, scene.ball.radius
    d = np.asarray(scene.ball.direction, dtype=float)
    ball = ball_mesh(R, scene.ball.resolution, order=scene.fidelity.order, centre=centre0)
    kin = tet_kinematics(ball)
    back = np.flatnonzero((ball.points - centre0) @ d < -scene.ball.driven_fraction * R)
    body = Body("ball", kin, _material(scene.ball.material, ms), offset, ball.n_points,
                driven=back, drive_velocity=scene.ball.velocity * d)
    mass = lumped_mass(kin, scene.ball.material.density * ms, ball.n_points)
    lam, mu = _lame(scene.ball.material)
    dt, element, _ = critical_time_step(kin, lam, mu, scene.ball.material.density * ms)
    return body, ball, mass, (dt, ("ball", element))


def _time_step(scene: Scene, dt_crit: float, dt_elem: tuple) -> float:
    """The run's step, s: the fidelity's ``dt`` (refused above the stable limit unless allowed)
    or its ``safety`` times the stable step the contact penalty keeps."""
    fid, fraction = scene.fidelity, scene.contact.dt_fraction
    dt_stable = fraction * dt_crit  # the contact penalty keeps the step above this
    if fid.dt is None or fid.integrator == "quasi-static":
        return fid.safety * dt_stable
    if fid.dt > dt_stable and not fid.allow_unstable_dt:
        raise UnstableTimeStepError(
            f"time step {fid.dt:.3g} s exceeds the stable limit {dt_stable:.3g} s ({dt_elem[0]} element "
            f"{dt_elem[1]}, contact fraction {fraction}); use dt <= {dt_stable:.3g} s, mass scaling, or drop "
            f"Fidelity.dt to let the solver choose")
    return fid.dt


def _contact_pair(scene: Scene, face: Mesh, ball: Mesh | None, mass: np.ndarray, dt_crit: float):
    """Penalty contact of the skin against the rigid sphere or the deformable ball's surface,
    with Coulomb friction; the penalty keeps the stable step at ``dt_fraction`` of ``dt_crit``
    (the quasi-static path uses the same penalty, so both paths solve the same contact problem)."""
    skin = face.node_set("skin")
    friction = CoulombFriction(scene.contact.friction) if scene.contact.friction > 0 else None
    # a penalty spring joins a skin node to the ball: its stable step depends on the lighter end.
    # Deformable tet10 balls put only 1/36 of an element's mass on each corner (HRZ), and the
    # rubber is 13x lighter than tissue, so the master nodes, not the skin, set the limit.
    m_contact = mass[skin]
    if ball is not None:
        tris = boundary_faces(ball.volume_type, ball.volume_cells) + face.n_points
        m_master = float(mass[np.unique(tris)].min())
        m_contact = 1.0 / (1.0 / m_contact + 1.0 / m_master)
    k_pen = penalty_stiffness(m_contact, dt_crit, scene.contact.dt_fraction)
    if scene.ball.rigid:
        return RigidSphereContact(scene.ball.radius, k_pen, friction, skin)
    return SurfaceContact(skin, tris, k_pen, friction)


def _contact_callback(scene: Scene, pair, centre0: np.ndarray):
    """The explicit model's contact callback for ``pair`` (:func:`_contact_pair`)."""
    if scene.ball.rigid:
        d = np.asarray(scene.ball.direction, dtype=float)
        return moving_sphere_contact(pair, pair.slaves, centre0, scene.ball.velocity * d)
    skin = pair.slaves

    def contact(x, v, t, dt_):
        res = pair.step(x, v, dt_)
        f = res.master_force.copy()  # the reaction on every node (the ball's surface)
        f[skin] += res.force
        pen = float(res.penetration.max()) if res.penetration.size else 0.0
        return ContactResponse(f, res.elastic_energy, res.friction_dissipation, res.force.sum(axis=0), pen)

    return contact


def ball_start(scene: Scene, skin_points: np.ndarray) -> np.ndarray:
    """The ball's centre at t = 0, ``(3,)`` mm: on the line along ``ball.direction`` through the
    target (plus offset), advanced until the closest of the ``skin_points (n, 3)`` mm is
    ``ball.gap`` from the sphere. Independent of the velocity; the centre then moves as
    ``centre0 + velocity * direction * t``."""
    d = np.asarray(scene.ball.direction, dtype=float)
    skin = np.asarray(skin_points, dtype=float)
    if scene.ball.target is None:
        target = skin[np.argmax(skin @ -d)]
    else:
        target = np.asarray(scene.ball.target, dtype=float)
    target = target + np.asarray(scene.ball.target_offset, dtype=float)
    R = scene.ball.radius
    # start behind the plane through the most upstream skin point, then advance until the
    # closest skin node is `gap` mm from the sphere (first touch of a sphere of radius R + gap)
    lead = float(np.max(skin @ -d))
    centre0 = target - d * (R + scene.ball.gap + (lead - target @ -d))
    first_touch = float(sweep_travel(skin, centre0, d, R + scene.ball.gap).min())
    if not np.isfinite(first_touch):
        raise ValueError(f"the ball (radius {R} mm) aimed at {np.round(target, 1).tolist()} mm along "
                         f"{list(scene.ball.direction)} misses the face; change ball.target or target_offset")
    return centre0 + d * first_touch


def face_mesh(scene: Scene) -> Mesh:
    """The scene's face: the tetrahedral phantom at ``scene.face.resolution`` and the fidelity's
    element order, or the mesh file ``scene.face.mesh`` (with node sets ``fixed_set``, ``skin``
    and, for a skull-held face, ``bone``). Points ``(n, 3)`` mm."""

    if scene.face.mesh:
        return _face_file(scene)
    return face_tet(scene.face.resolution, order=scene.fidelity.order,
                    lower_fixed_fraction=scene.face.lower_fixed_fraction)


def _face_file(scene: Scene) -> Mesh:
    """The face mesh file of ``scene`` in the toolkit's axes, checked: tetrahedra of the fidelity's
    order, the node sets the scene holds and aims at (:class:`~toolkit.impact.scene.SceneError`
    otherwise) and the anatomy (:func:`toolkit.common.meshes.axes.check_mesh_axes`)."""

    spec = scene.face
    assert spec.mesh is not None  # called for a scene whose face is a mesh file
    needed = list(dict.fromkeys([spec.fixed_set, "skin"] + (["bone"] if spec.support == "skull" else [])))
    face = mesh_to_toolkit(read(spec.mesh, units=spec.units), spec.axes)
    missing = [n for n in needed if n not in face.node_sets]
    if missing:
        hint = (" or hold the face by its fixed set only (support = \"band\", command line --support band)"
                if missing == ["bone"] else "")
        raise SceneError(f"face mesh {spec.mesh} lacks the node sets {missing} (it has {sorted(face.node_sets)}); "
                         f"an impact scene on it needs {needed}: make the mesh with `toolkit mesh`{hint}")
    types = face.volume_types
    if len(types) != 1 or types[0] not in MESH_ORDERS:
        raise SceneError(f"face mesh {spec.mesh}: volume cells {list(types)}; the impact workflow takes one block "
                         f"of {' or '.join(MESH_ORDERS)} (`toolkit mesh --order 1|2` writes them)")
    order = MESH_ORDERS[types[0]]
    if order != scene.fidelity.order:
        raise SceneError(f"face mesh {spec.mesh} holds {types[0]} (order {order}) and the scene asks for order "
                         f"{scene.fidelity.order}; pass --order {order} (Python: Fidelity.order = {order}) or "
                         f"remesh with `toolkit mesh --order {scene.fidelity.order}`")
    check_mesh_axes(face, axes=spec.axes, source=Path(spec.mesh).name)
    return face


def fixed_nodes(scene: Scene, face: Mesh) -> np.ndarray:
    """Face node ids (int64, ascending) with zero velocity: node set ``fixed_set``, and the
    bone-side set ``bone`` too when the face is held by the skull."""
    ids = face.node_set(scene.face.fixed_set)
    if scene.face.support == "skull":
        ids = np.union1d(ids, face.node_set("bone"))
    return np.asarray(ids, dtype=np.int64)


def sweep_travel(points: np.ndarray, centre0: np.ndarray, direction: np.ndarray, radius: float) -> np.ndarray:
    """Travel (mm) after which a sphere of ``radius`` mm starting at ``centre0`` and moving along
    the unit ``direction`` first touches each of the fixed ``points (n, 3)`` mm; ``inf`` for points
    off its path and negative for points already inside. Shape ``(n,)``."""
    rel = np.asarray(points, dtype=float) - centre0
    along = rel @ direction
    perp2 = np.einsum("ij,ij->i", rel, rel) - along**2
    out = np.full(along.shape, np.inf)
    hit = perp2 < radius**2
    out[hit] = along[hit] - np.sqrt(radius**2 - perp2[hit])
    return out


@dataclass(frozen=True, eq=False)
class ImpactResult:
    """What an impact run produced.

    Attributes
    ----------
    scene : Scene
    face : Mesh (reference), ball : Mesh or None
    times : (n_frames,) s
    displacement : (n_frames, n_face, 3) mm; von_mises : (n_frames, n_face) MPa
    energies : DataFrame per frame (mJ) with the balance error
    contact_force : (n_frames, 3) N on the face
    stats : dict (steps, dt_s, wall_time_s, energy_error, ...)
    plastic_volume_fraction : (n_frames,) share of the face volume (integration points) that has
        yielded
    fidelity : the record of the :class:`~toolkit.common.fidelity.FidelityChoice` the scene took
        its options from (``summary()["fidelity"]``), or None
    checks : the values of :func:`toolkit.impact.checks.answer_checks` (``summary()["checks"]["answer"]``)
    """

    scene: Scene
    face: Mesh
    ball: Mesh | None
    times: np.ndarray
    displacement: np.ndarray
    von_mises: np.ndarray
    equivalent_plastic_strain: np.ndarray
    energies: pd.DataFrame
    contact_force: np.ndarray
    stats: dict
    plastic_volume_fraction: np.ndarray | None = None
    fidelity: dict | None = None
    checks: dict | None = None

    def summary(self) -> dict:
        """JSON-ready summary (mm, s, MPa, N); ``fidelity`` when the options were chosen by a tolerance,
        ``checks`` the answer's checks."""
        mag = np.linalg.norm(self.displacement, axis=2)
        fidelity = {} if self.fidelity is None else {"fidelity": self.fidelity}
        return {
            "face_nodes": self.face.n_points,
            "face_elements": self.face.n_cells,
            "element": self.face.volume_type,
            "ball": "rigid" if self.ball is None else f"deformable ({self.ball.n_points} nodes)",
            "velocity_mm_s": self.scene.ball.velocity,
            "steps": int(self.stats["steps"]),
            "dt_s": float(self.stats["dt_s"]),
            "dt_critical_s": float(self.stats["dt_critical_s"]),
            "wall_time_s": float(self.stats["wall_time_s"]),
            "max_displacement_mm": float(mag.max()),
            "max_von_mises_mpa": float(self.von_mises.max()),
            "max_equivalent_plastic_strain": float(self.equivalent_plastic_strain.max()),
            "plastic_volume_fraction": (None if self.plastic_volume_fraction is None
                                        else float(np.max(self.plastic_volume_fraction))),
            "energy_error": float(self.stats["energy_error"]),
            "max_energy_error": float(self.stats["max_energy_error"]),
            "added_mass_fraction": float(self.stats["added_mass_fraction"]),
            "max_contact_force_n": float(self.stats["max_contact_force_n"]),
            "max_penetration_mm": float(self.stats["max_penetration_mm"]),
            # travel (mm) left between the ball's path and the fixed nodes; None: the path never meets them
            "fixed_clearance_mm": (None if not np.isfinite(self.stats.get("fixed_clearance_mm", np.inf))
                                   else float(self.stats["fixed_clearance_mm"])),
            **fidelity,
            **({} if self.checks is None else {"checks": {"answer": self.checks}}),
        }


def _run(scene: Scene, built: BuiltScene, on_frame, progress: bool, initial_guess=None) -> tuple[list, dict]:
    """The scene's integrator over its duration: frames and statistics."""
    if scene.fidelity.integrator == "explicit":
        return run_explicit(built.model, scene.duration, scene.n_frames, on_frame=on_frame, progress=progress)

    fid = scene.fidelity
    contact = StepContact(built.contact_pair, built.model.points.shape[0], built.ball_centre,
                          scene.ball.velocity * np.asarray(scene.ball.direction, dtype=float))
    options = QuasiStaticOptions(steps=fid.load_steps, tolerance=fid.tolerance)
    guess = None
    if initial_guess is not None:
        times, face_u = initial_guess
        times = np.concatenate([[0.0], times])
        face_u = np.concatenate([np.zeros((1, *face_u.shape[1:])), face_u])

        def guess(t):
            k = int(np.clip(np.searchsorted(times, t), 1, len(times) - 1))
            w = float(np.clip((t - times[k - 1]) / (times[k] - times[k - 1]), 0.0, 1.0))
            return (1.0 - w) * face_u[k - 1] + w * face_u[k]

    return run_quasistatic(built.model, contact, scene.duration, scene.n_frames, options, on_frame=on_frame,
                           progress=progress, initial_guess=guess)


def simulate(scene: Scene, out: str | Path | None = None, progress: bool = False, preview: bool = True,
             fidelity=None, initial_guess: tuple[np.ndarray, np.ndarray] | None = None) -> ImpactResult:
    """Run ``scene``; with ``out``, write ``scene.toml`` (the scene that runs) first, stream frames to
    ``out/face.xdmf`` (and ``ball.xdmf``) and write ``history.h5``, ``summary.json`` and ``preview.png``.

    ``fidelity``: the :class:`~toolkit.common.fidelity.FidelityChoice` the scene's options come
    from (:meth:`Scene.with_fidelity_choice`); its record goes to the summary as ``fidelity``.

    ``initial_guess``: ``(times (F,) s, displacement (F, n_face, 3) mm)`` of the face, e.g. a
    surrogate's prediction, where the quasi-static path's Newton iterations start (linear in
    time between the frames, from zero at t = 0; the ball from the previous step's increment),
    falling back to the previous step's increment where Newton fails from it
    (:func:`~toolkit.impact.quasi_static.run_quasistatic`). An explicit scene has no iterations to
    start: ValueError.

    ``summary.json`` has ``"status"``: ``"finished"``, or, when the run raises or is interrupted
    (``KeyboardInterrupt``), ``"failed"`` or ``"interrupted"`` with the ``reason``, the ``error``
    class, the last finished frame (``last_frame_time_s``, ``frames_written`` of
    ``frames_planned``) and, when the error knows it, the simulated time it stopped at
    (``stopped_at_time_s``); the frames
    written so far stay readable (:func:`toolkit.common.meshes.io.read_time_series`, meshio, ParaView)
    and ``history.h5`` holds them. The error is then raised again.
    """

    guess: tuple[np.ndarray, ...] | None = None
    if initial_guess is not None:
        if scene.fidelity.integrator == "explicit":
            raise ValueError("initial_guess with integrator = 'explicit': an explicit run has no iterations to "
                             "start; use scene.with_fidelity(integrator='quasi-static') or leave initial_guess out")
        guess = tuple(np.asarray(a, dtype=float) for a in initial_guess)
    if out is not None:
        check_output_dir(out)
    t0 = time.perf_counter()
    built = build_model(scene)
    if guess is not None:  # the face's node count is known now; nothing has run yet
        g_times, g_u = guess
        if g_times.ndim != 1 or g_u.shape != (len(g_times), built.face.n_points, 3) or not g_times.size \
                or not np.all(np.diff(g_times) > 0) or g_times[0] <= 0:
            raise ValueError(f"initial_guess: times {g_times.shape} and displacement {g_u.shape}; expected "
                             f"increasing times > 0 s (F,) and (F, {built.face.n_points}, 3) mm for this scene's face")
    writers, done = [], []
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        scene.write(out / "scene.toml")
        writers.append(TimeSeriesWriter(out / "face.xdmf", built.face.without_fields()))
        if built.ball is not None:
            writers.append(TimeSeriesWriter(out / "ball.xdmf", built.ball.without_fields()))

    def on_frame(frame, fields):
        for w, f in zip(writers, fields):
            w.append(frame.time, displacement=f["displacement"], von_mises=f["von_mises"])
        done.append(frame)
        count_finished("frame")

    try:
        frames, stats = _run(scene, built, on_frame, progress, guess)
    except BaseException as exc:
        for w in writers:
            w.close()
        if out is not None:
            _write_partial(out, scene, done, exc, time.perf_counter() - t0, fidelity)
        raise
    for w in writers:
        w.close()
    stats["dt_critical_s"] = built.dt_critical
    stats["added_mass_fraction"] = built.added_mass_fraction
    stats["fixed_clearance_mm"] = built.fixed_clearance_mm
    stats["wall_time_s"] = time.perf_counter() - t0
    energies = _energies(frames)
    result = ImpactResult(scene, built.face, built.ball, np.array([f.time for f in frames]),
                          np.stack([f.displacement for f in frames]), np.stack([f.von_mises for f in frames]),
                          np.stack([f.equivalent_plastic_strain for f in frames]), energies,
                          np.stack([f.contact_force for f in frames]), stats,
                          np.array([f.plastic_volume_fraction for f in frames]),
                          None if fidelity is None else fidelity.record())
    checks = answer_checks(built.face, result.displacement, result.von_mises, fixed_nodes(scene, built.face))
    result = replace(result, checks=checks)
    if not checks["passed"]:
        error = AnswerError("the impact answer failed its checks: " + "; ".join(checks["problems"])
                            + _crushed_remedy(scene, result.times, checks), checks)
        if out is not None:
            _write_history(out / "history.h5", frames)
            write_summary(out / "summary.json", {"status": "failed", "error": str(error), **result.summary()})
        raise error
    if out is not None:
        _write_history(out / "history.h5", frames)
        write_summary(out / "summary.json", {"status": "finished", **result.summary()})
        if preview:
            centre = built.ball_centre + scene.ball.velocity * np.asarray(scene.ball.direction) * result.times[-1]
            write_preview(out / "preview.png", built.face, result.displacement[-1], result.von_mises[-1],
                          result.times[-1], None if built.ball is not None else (centre, scene.ball.radius))
    return result


def _crushed_remedy(scene: Scene, times: np.ndarray, checks: dict) -> str:
    """What to change when an element inverts in a frame: the ball's travel then, and the longest
    duration whose frames all passed (``--duration``)."""
    k = checks.get("inverted_from_frame")
    if k is None:
        return ""
    travel = scene.ball.velocity * float(times[k])
    last = f"at most {float(times[k - 1]):.3g} s" if k > 0 else "a shorter one"
    return (f". At {float(times[k]):.3g} s the ball has travelled {travel:.1f} mm and crushes the tissue under it "
            f"beyond what its elements resolve; a shorter --duration ({last} at {scene.ball.velocity:g} mm/s, whose "
            "frames all passed) or a lower --velocity keeps every frame valid")


def _energies(frames: list):
    """Energies per frame (mJ) with the balance error, a DataFrame."""
    import pandas as pd

    return pd.DataFrame([{"time_s": f.time, **f.energies.__dict__, "balance_error": f.energies.balance_error}
                         for f in frames])


def _write_history(path: Path, frames: list) -> None:
    """``history.h5`` of ``frames``: times s, energies mJ, contact force N, per-frame maxima."""
    import h5py


    energies = _energies(frames)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as h5:
            h5["time_s"] = np.array([f.time for f in frames], dtype=float)
            for col in energies.columns:
                h5[f"energies/{col}"] = energies[col].to_numpy()
            h5["contact_force_n"] = np.array([f.contact_force for f in frames], dtype=float).reshape(-1, 3)
            h5["max_displacement_mm"] = np.array([np.linalg.norm(f.displacement, axis=1).max() for f in frames])
            h5["max_von_mises_mpa"] = np.array([f.von_mises.max() for f in frames])
            h5["plastic_volume_fraction"] = np.array([f.plastic_volume_fraction for f in frames], dtype=float)


def write_summary(path: Path, summary: dict) -> None:
    """``summary`` (JSON-ready) with ``toolkit_version``, written to ``path`` atomically."""

    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps({**summary, "toolkit_version": __version__}, indent=2))


def _write_partial(out: Path, scene: Scene, frames: list, exc: BaseException, wall_time_s: float,
                   fidelity=None) -> None:
    """The ``summary.json`` (and ``history.h5`` of the ``frames`` finished) of a run stopped by
    ``exc``: status ``interrupted`` for a ``KeyboardInterrupt``, else ``failed``."""
    interrupted = isinstance(exc, KeyboardInterrupt)
    stopped_at = getattr(exc, "time", None)
    summary = {
        "status": "interrupted" if interrupted else "failed",
        "reason": "interrupted (KeyboardInterrupt)" if interrupted else str(exc),
        "error": type(exc).__name__,
        "velocity_mm_s": scene.ball.velocity,
        "duration_s": scene.duration,
        "frames_written": len(frames),
        "frames_planned": int(scene.n_frames),
        "last_frame_time_s": float(frames[-1].time) if frames else None,
        "stopped_at_time_s": None if stopped_at is None else float(stopped_at),
        "wall_time_s": wall_time_s,
        **({} if fidelity is None else {"fidelity": fidelity.record()}),
    }
    if frames:
        _write_history(out / "history.h5", frames)
    write_summary(out / "summary.json", summary)


def write_preview(path: str | Path, face: Mesh, displacement: np.ndarray, von_mises: np.ndarray, time_s: float,
                  rigid_ball: tuple | None = None) -> Path:
    """``preview.png`` of one frame: the deformed face (``displacement (n, 3)`` mm) coloured by
    ``von_mises (n,)`` MPa, seen from the left, titled with ``time_s``; ``rigid_ball`` =
    ``(centre (3,) mm, radius mm)`` draws a rigid ball there, translucent."""

    shown = None if rigid_ball is None else ball_mesh(rigid_ball[1], "coarse", 1, centre=rigid_ball[0])
    render(face.with_point_data(von_mises=von_mises), path, scalars="von_mises", displacement=displacement,
           camera="left", cmap="inferno", scalar_label="von Mises (MPa)", title=f"t = {time_s:.2f} s",
           extra=[(shown, {"opacity": 0.35, "show_edges": False})] if shown is not None else ())
    return Path(path)
