"""Build an impact scene into an explicit model, run it, and write its outputs.

Only what the scene needs is built: a rigid ball has no mesh (contact against the
analytic sphere), an elastic material (no yield table) skips the return mapping, and
contact is searched only once the ball is near the skin.

Outputs (:meth:`ImpactResult.write`): ``face.xdmf`` (+ ``.h5``; point data
``displacement`` mm and ``von_mises`` MPa per frame), ``ball.xdmf`` for a deformable ball,
``history.h5`` (times, energies, contact force, penetration), ``summary.json`` and
``preview.png``. Frames are appended to the files as the run goes (an interrupted run
keeps its finished frames).
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolkit.common.errors import ToolkitError
from toolkit.common.fem.kinematics import lumped_mass
from toolkit.common.materials import lame
from toolkit.common.mesh import Mesh
from toolkit.common.topology import boundary_faces
from toolkit.impact.contact import CoulombFriction, RigidSphereContact, SurfaceContact, penalty_stiffness
from toolkit.impact.elements import critical_time_step, tet_kinematics
from toolkit.impact.explicit import Body, ContactResponse, ExplicitModel, moving_sphere_contact, run_explicit
from toolkit.impact.plasticity import HardeningTable, J2Plasticity
from toolkit.impact.scene import MaterialSpec, Scene

__all__ = ["simulate", "ImpactResult", "build_model", "UnstableTimeStepError", "SceneGeometryWarning", "sweep_travel",
           "face_mesh", "fixed_nodes", "ball_start"]


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
    contact_pair: object = None  # the RigidSphereContact or SurfaceContact behind model.contact


def build_model(scene: Scene) -> BuiltScene:
    """Meshes, materials, masses, time step and contact for ``scene``: the face, the ball aimed
    at it (:func:`ball_start`, and a warning if its path reaches fixed nodes), each body with
    its lumped masses and stable step, the run's time step, and the contact callback."""
    face = face_mesh(scene)
    fixed = fixed_nodes(scene, face)
    centre0 = ball_start(scene, face.points[face.node_set("skin")])
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
    from toolkit.common.phantom import ball as ball_mesh

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
    if fid.dt is None or fid.integrator == "implicit":
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
    (the implicit path uses the same penalty, so both paths solve the same contact problem)."""
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
    from toolkit.common.io import read
    from toolkit.common.phantom import face_tet

    if scene.face.mesh:
        needed = [scene.face.fixed_set, "skin"] + (["bone"] if scene.face.support == "skull" else [])
        return read(scene.face.mesh, require_node_sets=needed)
    return face_tet(scene.face.resolution, order=scene.fidelity.order,
                    lower_fixed_fraction=scene.face.lower_fixed_fraction)


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
    """

    scene: Scene
    face: Mesh
    ball: Mesh | None
    times: np.ndarray
    displacement: np.ndarray
    von_mises: np.ndarray
    equivalent_plastic_strain: np.ndarray
    energies: object
    contact_force: np.ndarray
    stats: dict
    plastic_volume_fraction: np.ndarray | None = None

    def summary(self) -> dict:
        mag = np.linalg.norm(self.displacement, axis=2)
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
        }


def _run(scene: Scene, built: BuiltScene, on_frame, progress: bool) -> tuple[list, dict]:
    """The scene's integrator over its duration: frames and statistics."""
    if scene.fidelity.integrator == "explicit":
        return run_explicit(built.model, scene.duration, scene.n_frames, on_frame=on_frame, progress=progress)
    from toolkit.impact.implicit import ImplicitOptions, StepContact, run_quasistatic

    fid = scene.fidelity
    contact = StepContact(built.contact_pair, built.model.points.shape[0], built.ball_centre,
                          scene.ball.velocity * np.asarray(scene.ball.direction, dtype=float))
    options = ImplicitOptions(steps=fid.load_steps, tolerance=fid.tolerance)
    return run_quasistatic(built.model, contact, scene.duration, scene.n_frames, options, on_frame=on_frame,
                           progress=progress)


def simulate(scene: Scene, out: str | Path | None = None, progress: bool = False, preview: bool = True) -> ImpactResult:
    """Run ``scene``; with ``out``, stream frames to ``out/face.xdmf`` (and ``ball.xdmf``) and write
    ``history.h5``, ``summary.json`` and ``preview.png``.
    """
    import pandas as pd

    from toolkit.common.io import TimeSeriesWriter, atomic_path

    t0 = time.perf_counter()
    built = build_model(scene)
    writers = []
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        writers.append(TimeSeriesWriter(out / "face.xdmf", built.face.without_fields()))
        if built.ball is not None:
            writers.append(TimeSeriesWriter(out / "ball.xdmf", built.ball.without_fields()))

    def on_frame(frame, fields):
        for w, f in zip(writers, fields):
            w.append(frame.time, displacement=f["displacement"], von_mises=f["von_mises"])

    try:
        frames, stats = _run(scene, built, on_frame, progress)
    finally:
        for w in writers:
            w.close()
    stats["dt_critical_s"] = built.dt_critical
    stats["added_mass_fraction"] = built.added_mass_fraction
    stats["fixed_clearance_mm"] = built.fixed_clearance_mm
    stats["wall_time_s"] = time.perf_counter() - t0
    energies = pd.DataFrame([{"time_s": f.time, **f.energies.__dict__, "balance_error": f.energies.balance_error}
                             for f in frames])
    result = ImpactResult(scene, built.face, built.ball, np.array([f.time for f in frames]),
                          np.stack([f.displacement for f in frames]), np.stack([f.von_mises for f in frames]),
                          np.stack([f.equivalent_plastic_strain for f in frames]), energies,
                          np.stack([f.contact_force for f in frames]), stats,
                          np.array([f.plastic_volume_fraction for f in frames]))
    if out is not None:
        import h5py

        with atomic_path(out / "history.h5") as tmp:
            with h5py.File(tmp, "w") as h5:
                h5["time_s"] = result.times
                for col in energies.columns:
                    h5[f"energies/{col}"] = energies[col].to_numpy()
                h5["contact_force_n"] = result.contact_force
                h5["max_displacement_mm"] = np.linalg.norm(result.displacement, axis=2).max(axis=1)
                h5["max_von_mises_mpa"] = result.von_mises.max(axis=1)
                h5["plastic_volume_fraction"] = result.plastic_volume_fraction
        with atomic_path(out / "summary.json") as tmp:
            tmp.write_text(json.dumps(result.summary(), indent=2))
        if preview:
            from toolkit.common.phantom import ball as ball_mesh
            from toolkit.common.plotting import render

            centre = built.ball_centre + scene.ball.velocity * np.asarray(scene.ball.direction) * result.times[-1]
            shown_ball = ball_mesh(scene.ball.radius, "coarse", 1, centre=centre) if built.ball is None else None
            render(built.face.with_point_data(von_mises=result.von_mises[-1]), out / "preview.png",
                   scalars="von_mises", displacement=result.displacement[-1], camera="left", cmap="inferno",
                   scalar_label="von Mises (MPa)", title=f"t = {result.times[-1]:.2f} s",
                   extra=[(shown_ball, {"opacity": 0.35, "show_edges": False})] if shown_ball is not None else ())
    return result
