"""The incremental orthognathic simulation of the lip-sliding paper (section 2.3.2).

The bony movements of a :class:`~toolkit.static.plan.SurgicalPlan` are applied in
``increments`` steps (slerp for rotations, linear for translations). Each increment:

1. moving nodes follow their segment; fixed nodes stay; **mucosa** nodes slide at their
   pre-operative distance from the moved bone surface (normal component prescribed: no
   separation, no penetration; tangential free); **lip** pairs across the mouth slit may not
   interpenetrate craniocaudally but slide otherwise (master-slave, active set);
2. each mucosa node is projected on the closest point of the moved bone surface plus its
   pre-operative offset ``d0`` along the normal there (the offset surface), and the
   increment is solved again with them prescribed there. A bone surface is an open patch: a
   node that slid past its edge is projected onto the plane of the edge triangle (the
   surface extended, offset likewise), not onto the edge line, which would gather every such
   node on one line and crush the elements between them.

The offset ``d0`` of a mucosa node is its distance to its bone surface (extended beyond the
rim) on the pre-operative mesh. A segmented face never puts the tissue exactly on the bone
(1-3 mm, up to 20 mm, on a real face): projecting the mucosa onto the bone itself would jump
its nodes by millimetres at the first increment and invert the elements between them and the
skin (:func:`toolkit.common.phantoms.off_bone.off_bone` reproduces this). A node farther than
``max_mucosa_offset`` (5 mm) from its bone does not slide (it is left free): the offset surface of
a rough bone has creases at such distances, and nodes sliding on it jump
(``benchmarks/off_bone.py``). The result's summary gives the offsets (``mucosa_offset_mm``) and
the nodes left free (``far_mucosa_nodes``).

Linear materials follow the lip-sliding paper: each increment is a small-strain solve on the
geometry left by the previous one (updated geometry, stress-free start). Neo-Hookean
is solved total-Lagrangian from the pre-operative face, the increments acting as load
steps. Every increment's cumulative displacement is kept: each is one learning sample
(the PointNet++ paper).

These safeguards keep the physiological plan space simulable (``benchmarks/static_robustness.py``):

- **release bands** (:meth:`~toolkit.static.boundary.BoundaryConditions.with_release_bands`):
  tissue within ``release_width / 2`` of a border between differently driven regions
  (osteotomy lines, the occlusal level between the jaws, segment next to fixed skull)
  is bound to neither side, as the stripped periosteum is; otherwise the boundary
  displacement jumps across a single element, which inverts it as the mesh is refined;
- **mesh regulation** (the lip-sliding paper, linear materials): when a step leaves elements below
  ``regulation_below`` quality, the free nodes around them that are not on the skin are
  moved to improve them (:func:`~toolkit.static.regulation.regulate`); each linear
  increment restarts stress-free, so nothing else changes. The skin, every constrained
  node and the lip pairs stay where the solve put them;
- **automatic increment cutting** (FEBio's auto time stepper): a step that inverts an
  element (even after regulation) or does not converge is retried as two half steps,
  down to ``2 ** max_cuts`` sub-steps per increment. Sub-steps are internal: the stored
  increments stay at fractions ``k / increments`` of the plan;
- **wider release bands** for the largest movements: a plan that cannot be simulated with
  ``release_width`` (even cut) is run again with each of ``wider_release`` in turn. Where a
  segment moves far towards a differently driven neighbour (a Le Fort I segment lifted
  ~9 mm at its lateral edge towards the fixed skull 10 mm away) the band between them cannot
  take the compression; surgically, larger movements need a wider subperiosteal
  dissection. The result reports the band it used (``release_width_mm``);
- **freeing the held cut**: a model of the face is truncated behind the ramus, and the cut is
  held (fixed) above the condyles. Where a plan drags the tissue just below the held part
  (a large proximal-segment rotation with a setback and yaw of the distal mandible), the
  clamped-to-free corner at the lower end of the held cut inverts the skin element there,
  worse as the mesh is refined (plan 10 of the full sampler at ``fine``); on a meshed face the
  held upper cut pins the cheek above a lifted maxilla alike. When the element that blocks a
  plan lies within ``free_cut_radius`` of a fixed node off the bone (the ``bone`` node set),
  the fixed nodes off the bone within that distance of it are freed for the rest of the run and
  the step is tried again: the truncation moves locally, the bony boundary conditions do not
  change. The result lists them (``freed_cut_nodes``).
"""

from __future__ import annotations

import json
import logging
import time
import warnings
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from toolkit import __version__
from toolkit.common.analysis.surface_distance import ClosestPoints, barycentric, beyond_rim_onto_plane, closest_points
from toolkit.common.defaults import STATIC_SIMULATION
from toolkit.common.errors import ToolkitError
from toolkit.common.fem.assembly import SparsePattern
from toolkit.common.fem.materials import LinearElastic, NeoHookean, TransverselyIsotropic
from toolkit.common.fem.solvers import SolverError, require_method
from toolkit.common.meshes.io import atomic_path, write, write_time_series
from toolkit.common.meshes.mesh import Mesh
from toolkit.common.meshes.topology import rim_edges, tet10_mid_edges
from toolkit.common.phantoms.phantom import FacePhantom
from toolkit.common.runtime import count_finished
from toolkit.static.boundary import DEFAULT_RELEASE_WIDTH, BoundaryConditions, NodeType
from toolkit.static.checks import MIN_CARRIED_MM2, MIN_CARRIED_SHARE, check_answer, check_plan
from toolkit.static.constraints import Constraints
from toolkit.static.plan import PlanRangeWarning, SurgicalPlan
from toolkit.static.problem import ConvergenceError, StaticProblem, solve_with_lip_contact
from toolkit.static.regulation import element_quality, regulate
from toolkit.static.stiffness import MaterialAssignment

__all__ = ["simulate", "SimulationOptions", "SimulationResult", "IncrementReport", "SimulationError",
           "material_assignment", "SLIDING_MODELS", "MATERIALS"]

log = logging.getLogger(__name__)

SLIDING_MODELS = ("none", "mucosa", "mucosa+lip")
MATERIALS = ("linear", "neo-hookean")
_MAX_CUT_FREEINGS = 3  # times a run may free more of the cut
_MAX_MUCOSA_FREED = 0.1  # share of the sliding mucosa a run may free around folding elements
_CUTS_BEFORE_FREEING = 2  # a step is cut this many times before the cut or mucosa around its failure is freed
_OFFSET_ITERATIONS = 20  # most repeated projections onto the offset surface of a mucosa node (_onto_offset)


class SimulationError(ToolkitError, RuntimeError):
    """An increment diverged or inverted elements even after cutting it.

    Attributes: ``increment`` (1-based), ``element`` (worst element or None), ``suggestion``,
    ``reason`` (what went wrong, without the increment and the suggestion).
    """

    def __init__(self, message: str, increment: int, element: int | None, suggestion: str):
        super().__init__(f"increment {increment}: {message}. Suggestion: {suggestion}")
        self.reason, self.increment, self.element, self.suggestion = message, increment, element, suggestion


class _StepFailure(RuntimeError):
    """One (sub-)step inverted an element or did not converge; ``element`` may be None."""

    def __init__(self, message: str, element: int | None = None):
        super().__init__(message)
        self.element = element


