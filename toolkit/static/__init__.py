"""Static workflow: orthognathic surgery simulated by incremental FEM (the lip-sliding paper).

``simulate(phantom, plan)`` runs the increments with mucosa and lip sliding; the pieces
(plan, boundary types, assembly, constraints, solvers, Newton/contact) are importable
for finer control. The answer within a tolerance, as in :mod:`toolkit.impact`:
``calibrate_surrogate``, ``Calibration``, ``answer`` (the surrogate's or the FE's, a
``TrustedAnswer``). Imports nothing from :mod:`toolkit.impact`.
"""

from toolkit.common.fem.solvers import SolverError
from toolkit.static.boundary import BoundaryConditions, BoundaryError, NodeType, knn_labels
from toolkit.static.case import StaticCase, load_case
from toolkit.static.constraints import Constraints
from toolkit.static.plan import (
    PHYSIOLOGICAL_RANGES,
    SEGMENTS,
    PlanError,
    PlanRangeWarning,
    RigidMotion,
    SurgicalPlan,
    default_plan,
)
from toolkit.static.problem import ConvergenceError, StaticProblem, solve_with_lip_contact
from toolkit.static.simulate import (
    IncrementReport,
    SimulationError,
    SimulationOptions,
    SimulationResult,
    material_assignment,
    simulate,
)
from toolkit.static.stiffness import MaterialAssignment
from toolkit.static.trust import Calibration, TrustedAnswer, answer, calibrate_surrogate

__all__ = [
    "simulate",
    "load_case",
    "StaticCase",
    "SimulationOptions",
    "SimulationResult",
    "IncrementReport",
    "SimulationError",
    "material_assignment",
    "SurgicalPlan",
    "RigidMotion",
    "default_plan",
    "SEGMENTS",
    "PHYSIOLOGICAL_RANGES",
    "PlanError",
    "PlanRangeWarning",
    "BoundaryConditions",
    "BoundaryError",
    "NodeType",
    "knn_labels",
    "Constraints",
    "MaterialAssignment",
    "StaticProblem",
    "solve_with_lip_contact",
    "ConvergenceError",
    "SolverError",
    "Calibration",
    "calibrate_surrogate",
    "answer",
    "TrustedAnswer",
]
