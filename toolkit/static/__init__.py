"""Static workflow: orthognathic surgery simulated by incremental FEM (the lip-sliding paper).

``simulate(phantom, plan)`` runs the increments with mucosa and lip sliding; the pieces
(plan, boundary types, assembly, constraints, solvers, Newton/contact) are importable
for finer control. The surrogate side, named as in :mod:`toolkit.impact`: ``build_database``
(``DatabaseConfig``) and ``load_database``, ``train_surrogate`` (PointNet++, ``SurrogateConfig``),
``Surrogate.load``, ``evaluate_surrogate`` (an ``Evaluation``), and the answer within a tolerance:
``calibrate_surrogate``, ``Calibration``, ``answer`` (the surrogate's or the FE's, a
``TrustedAnswer``). Imports nothing from :mod:`toolkit.impact`.
"""

from toolkit.common.fem.solvers import SolverError
from toolkit.common.training.evaluation import Evaluation
from toolkit.static.boundary import BoundaryConditions, BoundaryError, NodeType, knn_labels
from toolkit.static.case import StaticCase, load_case
from toolkit.static.constraints import Constraints
from toolkit.static.database import DatabaseConfig, StaticDatabase, build_database, load_database
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
from toolkit.static.surrogate import Surrogate, SurrogateConfig, evaluate_surrogate, train_surrogate
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
    "DatabaseConfig",
    "build_database",
    "load_database",
    "StaticDatabase",
    "train_surrogate",
    "Surrogate",
    "SurrogateConfig",
    "evaluate_surrogate",
    "Evaluation",
    "Calibration",
    "calibrate_surrogate",
    "answer",
    "TrustedAnswer",
]
