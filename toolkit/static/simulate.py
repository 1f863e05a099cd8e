"""The incremental orthognathic simulation of seed 001 (section 2.3.2).

The bony movements of a :class:`~toolkit.static.plan.SurgicalPlan` are applied in
``increments`` steps (slerp for rotations, linear for translations). Each increment:

1. moving nodes follow their segment; fixed nodes stay; **mucosa** nodes slide on the
   moved bone surface (normal component prescribed: no separation, no penetration;
   tangential free); **lip** pairs across the mouth slit may not interpenetrate
   craniocaudally but slide otherwise (master-slave, active set);
2. the mucosa nodes are projected on the closest point of the moved bone surface and
   the increment is solved again with them prescribed there.

Linear materials follow seed 001: each increment is a small-strain solve on the
geometry left by the previous one (updated geometry, stress-free start). Neo-Hookean
is solved total-Lagrangian from the pre-operative face, the increments acting as load
steps. Every increment's cumulative displacement is kept: each is one learning sample
(seed 000).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Mapping

import numpy as np

from toolkit.common.materials import LinearElastic, NeoHookean, TransverselyIsotropic
from toolkit.common.mesh import Mesh
from toolkit.common.phantom import FacePhantom
from toolkit.common.surface_distance import closest_points
from toolkit.static.assembly import MaterialAssignment, SparsePattern
from toolkit.static.boundary import BoundaryConditions, NodeType
from toolkit.static.constraints import Constraints
from toolkit.static.fem import ConvergenceError, StaticProblem, solve_with_lip_contact
from toolkit.static.plan import SurgicalPlan

__all__ = ["simulate", "SimulationOptions", "SimulationResult", "IncrementReport", "SimulationError",
           "material_assignment", "SLIDING_MODELS", "MATERIALS"]

log = logging.getLogger(__name__)

SLIDING_MODELS = ("none", "mucosa", "mucosa+lip")
MATERIALS = ("linear", "neo-hookean")


class SimulationError(RuntimeError):
    """An increment diverged or inverted elements.

    Attributes: ``increment`` (1-based), ``element`` (worst element or None), ``suggestion``.
    """

    def __init__(self, message: str, increment: int, element: int | None, suggestion: str):
        super().__init__(f"increment {increment}: {message}. Suggestion: {suggestion}")
        self.increment, self.element, self.suggestion = increment, element, suggestion


@dataclass(frozen=True)
class SimulationOptions:
    """Numerical options of :func:`simulate`.

    Attributes
    ----------
    solver : linear solver (``auto``, ``superlu``, ``amg``, ``cholmod``)
    lip_threshold : mm, seed 001's collision-detection distance for lip pairs
    min_scaled_jacobian : an increment whose deformed mesh falls below this raises
    progress : show a tqdm bar over increments
    """

    solver: str = "auto"
    lip_threshold: float = 0.2
    min_scaled_jacobian: float = 0.0
    progress: bool = False


@dataclass(frozen=True)
class IncrementReport:
    """Diagnostics of one increment (lengths mm, times s)."""

    increment: int
    seconds_step1: float
    seconds_step2: float
    linear_solves: int
    newton_iterations: int
    contact_iterations: int
    min_scaled_jacobian: float
    worst_element: int
    mucosa_gap_before_projection: float
    mucosa_gap_after_projection: float
    max_penetration: float  # over the lip pairs, whether or not lip contact is modelled
    active_lip_pairs: int


@dataclass(frozen=True, eq=False)
class SimulationResult:
    """Everything an incremental simulation produced.

    Attributes
    ----------
    reference : Mesh — the pre-operative face
    displacements : (increments + 1, n, 3) mm — cumulative displacement after each
        increment (row 0 is zero)
    boundary : BoundaryConditions used (after the sliding model)
    reports : list of IncrementReport
    wall_time_s : float
    material, sliding : the options as given
    """

    reference: Mesh
    displacements: np.ndarray
    boundary: BoundaryConditions
    reports: list
    wall_time_s: float
    material: str
    sliding: str

    @property
    def displacement(self) -> np.ndarray:
        """Final displacement ``(n, 3)`` mm."""
        return self.displacements[-1]

    @property
    def final_mesh(self) -> Mesh:
        """The predicted post-operative face (with ``displacement`` and ``boundary_type`` fields)."""
        return self.reference.translated(self.displacement).with_point_data(
            displacement=self.displacement, boundary_type=self.boundary.types.astype(np.int32))

    def summary(self) -> dict:
        """JSON-ready summary (mm, s)."""
        mag = np.linalg.norm(self.displacement, axis=1)
        return {
            "nodes": self.reference.n_points,
            "elements": self.reference.n_cells,
            "increments": len(self.reports),
            "material": self.material,
            "sliding": self.sliding,
            "wall_time_s": self.wall_time_s,
            "max_displacement_mm": float(mag.max()),
            "mean_skin_displacement_mm": float(mag[self.reference.node_sets["skin"]].mean())
            if "skin" in self.reference.node_sets else None,
            "min_scaled_jacobian": float(min(r.min_scaled_jacobian for r in self.reports)),
            "max_penetration_mm": float(max(r.max_penetration for r in self.reports)),
            "max_mucosa_gap_mm": float(max(r.mucosa_gap_after_projection for r in self.reports)),
            "increments_report": [asdict(r) for r in self.reports],
        }

    def write(self, out: str | Path, preview: bool = True) -> Path:
        """Write ``result.vtu``, ``increments.xdmf`` (+ .h5), ``summary.json`` and ``preview.png``."""
        from toolkit.common.io import atomic_path, write, write_time_series

        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        write(out / "result.vtu", self.final_mesh)
        write_time_series(out / "increments.xdmf", self.reference.without_fields(),
                          np.arange(self.displacements.shape[0], dtype=float),
                          {"displacement": self.displacements})
        with atomic_path(out / "summary.json") as tmp:
            tmp.write_text(json.dumps(self.summary(), indent=2))
        if preview:
            from toolkit.common.plotting import render

            render(self.reference, out / "preview.png", scalars=self.displacement, displacement=self.displacement,
                   camera="iso", cmap="viridis", scalar_label="|u| (mm)",
                   title=f"{self.material}, {self.sliding}, {len(self.reports)} increments")
        return out


def material_assignment(material: str | MaterialAssignment, mesh: Mesh) -> MaterialAssignment:
    """Seed 001's materials: ``linear`` (isotropic E 0.003 MPa, nu 0.47, transversely
    isotropic lip muscle 0.009/0.003 MPa along its fibres) or ``neo-hookean`` (E 0.003 MPa,
    nu 0.47 everywhere)."""
    if isinstance(material, MaterialAssignment):
        return material
    if material == "linear":
        regions = {"lip_muscle": TransverselyIsotropic()} if "lip_muscle" in mesh.element_sets \
            and "fibre_direction" in mesh.cell_data else {}
        return MaterialAssignment(LinearElastic(), regions)
    if material == "neo-hookean":
        return MaterialAssignment(NeoHookean())
    raise ValueError(f"unknown material {material!r}; expected one of {MATERIALS} or a MaterialAssignment")


def _motion(plan: SurgicalPlan, name: str):
    return plan.motions.get(name) if hasattr(plan.motions, "get") else plan.motions[name]


def _apply(plan: SurgicalPlan, name: str, points: np.ndarray) -> np.ndarray:
    m = _motion(plan, name)
    return points if m is None else m.apply(points)


def simulate(
    face: Mesh | FacePhantom,
    plan: SurgicalPlan,
    increments: int = 3,
    material: str | MaterialAssignment = "linear",
    sliding: str = "mucosa+lip",
    *,
    segments: Mapping | None = None,
    options: SimulationOptions | None = None,
) -> SimulationResult:
    """Run seed 001's incremental simulation.

    Parameters
    ----------
    face : FacePhantom, or a Mesh with the node sets of the phantoms (then pass ``segments``)
    plan : SurgicalPlan (segments ``lefort``, ``distal``, ``proximal_left``, ``proximal_right``)
    increments : number of increments (seed 001: 3)
    material : ``linear``, ``neo-hookean`` or a MaterialAssignment
    sliding : ``mucosa+lip`` (seed 001), ``mucosa`` or ``none``
    segments : name -> BoneSegment (bone surfaces and attachment sets); default the phantom's
    options : SimulationOptions

    Returns
    -------
    SimulationResult — displacements ``(increments + 1, n, 3)`` mm and diagnostics

    Raises
    ------
    SimulationError naming the increment, the worst element and a suggestion.
    """
    from tqdm.auto import tqdm

    t_start = time.perf_counter()
    options = options or SimulationOptions()
    if isinstance(face, FacePhantom):
        mesh, segments = face.mesh, segments or face.segments
    else:
        mesh = face
    if segments is None:
        raise ValueError("a bare Mesh needs segments=... (name -> BoneSegment) for the bony surfaces")
    if sliding not in SLIDING_MODELS:
        raise ValueError(f"unknown sliding model {sliding!r}; expected one of {SLIDING_MODELS}")
    if int(increments) < 1:
        raise ValueError(f"increments must be >= 1, got {increments}")
    materials = material_assignment(material, mesh)
    material_name = material if isinstance(material, str) else "custom"
    bc_all = BoundaryConditions.from_mesh(mesh, segments, lip_threshold=options.lip_threshold)
    bc = bc_all.with_sliding(sliding)
    names = bc.segment_names
    X = mesh.points
    n = mesh.n_points
    moving = bc.nodes(NodeType.MOVING)
    fixed = bc.nodes(NodeType.FIXED)
    mucosa = bc.nodes(NodeType.MUCOSA_SLIDING)
    seg_of = bc.segment
    surfaces = {name: segments[name].surface for name in names}
    total_lagrangian = not materials.is_linear

    plans = plan.increments(int(increments))
    displacements = [np.zeros((n, 3))]
    reports = []
    x = X.copy()  # current configuration
    pattern: SparsePattern | None = None
    problem = StaticProblem(mesh, materials, options.solver) if total_lagrangian else None
    prev_plan = None
    bar = tqdm(plans, desc="increments", disable=not options.progress, leave=False)
    for k, plan_k in enumerate(bar, start=1):
        base = X if total_lagrangian else x  # configuration the displacement is measured from
        if not total_lagrangian:
            try:
                problem = StaticProblem(mesh.with_points(x), materials, options.solver, pattern)
            except ConvergenceError as exc:
                raise SimulationError(str(exc), k, None, "use more increments or a smaller movement") from exc
            pattern = problem.pattern
        # --- targets of this increment
        target = np.empty((n, 3))
        target[fixed] = X[fixed]
        for s, name in enumerate(names):
            ids = moving[seg_of[moving] == s]
            target[ids] = _apply(plan_k, name, X[ids])
        presc_nodes = np.concatenate([fixed, moving])
        presc_vals = target[presc_nodes] - base[presc_nodes]
        u_start = None if not total_lagrangian else displacements[-1]

        def run(constraints):
            if bc.upper_lip.size:
                res = solve_with_lip_contact(problem, constraints, bc.upper_lip, bc.lower_lip,
                                             threshold=options.lip_threshold, u_start=u_start)
                return res.solution, res
            return problem.solve(constraints, u_start=u_start), None

        t0 = time.perf_counter()
        try:
            # --- step 1: mucosa slides on the moved bone (normal prescribed, tangents free)
            gap_before = 0.0
            if mucosa.size:
                normals = np.empty((mucosa.size, 3))
                on_surface = np.empty((mucosa.size, 3))
                for s, name in enumerate(names):
                    sel = np.flatnonzero(seg_of[mucosa] == s)
                    if not sel.size:
                        continue
                    surf = surfaces[name]
                    prev_pts = surf.points if prev_plan is None else _apply(prev_plan, name, surf.points)
                    cp = closest_points(x[mucosa[sel]], prev_pts, surf.cells["tri3"])
                    # carry the closest point and normal rigidly with the increment's motion
                    new_pts = _apply(plan_k, name, surf.points)
                    tri = surf.cells["tri3"][cp.triangle]
                    bary = _barycentric(cp.point, prev_pts[tri])
                    on_surface[sel] = np.einsum("ij,ijk->ik", bary, new_pts[tri])
                    nrm = np.cross(new_pts[tri[:, 1]] - new_pts[tri[:, 0]], new_pts[tri[:, 2]] - new_pts[tri[:, 0]])
                    normals[sel] = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
                g = np.einsum("ij,ij->i", normals, on_surface - base[mucosa])
                c1 = Constraints(n, presc_nodes, presc_vals, mucosa, normals, g)
            else:
                c1 = Constraints(n, presc_nodes, presc_vals)
            sol1, contact1 = run(c1)
            t1 = time.perf_counter()
            sol, contact = sol1, contact1
            gap_after = 0.0
            if mucosa.size:
                # --- step 2: project the mucosa nodes onto the moved bone and re-solve
                pos = base[mucosa] + sol1.displacement[mucosa]
                proj = np.empty_like(pos)
                dist = np.empty(mucosa.size)
                for s, name in enumerate(names):
                    sel = np.flatnonzero(seg_of[mucosa] == s)
                    if sel.size:
                        surf = surfaces[name]
                        cp = closest_points(pos[sel], _apply(plan_k, name, surf.points), surf.cells["tri3"])
                        proj[sel], dist[sel] = cp.point, cp.distance
                gap_before = float(dist.max())
                c2 = Constraints(n, np.concatenate([presc_nodes, mucosa]),
                                 np.vstack([presc_vals, proj - base[mucosa]]))
                u_start = sol1.displacement
                sol, contact = run(c2)
                gap_after = float(np.abs(base[mucosa] + sol.displacement[mucosa] - proj).max())
        except ConvergenceError as exc:
            raise SimulationError(str(exc), k, None,
                                  "use more increments, a smaller movement, or the linear material") from exc
        t2 = time.perf_counter()
        u_k = sol.displacement
        total = u_k if total_lagrangian else displacements[-1] + u_k
        deformed = mesh.with_points(X + total)
        sj = deformed.scaled_jacobian()
        worst = int(np.argmin(sj))
        if sj[worst] <= options.min_scaled_jacobian:
            raise SimulationError(
                f"{int((sj <= options.min_scaled_jacobian).sum())} elements inverted or degenerate "
                f"(worst: element {worst}, scaled Jacobian {sj[worst]:.3g}, centroid "
                f"{np.round(deformed.points[deformed.volume_cells[worst]].mean(axis=0), 1).tolist()} mm)",
                k, worst, "use more increments or a smaller movement")
        displacements.append(total)
        x = X + total
        reports.append(IncrementReport(
            increment=k, seconds_step1=t1 - t0, seconds_step2=t2 - t1,
            linear_solves=len(sol1.solves) + (len(sol.solves) if sol is not sol1 else 0),
            newton_iterations=sol1.newton_iterations + (sol.newton_iterations if sol is not sol1 else 0),
            contact_iterations=(contact1.iterations if contact1 else 0) + (contact.iterations if contact and
                                                                            contact is not contact1 else 0),
            min_scaled_jacobian=float(sj[worst]), worst_element=worst,
            mucosa_gap_before_projection=gap_before, mucosa_gap_after_projection=gap_after,
            max_penetration=_penetration(X + total, bc_all.upper_lip, bc_all.lower_lip),
            active_lip_pairs=int(contact.active.sum()) if contact else 0))
        log.info("increment %d/%d: min SJ %.3f, max |u| %.2f mm", k, len(plans), sj[worst],
                 np.linalg.norm(total, axis=1).max())
        prev_plan = plan_k
    return SimulationResult(mesh, np.stack(displacements), bc, reports, time.perf_counter() - t_start,
                            material_name, sliding)


def _penetration(x: np.ndarray, upper: np.ndarray, lower: np.ndarray) -> float:
    """Largest craniocaudal overlap of paired upper/lower lip nodes, mm (0 if none).

    Measured for every sliding model, so that runs without lip contact show what it prevents.
    """
    if not upper.size:
        return 0.0
    return float(max(0.0, (x[lower, 2] - x[upper, 2]).max()))


def _barycentric(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentric coordinates ``(k, 3)`` of points ``p (k, 3)`` in triangles ``tri (k, 3, 3)``."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.stack([1 - v - w, v, w], axis=1)