@dataclass(frozen=True)
class SimulationOptions:
    """Numerical options of :func:`simulate`.

    Attributes
    ----------
    solver : linear solver (``auto``, ``superlu``, ``pardiso``, ``amg``, ``cholmod``; see
        :mod:`toolkit.common.fem.solvers`)
    lip_threshold : mm, the lip-sliding paper's collision-detection distance for lip pairs
    min_scaled_jacobian : a step whose deformed mesh has an element at or below this
        (minimum corner scaled Jacobian) is cut, and the run fails if cutting cannot help
    release_width : mm, width of the bands of tissue bound to neither side along the borders
        between differently driven regions (0: none)
    wider_release : mm, wider bands to retry a plan with, in turn, when it cannot be simulated
        with ``release_width`` (those not wider than it are skipped; ``()``: never retry; the
        result's ``release_width`` says which band was used)
    regulation_below : linear materials: a step that leaves an element below this scaled
        Jacobian, and below half its own pre-operative value, regulates the mesh around it
        (towards twice this value, at most the element's pre-operative quality, so the poor
        elements of a real mesh are kept from inverting rather than remeshed; None: never;
        Neo-Hookean never regulates)
    max_cuts : how many times a failing increment may be halved (``2 ** max_cuts`` sub-steps)
    free_cut_radius : mm; when the element that blocks a plan lies within this distance of a
        fixed node off the bone (the truncation cut of the face; meshes without a ``bone`` node
        set have none) and a step cut twice still fails there, the fixed nodes off the bone within
        this distance of its centroid are freed for the rest of the run and the step is tried
        again (at most three times a run; 0: never)
    max_mucosa_offset : mm; a mucosa node farther than this from its bone surface on the
        pre-operative mesh is left free instead of sliding (inf: every mucosa node slides)
    free_mucosa_radius : mm; when a step cut twice (or ``max_cuts`` times, if fewer) still
        inverts an element, the sliding mucosa nodes within this distance of that element's
        centroid are freed for the rest of the run and the step is tried again (at most
        a tenth of the sliding mucosa per run; the result's ``freed_mucosa`` lists them; 0: never)
    min_carried_mm2 : mm^2; a plan that moves the Le Fort I or distal segment is refused before
        any solve when that segment's attached set covers less of the tissue's boundary
        (:func:`~toolkit.static.checks.check_plan`; 0: only an empty set is refused)
    min_carried_share : the same when the attached set covers less than this share of the tissue
        on the segment's bone (its attached and sliding mucosa sets; 0: no share is required)
    progress : show a tqdm bar over increments
    """

    solver: str = "auto"
    lip_threshold: float = 0.2
    min_scaled_jacobian: float = 0.0
    release_width: float = DEFAULT_RELEASE_WIDTH
    wider_release: tuple[float, ...] = (15.0, 20.0)
    regulation_below: float | None = 0.1
    max_cuts: int = 4
    free_cut_radius: float = 6.0
    max_mucosa_offset: float = 5.0
    free_mucosa_radius: float = 6.0
    min_carried_mm2: float = MIN_CARRIED_MM2
    min_carried_share: float = MIN_CARRIED_SHARE
    progress: bool = False

    def __post_init__(self):
        require_method(self.solver)
        if int(self.max_cuts) != self.max_cuts or self.max_cuts < 0:
            raise ValueError(f"max_cuts = {self.max_cuts!r}; expected an integer >= 0")
        if not np.isfinite(self.release_width) or self.release_width < 0:
            raise ValueError(f"release_width = {self.release_width!r} mm; expected a finite number >= 0")
        if not np.isfinite(self.free_cut_radius) or self.free_cut_radius < 0:
            raise ValueError(f"free_cut_radius = {self.free_cut_radius!r} mm; expected a finite number >= 0")
        if not np.isfinite(self.free_mucosa_radius) or self.free_mucosa_radius < 0:
            raise ValueError(f"free_mucosa_radius = {self.free_mucosa_radius!r} mm; expected a finite number >= 0")
        if not 0 <= self.min_carried_share <= 1:
            raise ValueError(f"min_carried_share = {self.min_carried_share!r}; expected a share in [0, 1]")
        if not self.max_mucosa_offset >= 0:
            raise ValueError(f"max_mucosa_offset = {self.max_mucosa_offset!r} mm; expected a number >= 0 (inf: "
                             f"no limit)")
        wider = tuple(float(w) for w in self.wider_release)
        if any(not np.isfinite(w) or w <= 0 for w in wider) or list(wider) != sorted(set(wider)):
            raise ValueError(f"wider_release = {self.wider_release!r} mm; expected increasing positive widths")
        object.__setattr__(self, "wider_release", wider)


@dataclass(frozen=True)
class IncrementReport:
    """Diagnostics of one increment, summed over its sub-steps (lengths mm, times s)."""

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
    substeps: int = 1
    failed_attempts: int = 0
    regulated_nodes: int = 0
    max_regulation_shift: float = 0.0


#: the ``boundary_type`` point field's codes (:class:`~toolkit.static.boundary.NodeType`), as
#: ``summary.json`` lists them
BOUNDARY_TYPE_CODES = {"0": "free", "1": "moving with a bone", "2": "fixed",
                       "3": "mucosa sliding on its bone", "4": "lip sliding on the other lip"}


