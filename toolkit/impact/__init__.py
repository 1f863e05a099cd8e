"""Impact workflow: explicit finite-strain elastoplastic ball impact on the face (seed 002).

``simulate(default_scene())`` runs seed 002's scene; the pieces (scene, elements,
plasticity, contact, integrator) are importable. Imports nothing from :mod:`toolkit.static`.
"""

from toolkit.impact.explicit import InstabilityError
from toolkit.impact.scene import (
    BallSpec,
    ContactSpec,
    FaceSpec,
    Fidelity,
    MaterialSpec,
    Scene,
    default_scene,
    yielding_scene,
)
from toolkit.impact.simulate import ImpactResult, SceneGeometryWarning, UnstableTimeStepError, build_model, simulate

__all__ = [
    "Scene",
    "FaceSpec",
    "BallSpec",
    "ContactSpec",
    "Fidelity",
    "MaterialSpec",
    "default_scene",
    "yielding_scene",
    "simulate",
    "build_model",
    "ImpactResult",
    "InstabilityError",
    "UnstableTimeStepError",
    "SceneGeometryWarning",
]
