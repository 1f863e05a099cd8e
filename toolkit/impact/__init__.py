"""Impact workflow: finite-strain elastoplastic ball impact on the face (the impact paper).

``simulate(default_scene())`` runs the impact paper's scene by quasi-static load steps
(``Fidelity.integrator = "quasi-static"``, the default) or, by name, by the paper's explicit
dynamics (``"explicit"``); the pieces (scene, elements, plasticity, contact, integrators) are
importable. The surrogate side: ``build_database``
(one simulation per velocity, HDF5), ``train_surrogate`` (the impact paper's LSTM, a stronger one,
an MLP baseline), ``evaluate_surrogate`` (an ``Evaluation``), ``predict_scene``, and the answer within a tolerance:
``calibrate_surrogate``, ``Calibration``, ``answer`` (the LSTM's or the FE's, a ``TrustedAnswer``). Imports nothing from
:mod:`toolkit.static`.
"""

from toolkit.impact.database import ImpactDatabase, build_database, load_database
from toolkit.impact.evaluation import Evaluation, evaluate_surrogate
from toolkit.impact.explicit import InstabilityError
from toolkit.impact.quasi_static import ConvergenceError
from toolkit.impact.scene import (
    BallSpec,
    ContactSpec,
    FaceSpec,
    Fidelity,
    MaterialSpec,
    Scene,
    SceneError,
    default_scene,
    meshed_scene,
    yielding_scene,
)
from toolkit.impact.simulate import ImpactResult, SceneGeometryWarning, UnstableTimeStepError, build_model, simulate
from toolkit.impact.surrogate import CONFIGS, Surrogate, SurrogateConfig, predict_scene, train_surrogate
from toolkit.impact.trust import Calibration, TrustedAnswer, answer, calibrate_surrogate

__all__ = [
    "Scene",
    "SceneError",
    "FaceSpec",
    "BallSpec",
    "ContactSpec",
    "Fidelity",
    "MaterialSpec",
    "default_scene",
    "yielding_scene",
    "meshed_scene",
    "simulate",
    "build_model",
    "ImpactResult",
    "InstabilityError",
    "ConvergenceError",
    "UnstableTimeStepError",
    "SceneGeometryWarning",
    "build_database",
    "load_database",
    "ImpactDatabase",
    "train_surrogate",
    "Surrogate",
    "SurrogateConfig",
    "CONFIGS",
    "evaluate_surrogate",
    "Evaluation",
    "predict_scene",
    "Calibration",
    "calibrate_surrogate",
    "answer",
    "TrustedAnswer",
]