@dataclass(frozen=True, eq=False)
class SimulationResult:
    """Everything an incremental simulation produced.

    Attributes
    ----------
    reference : Mesh — the pre-operative face
    displacements : (increments + 1, n, 3) mm — cumulative displacement after each
        increment (row 0 is zero)
    boundary : BoundaryConditions used (after the sliding model and the release bands)
    reports : list of IncrementReport
    wall_time_s : float
    material, sliding : the options as given
    release_width : mm, the release band the run used (wider than asked when the plan needed
        one of ``SimulationOptions.wider_release``; None when not applicable, e.g. a surrogate)
    freed_cut : (k,) int64 — fixed nodes of the truncation cut the plan needed freed
        (``SimulationOptions.free_cut_radius``; empty for almost every plan)
    mucosa_offset : (m,) float, mm — distance of each mucosa node of the sliding model (outside
        the release bands, those left free as ``far_mucosa`` included) to its bone surface on
        the pre-operative mesh; empty without mucosa sliding
    far_mucosa : (f,) int64 — mucosa nodes left free as farther than
        ``SimulationOptions.max_mucosa_offset`` from their bone
    freed_mucosa : (g,) int64 — sliding mucosa nodes freed during the run around elements that
        would otherwise have folded (``SimulationOptions.free_mucosa_radius``; sliding before the
        increment that freed them, free after it; ``boundary`` has them free)
    fidelity : the record of the :class:`~toolkit.common.fidelity.FidelityChoice` the run took
        its options from (``summary()["fidelity"]``), or None
    checks : ``{"plan": ..., "answer": ...}``, the values :func:`~toolkit.static.checks.check_plan`
        and :func:`~toolkit.static.checks.check_answer` checked (``summary()["checks"]``), or None
    plan : the SurgicalPlan that ran (written as ``plan.toml`` beside the result), or None
    """

    reference: Mesh
    displacements: np.ndarray
    boundary: BoundaryConditions
    reports: list
    wall_time_s: float
    material: str
    sliding: str
    release_width: float | None = None
    freed_cut: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    mucosa_offset: np.ndarray = field(default_factory=lambda: np.zeros(0))
    far_mucosa: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    freed_mucosa: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    fidelity: dict | None = None
    checks: dict | None = None
    plan: SurgicalPlan | None = None

    @property
    def displacement(self) -> np.ndarray:
        """Final displacement ``(n, 3)`` mm."""
        return self.displacements[-1]

    @property
    def reference_mesh(self) -> Mesh:
        """The pre-operative face with point fields ``displacement`` (mm) and ``boundary_type``
        (:data:`BOUNDARY_TYPE_CODES`): the usual convention (ParaView's Warp By Vector gives the
        post-operative face)."""
        return self.reference.with_point_data(displacement=self.displacement,
                                              boundary_type=self.boundary.types.astype(np.int32))

    @property
    def final_mesh(self) -> Mesh:
        """The predicted post-operative face (deformed points, field ``boundary_type`` only)."""
        return self.reference.translated(self.displacement).with_point_data(
            boundary_type=self.boundary.types.astype(np.int32))

    def summary(self) -> dict:
        """JSON-ready summary (mm, s); ``fidelity`` when the options were chosen by a tolerance."""
        mag = np.linalg.norm(self.displacement, axis=1)
        fidelity = {} if self.fidelity is None else {"fidelity": self.fidelity}
        return {
            "nodes": self.reference.n_points,
            "elements": self.reference.n_cells,
            "increments": len(self.reports),
            "material": self.material,
            "sliding": self.sliding,
            "wall_time_s": self.wall_time_s,
            "seconds_per_increment": [r.seconds_step1 + r.seconds_step2 for r in self.reports],
            "max_displacement_mm": float(mag.max()),
            "mean_skin_displacement_mm": float(mag[self.reference.node_sets["skin"]].mean())
            if "skin" in self.reference.node_sets else None,
            "min_scaled_jacobian": float(min(r.min_scaled_jacobian for r in self.reports)),
            "max_penetration_mm": float(max(r.max_penetration for r in self.reports)),
            "max_mucosa_gap_mm": float(max(r.mucosa_gap_after_projection for r in self.reports)),
            "mucosa_offset_mm": _offset_statistics(self.mucosa_offset),
            "far_mucosa_nodes": int(np.size(self.far_mucosa)),
            "released_nodes": int(self.boundary.released.size),
            "release_width_mm": self.release_width,
            "freed_cut_nodes": int(np.size(self.freed_cut)),
            "freed_mucosa_nodes": int(np.size(self.freed_mucosa)),
            "substeps": int(sum(r.substeps for r in self.reports)),
            "increments_cut": int(sum(r.substeps > 1 for r in self.reports)),
            "regulated_nodes": int(sum(r.regulated_nodes for r in self.reports)),
            "max_regulation_shift_mm": float(max(r.max_regulation_shift for r in self.reports)),
            "increments_report": [asdict(r) for r in self.reports],
            **({} if self.checks is None else {"checks": self.checks}),
            **fidelity,
            "boundary_type_codes": BOUNDARY_TYPE_CODES,
            "toolkit_version": __version__,
        }

    def write(self, out: str | Path, preview: bool = True, point_data: Mapping | None = None) -> Path:
        """Write ``result.vtu`` (pre-operative face with ``displacement`` and any ``point_data``,
        name -> ``(n, ...)`` array), ``postop.vtu`` (the post-operative face), ``summary.json``,
        ``increments.xdmf`` (+ .h5, one XDMF ``Mixed`` topology for a mesh of several cell types),
        ``plan.toml`` (the plan that ran, when the result holds it) and ``preview.png``.

        ``summary.json`` comes last, so a folder holding it holds the whole result; a write that
        fails (a full disk) removes the files this call wrote before raising."""

        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        names = ["result.vtu", "postop.vtu", "plan.toml", "increments.xdmf", "increments.h5", "preview.png",
                 "summary.json"]
        before = {name for name in names if (out / name).exists()}
        try:
            write(out / "result.vtu", self.reference_mesh.with_point_data(**(point_data or {})))
            write(out / "postop.vtu", self.final_mesh)
            if self.plan is not None:
                self.plan.write(out / "plan.toml")
            write_time_series(out / "increments.xdmf", self.reference.without_fields(),
                              np.arange(self.displacements.shape[0], dtype=float),
                              {"displacement": self.displacements})
            if preview:
                from toolkit.common.plotting import render

                render(self.reference, out / "preview.png", scalars=self.displacement,
                       displacement=self.displacement, camera="iso", cmap="viridis", scalar_label="|u| (mm)",
                       title=f"{self.material}, {self.sliding}, {len(self.reports)} increments")
            with atomic_path(out / "summary.json") as tmp:
                tmp.write_text(json.dumps(self.summary(), indent=2))
        except BaseException:
            for name in set(names) - before:
                (out / name).unlink(missing_ok=True)
            raise
        return out


def material_assignment(material: str | MaterialAssignment, mesh: Mesh) -> MaterialAssignment:
    """The lip-sliding paper's materials: ``linear`` (isotropic E 0.003 MPa, nu 0.47, transversely
    isotropic lip muscle 0.009/0.003 MPa along its fibres) or ``neo-hookean`` (E 0.003 MPa,
    nu 0.47 everywhere).

    The lip muscle is the element set ``lip_muscle``, its fibres the cell field
    ``fibre_direction``; a mesh with the set but not the field gets an isotropic lip muscle and a
    warning (:func:`~toolkit.static.case.load_case` derives the field first)."""
    if isinstance(material, MaterialAssignment):
        return material
    if material == "linear":
        if "lip_muscle" not in mesh.element_sets:
            return MaterialAssignment(LinearElastic())
        if "fibre_direction" not in mesh.cell_data:
            warnings.warn("the mesh has a 'lip_muscle' element set but no 'fibre_direction' cell field (an Abaqus "
                          "file keeps none): the lip muscle is isotropic; load the mesh with load_case, which gives "
                          "it the superior fibres of toolkit.common.fem.fibres, or write it as VTU", stacklevel=2)
            return MaterialAssignment(LinearElastic())
        return MaterialAssignment(LinearElastic(), {"lip_muscle": TransverselyIsotropic()})
    if material == "neo-hookean":
        return MaterialAssignment(NeoHookean())
    raise ValueError(f"unknown material {material!r}; expected one of {MATERIALS} or a MaterialAssignment")


# ------------------------------------------------------------------ the model
@dataclass(eq=False)
class _Model:
    """What every step of one simulation shares (built once by :func:`simulate`)."""

    mesh: Mesh
    materials: MaterialAssignment
    bc: BoundaryConditions  # after the sliding model
    bc_all: BoundaryConditions  # lip pairs whatever the sliding model (for the penetration report)
    surfaces: dict
    options: SimulationOptions
    total_lagrangian: bool
    pattern: SparsePattern | None = None
    orderings: dict = field(default_factory=dict)  # system size -> fill-reducing ordering, for every step
    reference_problem: StaticProblem | None = None
    guess: np.ndarray | None = None  # (increments + 1, n, 3) mm, a predicted displacement after each increment
    moving: np.ndarray = field(init=False)
    fixed: np.ndarray = field(init=False)
    mucosa: np.ndarray = field(init=False)
    movable: np.ndarray = field(init=False)
    quality0: np.ndarray = field(init=False)
    rims: dict = field(init=False)  # segment name -> rim edges of its bone surface
    mucosa_offset: np.ndarray = field(init=False)  # pre-operative offset of every mucosa node of the sliding model
    far_mucosa: np.ndarray = field(init=False)  # of those, the ones left free (beyond max_mucosa_offset)
    offset: np.ndarray = field(init=False)  # (m,) mm, offset d0 of each sliding mucosa node
    side: np.ndarray = field(init=False)  # (m,) +-1, side of its bone triangle's normal it lies on
    # tet10 mid-edge mucosa nodes and their edges (:func:`_edge_followers`)
    edge_followers: tuple = field(init=False)
    # nodes freed during the run around elements that folded (:meth:`free_near`)
    freed_cut: np.ndarray = field(init=False)
    cut_freeings: int = field(init=False)
    freed_mucosa: np.ndarray = field(init=False)

    def __post_init__(self):
        self.quality0 = element_quality(self.mesh, self.mesh.points)
        self.rims = {name: rim_edges(surf.cells["tri3"]) for name, surf in self.surfaces.items()}
        mucosa = self.bc.nodes(NodeType.MUCOSA_SLIDING)
        offset, side = self._offsets(mucosa)
        far = offset > self.options.max_mucosa_offset
        self.mucosa_offset, self.far_mucosa = offset, mucosa[far]
        if far.any():  # freed far mucosa frees the middle of its edges, as the bands and the cut do
            self.bc = self.bc.with_freed(self.far_mucosa).with_mid_edges_of_corners(self.mesh)
        self.moving = self.bc.nodes(NodeType.MOVING)
        self.fixed = self.bc.nodes(NodeType.FIXED)
        self.mucosa = self.bc.nodes(NodeType.MUCOSA_SLIDING)
        sliding = np.isin(mucosa, self.mucosa)  # the offsets of the nodes still sliding, in their order
        self.offset, self.side = offset[sliding], side[sliding]
        self.edge_followers = _edge_followers(self.mesh, self.mucosa)
        self.freed_mucosa = np.zeros(0, np.int64)
        self.freed_cut, self.cut_freeings = np.zeros(0, np.int64), 0
        # what regulation may move: free nodes off the skin (the prediction) and off the lip pairs,
        # and mucosa nodes along their bone (they are put back on it exactly afterwards)
        movable = np.isin(self.bc.types, (NodeType.FREE, NodeType.MUCOSA_SLIDING))
        if "skin" in self.mesh.node_sets:
            movable[self.mesh.node_sets["skin"]] = False
        else:
            from toolkit.common.meshes.topology import triangulated_boundary

            movable[np.unique(triangulated_boundary(self.mesh.cells))] = False
        movable[self.bc_all.upper_lip] = False
        movable[self.bc_all.lower_lip] = False
        self.movable = movable

    def free_near(self, element: int | None) -> str | None:
        """Free, for the rest of the run, what holds the tissue around ``element`` (its
        pre-operative centroid): the fixed nodes of the truncation cut within
        ``options.free_cut_radius`` mm (:func:`_cut_near`; at most ``_MAX_CUT_FREEINGS`` times a
        run) or else the sliding mucosa nodes within ``options.free_mucosa_radius`` mm (until
        ``_MAX_MUCOSA_FREED`` of the mucosa sliding at the start is free), with the ``tet10``
        mid-edge nodes of their edges. Returns what was freed, in words, or None, changing
        nothing, when neither applies.

        The truncation is where the model ends, not anatomy: freeing it near the element moves
        the model's edge locally. Where a real face's mucosa is thinner than one element, an
        element has two to four corners sliding on the bone, and a moving curved or sharp bone
        can leave it no shape to take: freeing that patch lets the mucosa part from the bone
        there instead of folding."""
        if element is None:
            return None
        cut = _cut_near(self, element)
        if cut.size and self.cut_freeings < _MAX_CUT_FREEINGS:
            self._free(cut)
            self.freed_cut, self.cut_freeings = np.union1d(self.freed_cut, cut), self.cut_freeings + 1
            return f"{cut.size} fixed nodes of the cut within {self.options.free_cut_radius:g} mm of that element"
        radius, X = self.options.free_mucosa_radius, self.mesh.points
        if radius <= 0 or not self.mucosa.size:
            return None
        centroid = X[_element_nodes(self.mesh, element)].mean(axis=0)
        near = self.mucosa[np.linalg.norm(X[self.mucosa] - centroid, axis=1) < radius]
        sliding_at_start = self.mucosa.size + self.freed_mucosa.size  # _free moves each freed one there
        if not near.size or self.freed_mucosa.size + near.size > _MAX_MUCOSA_FREED * sliding_at_start:
            return None
        self._free(near)
        return f"{near.size} sliding mucosa nodes within {radius:g} mm of that element ({self.freed_mucosa.size} " \
               f"freed so far)"

    def _free(self, nodes: np.ndarray) -> None:
        """Make ``nodes`` free (and the ``tet10`` mid-edge nodes of their edges), keeping the
        offsets of the mucosa nodes still sliding; the sliding nodes freed join ``freed_mucosa``."""
        before = self.mucosa
        self.bc = self.bc.with_freed(nodes).with_mid_edges_of_corners(self.mesh)
        self.moving = self.bc.nodes(NodeType.MOVING)
        self.fixed = self.bc.nodes(NodeType.FIXED)
        self.mucosa = self.bc.nodes(NodeType.MUCOSA_SLIDING)
        sliding = np.isin(before, self.mucosa)
        self.offset, self.side = self.offset[sliding], self.side[sliding]
        self.edge_followers = _edge_followers(self.mesh, self.mucosa)
        self.freed_mucosa = np.union1d(self.freed_mucosa, before[~sliding])

    def _offsets(self, mucosa: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance (mm) of the ``mucosa`` nodes to their bone surface extended beyond its rim
        on the pre-operative mesh, and the side (+-1) of the closest triangle they lie on."""
        X = self.mesh.points
        offset, side = np.zeros(mucosa.size), np.ones(mucosa.size)
        seg = self.bc.segment[mucosa]
        for s, name in enumerate(self.bc.segment_names):
            sel = np.flatnonzero(seg == s)
            if sel.size:
                ext = _on_extended(X[mucosa[sel]], self.surfaces[name].points, self.surfaces[name], self.rims[name])
                offset[sel] = ext.distance
                side[sel] = np.where(np.einsum("ij,ij->i", X[mucosa[sel]] - ext.point, ext.normal) < 0, -1.0, 1.0)
        return offset, side

    def guess_at(self, fraction: float) -> np.ndarray | None:
        """The initial guess's displacement ``(n, 3)`` mm at ``fraction`` of the plan (linear
        between increments), or None without one."""
        if self.guess is None:
            return None
        t = fraction * (self.guess.shape[0] - 1)
        k = min(int(np.floor(t)), self.guess.shape[0] - 2)
        return self.guess[k] + (t - k) * (self.guess[k + 1] - self.guess[k])

    def problem(self, x: np.ndarray) -> StaticProblem:
        """The problem a step solves: on the current geometry ``x`` (linear, updated) or on
        the pre-operative face (Neo-Hookean, total Lagrangian)."""
        if self.total_lagrangian:
            if self.reference_problem is None:
                self.reference_problem = StaticProblem(self.mesh, self.materials, self.options.solver,
                                                       orderings=self.orderings)
            return self.reference_problem
        try:
            problem = StaticProblem(self.mesh.with_points(x), self.materials, self.options.solver, self.pattern,
                                    orderings=self.orderings)
        except ConvergenceError as exc:
            raise _StepFailure(str(exc)) from exc
        self.pattern = problem.pattern
        return problem


@dataclass(frozen=True, eq=False)
class _State:
    """Where the simulation stands: plan fraction, total displacement ``u (n, 3)`` mm, the
    lip pairs tied at the end of the last step (None before the first) and, for a linear
    material, the last step's displacement per unit of plan fraction ``rate (n, 3)`` mm (None
    before the first), which predicts the next step's."""

    fraction: float
    plan: SurgicalPlan | None  # the plan at ``fraction`` (None before the first step)
    u: np.ndarray
    active: np.ndarray | None = None
    rate: np.ndarray | None = None


@dataclass(frozen=True)
class _StepDiagnostics:
    seconds_step1: float
    seconds_step2: float
    linear_solves: int
    newton_iterations: int
    contact_iterations: int
    min_scaled_jacobian: float
    worst_element: int
    gap_before: float
    gap_after: float
    active_lip_pairs: int
    regulated_nodes: int = 0
    regulation_shift: float = 0.0


# ------------------------------------------------------------------ one step
def _apply(plan: SurgicalPlan | None, name: str, points: np.ndarray) -> np.ndarray:
    """Points of segment ``name`` moved by ``plan``; segments no plan moves (the skull) stay."""
    return points if plan is None else plan.motion(name).apply(points)


def _targets(model: _Model, plan: SurgicalPlan, base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Prescribed nodes (fixed, then moving) and their displacement from ``base``, mm."""
    X = model.mesh.points
    nodes = np.concatenate([model.fixed, model.moving])
    target = X[nodes].copy()
    seg = model.bc.segment[model.moving]
    for s, name in enumerate(model.bc.segment_names):
        sel = model.fixed.size + np.flatnonzero(seg == s)
        target[sel] = _apply(plan, name, X[nodes[sel]])
    return nodes, target - base[nodes]


def _on_extended(positions: np.ndarray, points: np.ndarray, surface: Mesh, rim: np.ndarray) -> ClosestPoints:
    """Closest points of ``positions`` on ``surface`` placed at ``points``, extended beyond its
    ``rim`` by the planes of its rim triangles."""
    tris = surface.cells["tri3"]
    return beyond_rim_onto_plane(positions, closest_points(positions, points, tris), points, tris, rim)[0]


def _away_from_bone(positions: np.ndarray, on_bone: np.ndarray, normal: np.ndarray, side: np.ndarray) -> np.ndarray:
    """Unit normals ``(k, 3)`` of the offset surface through ``positions`` at their closest
    points ``on_bone``: from the bone point to the node, or ``side`` times the triangle
    ``normal`` where the node is on the bone or on the other side of it."""
    v = positions - on_bone
    length = np.linalg.norm(v, axis=1)
    ok = (length > 1e-9) & (side * np.einsum("ij,ij->i", v, normal) > 0)
    return np.where(ok[:, None], v / np.where(ok, length, 1.0)[:, None], side[:, None] * normal)


def _onto_offset(positions: np.ndarray, offset: np.ndarray, side: np.ndarray, on_bone: np.ndarray,
                 normal: np.ndarray, points: np.ndarray, surface: Mesh, rim: np.ndarray) -> np.ndarray:
    """Points ``(k, 3)`` at distance ``offset`` from ``surface`` (at ``points``, extended beyond
    its ``rim``) reached from ``positions`` along the normal at their closest points ``on_bone``
    (triangle ``normal``). Where the bone is concave within the offset, the closest point of
    that point is elsewhere: the step is repeated from it until the points move less than
    1e-9 mm (at most ``_OFFSET_ITERATIONS`` times)."""
    x = on_bone + offset[:, None] * _away_from_bone(positions, on_bone, normal, side)
    for _ in range(_OFFSET_ITERATIONS):
        near = _on_extended(x, points, surface, rim)
        nxt = near.point + offset[:, None] * _away_from_bone(x, near.point, near.normal, side)
        done = np.abs(nxt - x).max() < 1e-9
        x = nxt
        if done:
            break
    return x


def _carried(vectors: np.ndarray, before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """``vectors (k, 3)`` rotated with their triangles, rigidly moved from ``before`` to
    ``after`` (``(k, 3, 3)`` corners, mm)."""

    def frame(t):
        e1 = t[:, 1] - t[:, 0]
        n = np.cross(e1, t[:, 2] - t[:, 0])
        e1 = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
        return np.stack([e1, np.cross(n, e1), n], axis=1)  # rows: the frame's axes

    local = np.einsum("kij,kj->ki", frame(before), vectors)
    return np.einsum("kij,ki->kj", frame(after), local)


def _sliding_constraints(model: _Model, state: _State, plan: SurgicalPlan, base: np.ndarray, x: np.ndarray,
                         nodes: np.ndarray, values: np.ndarray) -> Constraints:
    """Step 1: each mucosa node keeps its closest point on its bone, carried rigidly from the
    previous bone position to the new one, and its offset ``d0`` along the normal there; its
    normal displacement to that point of the offset surface is prescribed."""
    n, mucosa = model.mesh.n_points, model.mucosa
    if not mucosa.size:
        return Constraints(n, nodes, values)
    normals = np.empty((mucosa.size, 3))
    on_surface = np.empty((mucosa.size, 3))
    seg = model.bc.segment[mucosa]
    for s, name in enumerate(model.bc.segment_names):
        sel = np.flatnonzero(seg == s)
        if not sel.size:
            continue
        surf = model.surfaces[name]
        tris = surf.cells["tri3"]
        prev_pts = _apply(state.plan, name, surf.points)
        cp = closest_points(x[mucosa[sel]], prev_pts, tris)
        new_pts = _apply(plan, name, surf.points)
        off = model.offset[sel] > 0
        point = cp.point
        if off.any():  # off the bone: on the surface extended beyond its rim, like the projection
            ext, _ = beyond_rim_onto_plane(x[mucosa[sel]], cp, prev_pts, tris, model.rims[name])
            point = np.where(off[:, None], ext.point, cp.point)
        tri = tris[cp.triangle]
        bary = barycentric(point, prev_pts[tri])
        on_surface[sel] = np.einsum("ij,ijk->ik", bary, new_pts[tri])
        nrm = np.cross(new_pts[tri[:, 1]] - new_pts[tri[:, 0]], new_pts[tri[:, 2]] - new_pts[tri[:, 0]])
        normals[sel] = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
        if off.any():
            o = sel[off]
            away = _away_from_bone(x[mucosa[o]], point[off], cp.normal[off], model.side[o])
            away = _carried(away, prev_pts[tri[off]], new_pts[tri[off]])
            on_surface[o] += model.offset[o, None] * away
            normals[o] = away
    g = np.einsum("ij,ij->i", normals, on_surface - base[mucosa])
    return Constraints(n, nodes, values, mucosa, normals, g)


def _edge_followers(mesh: Mesh, mucosa: np.ndarray) -> tuple[np.ndarray, ...]:
    """The ``tet10`` mid-edge nodes among ``mucosa``: their positions in ``mucosa`` ``(k,)``, the
    node ids of their edge's two corners ``(k,)`` each, the corners' positions in ``mucosa``
    (-1 for a corner that does not slide) and the node's pre-operative offset ``(k, 3)`` mm from
    the corners' midpoint (0 for straight edges)."""

    none = np.zeros(0, np.int64)
    if "tet10" not in mesh.cells or not mucosa.size:
        return none, none, none, none, none, np.zeros((0, 3))
    mid, a, b = tet10_mid_edges(mesh.cells["tet10"])
    where = np.full(mesh.n_points, -1, np.int64)
    where[mucosa] = np.arange(mucosa.size)
    keep = where[mid] >= 0
    mid, a, b = mid[keep], a[keep], b[keep]
    X = mesh.points
    return where[mid], a, b, where[a], where[b], X[mid] - 0.5 * (X[a] + X[b])


def _projection(model: _Model, plan: SurgicalPlan, x: np.ndarray) -> tuple[np.ndarray, float]:
    """Step 2: closest points ``(m, 3)`` mm of the mucosa nodes at ``x (n, 3)`` on their moved
    bone (extended beyond its edge by the planes of its edge triangles), each moved by its offset
    ``d0`` along the normal there (onto the offset surface), and the largest distance to
    them (the gap closed by the projection), mm.

    A ``tet10`` mid-edge node is put where its edge's shape puts it between its corners (its
    pre-operative offset from their midpoint; a corner that does not slide stays at ``x``), not
    on the bone on its own: corners that slid over a sharp or curved part of the bone (an
    osteotomy border), or a free corner beside a sliding one, would otherwise have it pulled onto
    the bone between them and fold the element."""
    mucosa = model.mucosa
    positions = x[mucosa]
    proj = np.empty_like(positions)
    dist = np.zeros(mucosa.size)
    mid, a, b, at_a, at_b, offset = model.edge_followers
    seg = model.bc.segment[mucosa].copy()
    seg[mid] = -1  # placed from their corners below
    for s, name in enumerate(model.bc.segment_names):
        sel = np.flatnonzero(seg == s)
        if sel.size:
            surf = model.surfaces[name]
            moved = _apply(plan, name, surf.points)
            cp = _on_extended(positions[sel], moved, surf, model.rims[name])
            proj[sel], dist[sel] = cp.point, cp.distance
            off = model.offset[sel] > 0
            if off.any():
                o = sel[off]
                proj[o] = _onto_offset(positions[o], model.offset[o], model.side[o], cp.point[off], cp.normal[off],
                                       moved, surf, model.rims[name])
                dist[o] = np.linalg.norm(positions[o] - proj[o], axis=1)
    if mid.size:
        ends = [np.where((at >= 0)[:, None], proj[np.maximum(at, 0)], x[node]) for node, at in ((a, at_a), (b, at_b))]
        proj[mid] = 0.5 * (ends[0] + ends[1]) + offset
        dist[mid] = np.linalg.norm(positions[mid] - proj[mid], axis=1)
    return proj, float(dist.max(initial=0.0))


def _solve_from(model: _Model, problem: StaticProblem, constraints: Constraints, starts: tuple,
                active: np.ndarray | None = None):
    """:func:`_solve` from the first of ``starts`` it converges from (Newton; a linear solve
    converges from the first); a start that inverts an element counts as not converging. The
    last failure is raised."""
    for i, start in enumerate(starts):
        try:
            return _solve(model, problem, constraints, start, active)
        except (ConvergenceError, FloatingPointError):
            if i == len(starts) - 1:
                raise
            log.info("Newton did not converge from the initial guess; starting from the previous equilibrium")


def _solve(model: _Model, problem: StaticProblem, constraints: Constraints, u_start, active=None):
    """One constrained solve, with the lip-contact active set when lips slide (starting from
    ``active``, the pairs tied at the end of the solve before, when given)."""
    bc = model.bc
    if bc.upper_lip.size:
        res = solve_with_lip_contact(problem, constraints, bc.upper_lip, bc.lower_lip,
                                     threshold=model.options.lip_threshold, u_start=u_start, active=active)
        return res.solution, res
    return problem.solve(constraints, u_start=u_start), None


def _quality(model: _Model, u_total: np.ndarray) -> tuple[np.ndarray, int]:
    """Per-element minimum corner scaled Jacobian of the deformed mesh and the worst element."""
    sj = model.mesh.with_points(model.mesh.points + u_total).scaled_jacobian()
    return sj, int(np.argmin(sj))


def _step(model: _Model, state: _State, plan: SurgicalPlan, guess: np.ndarray | None = None,
          predicted: np.ndarray | None = None) -> tuple[_State, _StepDiagnostics]:
    """Advance from ``state`` to the bone positions of ``plan``: targets, sliding solve,
    projection, re-solve, quality check. A Newton solve starts from ``guess`` (the total
    displacement ``(n, 3)`` mm expected at the end of the step) when given, and from the previous
    equilibrium if it does not converge from there; a linear material's first iterative solve
    starts from ``predicted`` (the step's displacement ``(n, 3)`` mm, expected), which changes
    only its iteration count. Raises :class:`_StepFailure`."""
    X = model.mesh.points
    x = X + state.u
    base = X if model.total_lagrangian else x  # configuration the step's displacement is measured from
    starts = ((state.u,) if guess is None else (guess, state.u)) if model.total_lagrangian else (predicted,)
    problem = model.problem(x)
    nodes, values = _targets(model, plan, base)
    t0 = time.perf_counter()
    try:
        sol1, contact1 = _solve_from(model, problem,
                                     _sliding_constraints(model, state, plan, base, x, nodes, values), starts,
                                     state.active)
        t1 = time.perf_counter()
        sol, contact, gap_before, gap_after = sol1, contact1, 0.0, 0.0
        if model.mucosa.size:
            proj, gap_before = _projection(model, plan, base + sol1.displacement)
            c2 = Constraints(X.shape[0], np.concatenate([nodes, model.mucosa]),
                             np.vstack([values, proj - base[model.mucosa]]))
            sol, contact = _solve(model, problem, c2, sol1.displacement,
                                  None if contact1 is None else contact1.active)
            gap_after = float(np.abs(base[model.mucosa] + sol.displacement[model.mucosa] - proj).max())
    except (ConvergenceError, SolverError) as exc:
        raise _StepFailure(str(exc)) from exc
    t2 = time.perf_counter()
    u = sol.displacement if model.total_lagrangian else state.u + sol.displacement
    sj, worst = _quality(model, u)
    regulated, shift = 0, 0.0
    below = model.options.regulation_below
    if not model.total_lagrangian and below is not None and np.any(sj < np.minimum(below, 0.5 * model.quality0)):
        reg = regulate(model.mesh, X + u, model.movable, target=np.minimum(2.0 * below, model.quality0))
        if reg.moved and reg.min_quality_after > model.options.min_scaled_jacobian:
            x_reg = reg.points.copy()
            if model.mucosa.size:  # back onto the bone, exactly
                x_reg[model.mucosa] = _projection(model, plan, x_reg)[0]
            u, regulated, shift = x_reg - X, reg.moved, reg.max_shift
            sj, worst = _quality(model, u)
    if sj[worst] <= model.options.min_scaled_jacobian:
        centroid = np.round((X + u)[_element_nodes(model.mesh, worst)].mean(axis=0), 1).tolist()
        raise _StepFailure(f"{int((sj <= model.options.min_scaled_jacobian).sum())} elements inverted or degenerate "
                           f"(worst: element {worst}, scaled Jacobian {sj[worst]:.3g}, centroid {centroid} mm)", worst)
    both = [sol1] if sol is sol1 else [sol1, sol]
    contacts = [c for c in ((contact1,) if contact is contact1 else (contact1, contact)) if c is not None]
    diag = _StepDiagnostics(
        seconds_step1=t1 - t0, seconds_step2=t2 - t1, linear_solves=sum(len(s.solves) for s in both),
        newton_iterations=sum(s.newton_iterations for s in both),
        contact_iterations=sum(c.iterations for c in contacts), min_scaled_jacobian=float(sj[worst]),
        worst_element=worst, gap_before=gap_before, gap_after=gap_after,
        active_lip_pairs=int(contact.active.sum()) if contact is not None else 0,
        regulated_nodes=regulated, regulation_shift=shift)
    return _State(state.fraction, plan, u, None if contact is None else contact.active), diag


# ------------------------------------------------------ increments and cutting
def _advance(model: _Model, plan: SurgicalPlan, state: _State, fraction: float, depth: int = 0):
    """Step from ``state`` to ``fraction`` of ``plan``, halving the step on failure; a step
    already cut twice that still fails frees the held cut or the sliding mucosa around the
    failing element (:meth:`_Model.free_near`) and is tried again before it is cut further.

    Returns the new state, the diagnostics of every successful sub-step and the number of
    failed attempts. Raises :class:`_StepFailure` when ``max_cuts`` halvings do not help.
    """
    share = fraction - state.fraction
    # a linear step's iterative solve starts from the step before it, scaled to this one's share
    predicted = None if state.rate is None or model.total_lagrangian else state.rate * share
    try:
        new, diag = _step(model, state, plan.interpolated(fraction), model.guess_at(fraction), predicted)
        rate = None if model.total_lagrangian else (new.u - state.u) / share
        return replace(new, fraction=fraction, rate=rate), [diag], 0
    except _StepFailure as exc:
        freed = model.free_near(exc.element) if depth >= min(_CUTS_BEFORE_FREEING, model.options.max_cuts) else None
        if freed:
            log.warning("step %.4g -> %.4g failed (%s); freed %s and trying it again",
                        state.fraction, fraction, exc, freed)
            new, diags, failed = _advance(model, plan, state, fraction, depth)
            return new, diags, failed + 1
        if depth >= model.options.max_cuts:
            raise
        log.info("step %.4g -> %.4g failed (%s); cutting it in two", state.fraction, fraction, exc)
    mid = 0.5 * (state.fraction + fraction)
    half, d1, f1 = _advance(model, plan, state, mid, depth + 1)
    new, d2, f2 = _advance(model, plan, half, fraction, depth + 1)
    return new, d1 + d2, 1 + f1 + f2


def _report(k: int, diags: list, failed: int, model: _Model, u: np.ndarray) -> IncrementReport:
    last = diags[-1]
    worst = min(diags, key=lambda d: d.min_scaled_jacobian)
    return IncrementReport(
        increment=k, seconds_step1=sum(d.seconds_step1 for d in diags),
        seconds_step2=sum(d.seconds_step2 for d in diags), linear_solves=sum(d.linear_solves for d in diags),
        newton_iterations=sum(d.newton_iterations for d in diags),
        contact_iterations=sum(d.contact_iterations for d in diags),
        min_scaled_jacobian=worst.min_scaled_jacobian, worst_element=worst.worst_element,
        mucosa_gap_before_projection=max(d.gap_before for d in diags),
        mucosa_gap_after_projection=max(d.gap_after for d in diags),
        max_penetration=_penetration(model.mesh.points + u, model.bc_all.upper_lip, model.bc_all.lower_lip),
        active_lip_pairs=last.active_lip_pairs, substeps=len(diags), failed_attempts=failed,
        regulated_nodes=sum(d.regulated_nodes for d in diags),
        max_regulation_shift=max(d.regulation_shift for d in diags))


def simulate(
    face: Mesh | FacePhantom,
    plan: SurgicalPlan,
    increments: int = STATIC_SIMULATION["increments"],
    material: str | MaterialAssignment = STATIC_SIMULATION["material"],
    sliding: str = STATIC_SIMULATION["sliding"],
    *,
    segments: Mapping | None = None,
    options: SimulationOptions | None = None,
    initial_guess: np.ndarray | None = None,
) -> SimulationResult:
    """Run the lip-sliding paper's incremental simulation.

    Parameters
    ----------
    face : FacePhantom, or a Mesh with the node sets of the phantoms (then pass ``segments``)
    plan : SurgicalPlan (segments ``lefort``, ``distal``, ``proximal_left``, ``proximal_right``)
    increments : number of increments (the lip-sliding paper: 3)
    material : ``linear``, ``neo-hookean`` or a MaterialAssignment
    sliding : ``mucosa+lip`` (the lip-sliding paper), ``mucosa`` or ``none``
    segments : name -> BoneSegment (bone surfaces and attachment sets); default the phantom's
    options : SimulationOptions
    initial_guess : ``(increments + 1, n, 3)`` mm, an expected total displacement after each
        increment (a surrogate's answer): each Newton solve (Neo-Hookean) starts from it, linear
        between increments for a cut step, and from the previous equilibrium when it does not
        converge from there. A linear material's solve is direct and does not use it.

    Returns
    -------
    SimulationResult — displacements ``(increments + 1, n, 3)`` mm and diagnostics

    Raises
    ------
    SimulationError naming the increment, the worst element and a suggestion (after the
    retries: within the run, fixed nodes of the cut or sliding mucosa freed near an element that
    failed, ``options.free_cut_radius`` and ``options.free_mucosa_radius``; then the run again with
    each of ``options.wider_release``, the cut freed so far freed from its start).
    """
    t_start = time.perf_counter()
    options = options or SimulationOptions()
    if int(increments) != increments or increments < 1:
        raise ValueError(f"increments must be an integer >= 1, got {increments!r}")
    if initial_guess is not None:
        initial_guess = np.asarray(initial_guess, dtype=float)
        n = face_mesh_and_segments(face, segments)[0].n_points
        if initial_guess.shape != (int(increments) + 1, n, 3) or not np.isfinite(initial_guess).all():
            raise ValueError(f"initial_guess has shape {initial_guess.shape}; expected finite ({int(increments) + 1}, "
                             f"{n}, 3) mm (the total displacement before and after each increment)")
    mesh, segs = face_mesh_and_segments(face, segments)
    plan_checks = check_plan(mesh, BoundaryConditions.from_mesh(mesh, segs, lip_threshold=options.lip_threshold),
                             segs, plan, options.min_carried_mm2, options.min_carried_share)
    widths = (options.release_width, *(w for w in options.wider_release if w > options.release_width))
    attempt, freed = 0, np.zeros(0, np.int64)
    while True:
        width = widths[attempt]
        model = _build_model(face, material, sliding, segments,
                             replace(options, release_width=width, wider_release=()), freed)
        model.guess, model.freed_cut = initial_guess, freed
        try:
            with warnings.catch_warnings():
                # the plan warned of a movement beyond the physiological range where it was built;
                # its increments (fractions of it) do not repeat that once per increment
                warnings.simplefilter("ignore", PlanRangeWarning)
                displacements, reports = _increments(model, plan, int(increments))
            break
        except SimulationError as exc:
            freed = model.freed_cut
            if attempt + 1 == len(widths):
                if attempt or freed.size:
                    tried = ", ".join(f"{w:g}" for w in widths)
                    raise SimulationError(f"{exc.reason} (with each release band tried: {tried} mm; "
                                          f"{freed.size} fixed nodes of the cut freed; "
                                          f"{model.freed_mucosa.size} sliding mucosa nodes freed)", exc.increment,
                                          exc.element, exc.suggestion) from exc
                raise
            attempt += 1
            log.warning("%s; retrying with a %g mm release band", exc, widths[attempt])
    material_name = material if isinstance(material, str) else "custom"
    checks = check_answer(model.mesh, model.bc, plan, displacements[-1], min(r.min_scaled_jacobian for r in reports))
    return SimulationResult(model.mesh, displacements, model.bc, reports, time.perf_counter() - t_start,
                            material_name, sliding, release_width=width, freed_cut=model.freed_cut,
                            mucosa_offset=model.mucosa_offset, far_mucosa=model.far_mucosa,
                            freed_mucosa=model.freed_mucosa,
                            checks={"plan": plan_checks, "answer": checks}, plan=plan)


def _cut_near(model: _Model, element: int | None) -> np.ndarray:
    """Fixed nodes off the bone (the truncation cut) not yet freed within
    ``free_cut_radius`` mm of the centroid of ``element`` (empty when none is that close).
    A mesh without a ``bone`` node set has no such cut."""
    radius, mesh = model.options.free_cut_radius, model.mesh
    if element is None or radius <= 0 or "bone" not in mesh.node_sets:
        return np.zeros(0, np.int64)
    cut = np.setdiff1d(model.fixed, mesh.node_sets["bone"])
    centroid = mesh.points[_element_nodes(mesh, element)].mean(axis=0)
    return cut[np.linalg.norm(mesh.points[cut] - centroid, axis=1) < radius]


def _increments(model: _Model, plan: SurgicalPlan, n: int) -> tuple[np.ndarray, list]:
    """The ``n`` increments of ``plan``: cumulative displacements ``(n + 1, nodes, 3)`` mm and
    the IncrementReports. Raises :class:`SimulationError`."""
    from tqdm.auto import tqdm

    state = _State(0.0, None, np.zeros((model.mesh.n_points, 3)))
    displacements, reports = [state.u], []
    for k in tqdm(range(1, n + 1), desc="increments", disable=not model.options.progress, leave=False):
        try:
            state, diags, failed = _advance(model, plan, state, k / n)
        except _StepFailure as exc:
            raise SimulationError(str(exc), k, exc.element, _remedy(model, n)) from exc
        reports.append(_report(k, diags, failed, model, state.u))
        displacements.append(state.u)
        log.info("increment %d/%d: %d sub-step(s), min SJ %.3f, max |u| %.2f mm", k, n, len(diags),
                 reports[-1].min_scaled_jacobian, np.linalg.norm(state.u, axis=1).max())
        count_finished("increment")
    return np.stack(displacements), reports


def face_mesh_and_segments(face: Mesh | FacePhantom, segments: Mapping | None = None) -> tuple[Mesh, Mapping]:
    """The mesh and bony segments of ``face`` (a phantom's own segments unless ``segments`` is given;
    a bare Mesh needs them)."""
    if isinstance(face, FacePhantom):
        return face.mesh, segments or face.segments
    if segments is None:
        raise ValueError("a bare Mesh needs segments=... (name -> BoneSegment) for the bony surfaces")
    return face, segments


def boundary_conditions(mesh: Mesh, segments: Mapping, sliding: str,
                        options: SimulationOptions | None = None) -> tuple[BoundaryConditions, BoundaryConditions]:
    """The boundary conditions a simulation uses: ``(bc, bc_all)`` where ``bc`` has the release
    bands and the sliding model applied (and the ``tet10`` mid-edge nodes of freed corners freed:
    :meth:`~toolkit.static.boundary.BoundaryConditions.with_mid_edges_of_corners`) and ``bc_all``
    is as read from the node sets (its lip pairs whatever the sliding model). The surrogate's
    database and predictions use the same."""
    options = options or SimulationOptions()
    if sliding not in SLIDING_MODELS:
        raise ValueError(f"unknown sliding model {sliding!r}; expected one of {SLIDING_MODELS}")
    bc_all = BoundaryConditions.from_mesh(mesh, segments, lip_threshold=options.lip_threshold)
    bc = bc_all.with_release_bands(mesh, options.release_width).with_sliding(sliding)
    return bc.with_mid_edges_of_corners(mesh), bc_all


def _build_model(face, material, sliding, segments, options: SimulationOptions,
                 freed: np.ndarray | None = None) -> _Model:
    """Mesh, materials, boundary conditions (sliding model, release bands, ``freed`` nodes of
    the cut) and bone surfaces."""
    mesh, segments = face_mesh_and_segments(face, segments)
    bc, bc_all = boundary_conditions(mesh, segments, sliding, options)
    if freed is not None:
        bc = bc.with_freed(freed).with_mid_edges_of_corners(mesh)
    materials = material_assignment(material, mesh)
    surfaces = {name: segments[name].surface for name in bc.segment_names}
    return _Model(mesh, materials, bc, bc_all, surfaces, options, total_lagrangian=not materials.is_linear)


def _element_nodes(mesh: Mesh, element: int) -> np.ndarray:
    """Nodes of volume element ``element`` (numbered over the volume blocks in order)."""
    for block in mesh.volume_blocks:
        if element < block.cells.shape[0]:
            return block.cells[element]
        element -= block.cells.shape[0]
    raise IndexError(f"volume element {element} out of range")


def _remedy(model: _Model, increments: int) -> str:
    cuts = model.options.max_cuts
    return (f"the step was already cut {cuts} times ({2 ** cuts} sub-steps); use more increments than {increments}, "
            f"a wider release band than {model.options.release_width:g} mm, a smaller movement, a larger "
            f"free_cut_radius than {model.options.free_cut_radius:g} mm if the element is near the fixed cut, "
            f"a larger free_mucosa_radius than {model.options.free_mucosa_radius:g} mm if it is on the sliding mucosa, "
            f"or check the boundary node sets near that element")


def _offset_statistics(offset: np.ndarray) -> dict | None:
    """Median, 90th percentile and maximum (mm) of the mucosa offsets; None without any."""
    if not np.size(offset):
        return None
    median, p90 = np.percentile(offset, [50, 90])
    return {"nodes": int(offset.size), "median": float(median), "p90": float(p90), "max": float(np.max(offset))}


def _penetration(x: np.ndarray, upper: np.ndarray, lower: np.ndarray) -> float:
    """Largest craniocaudal overlap of paired upper/lower lip nodes, mm (0 if none).

    Measured for every sliding model, so that runs without lip contact show what it prevents.
    """
    if not upper.size:
        return 0.0
    return float(max(0.0, (x[lower, 2] - x[upper, 2]).max()))
