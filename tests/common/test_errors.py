"""The error hierarchy: one ``except ToolkitError`` catches every error the toolkit raises on
purpose, and each class keeps its builtin base so ``except ValueError`` / ``RuntimeError`` in user
code catches what it caught."""

import pickle

import numpy as np
import pytest

import toolkit
import toolkit.common
from toolkit.common.config_diff import IncompatibleError
from toolkit.common.errors import AnswerError, ConvergenceError, ToolkitError
from toolkit.common.fem.pardiso import PardisoError
from toolkit.common.fem.solvers import SolverError
from toolkit.common.fidelity import FidelityError
from toolkit.common.meshes.axes import AxesError
from toolkit.common.meshes.io import UnitsError
from toolkit.common.meshes.mesh import DegenerateElementError, InvertedElementError, Mesh, MeshError, MissingSetError
from toolkit.common.outputs import OutputError
from toolkit.common.phantoms.mixed_bar import mixed_bar
from toolkit.common.training.database import DatabaseError
from toolkit.impact.explicit import InstabilityError
from toolkit.impact.plasticity import InvertedPointError
from toolkit.impact.scene import BallSpec, SceneError
from toolkit.impact.simulate import UnstableTimeStepError
from toolkit.mesh.backends import MeshingError
from toolkit.mesh.ct_anatomy import CTError
from toolkit.mesh.face import FaceInputError
from toolkit.mesh.mouth import MouthError
from toolkit.mesh.rules import RulesError
from toolkit.mesh.surface import SurfaceError
from toolkit.mesh.volume import VolumeError
from toolkit.static.anatomy import AnatomyError
from toolkit.static.boundary import BoundaryError
from toolkit.static.plan import PlanError, RigidMotion, SurgicalPlan
from toolkit.static.simulate import SimulationError

#: every public error class and the builtin exception it is also
BUILTIN_BASES = {
    MeshError: ValueError,
    InvertedElementError: ValueError,
    DegenerateElementError: ValueError,
    UnitsError: ValueError,
    AxesError: ValueError,
    MissingSetError: KeyError,
    OutputError: ValueError,
    DatabaseError: ValueError,
    IncompatibleError: ValueError,
    PlanError: ValueError,
    BoundaryError: ValueError,
    SceneError: ValueError,
    UnstableTimeStepError: ValueError,
    ConvergenceError: RuntimeError,
    SolverError: RuntimeError,
    PardisoError: RuntimeError,
    SimulationError: RuntimeError,
    AnswerError: RuntimeError,
    InstabilityError: RuntimeError,
    InvertedPointError: FloatingPointError,
    SurfaceError: ValueError,
    FaceInputError: ValueError,
    RulesError: ValueError,
    VolumeError: ValueError,
    CTError: ValueError,
    MouthError: ValueError,
    MeshingError: RuntimeError,
    AnatomyError: ValueError,
    FidelityError: ValueError,
}


@pytest.mark.parametrize("cls", list(BUILTIN_BASES), ids=lambda c: c.__name__)
def test_every_error_is_a_toolkit_error_and_keeps_its_builtin_base(cls):
    """Each class derives from ToolkitError and from the builtin it derived from alone."""
    assert issubclass(cls, ToolkitError)
    assert issubclass(cls, BUILTIN_BASES[cls])


#: exceptions that signal between the Newton loop and its callers, which turn them into a
#: ConvergenceError: they never reach a user
NEWTON_SIGNALS = {"InadmissibleState", "NewtonFailed"}


def _exported_error_classes():
    """Every exception class (warnings aside) in the ``__all__`` of every toolkit module."""
    import importlib
    import pkgutil

    found = set()
    for info in pkgutil.walk_packages(toolkit.__path__, "toolkit."):
        if info.name.endswith("__main__"):  # running it is the command line
            continue
        module = importlib.import_module(info.name)
        for name in getattr(module, "__all__", ()):
            obj = getattr(module, name)
            if (isinstance(obj, type) and issubclass(obj, Exception) and not issubclass(obj, Warning)
                    and name not in NEWTON_SIGNALS):
                found.add(obj)
    return found


def test_the_list_above_covers_every_exported_error():
    """No error class exported by a toolkit module escapes the hierarchy (or this test's list)."""
    exported = _exported_error_classes() - {ToolkitError}
    assert exported <= set(BUILTIN_BASES), sorted(c.__name__ for c in exported - set(BUILTIN_BASES))
    assert all(issubclass(c, ToolkitError) for c in exported)


def test_one_convergence_error_for_both_workflows():
    """Static and impact raise the same class, re-exported where each workflow's code is."""
    import toolkit.impact
    import toolkit.impact.quasi_static
    import toolkit.static
    import toolkit.static.problem

    assert (toolkit.ConvergenceError is toolkit.common.ConvergenceError is toolkit.static.ConvergenceError
            is toolkit.static.problem.ConvergenceError is toolkit.impact.quasi_static.ConvergenceError
            is toolkit.impact.ConvergenceError is ConvergenceError)


def test_convergence_error_carries_iteration_residual_and_time_through_pickling():
    """The static form carries the iteration and the residual, the impact form the time, which
    also prefixes the message; a process pool's pickling keeps all of them."""
    static = ConvergenceError("lip contact active set did not settle in 20 iterations", 20, 1e-3)
    assert str(static) == "lip contact active set did not settle in 20 iterations"
    assert (static.iteration, static.residual, static.time) == (20, 1e-3, None)
    impact = ConvergenceError("load step 0.01 s failed", time=0.123456)
    assert str(impact) == "t = 0.12346 s: load step 0.01 s failed"
    assert (impact.iteration, impact.residual, impact.time) == (None, None, 0.123456)
    for exc in (static, impact):
        back = pickle.loads(pickle.dumps(exc))
        assert type(back) is ConvergenceError
        assert str(back) == str(exc)
        assert (back.iteration, back.residual, back.time) == (exc.iteration, exc.residual, exc.time)


def test_an_inverted_element_is_caught_as_a_toolkit_error():
    """Mesh: one hex of a bar turned inside out (its top and bottom faces swapped)."""
    mesh = mixed_bar(1)
    cells = dict(mesh.cells)
    hexes = cells["hex8"].copy()
    hexes[0] = hexes[0][[4, 5, 6, 7, 0, 1, 2, 3]]
    cells["hex8"] = hexes
    with pytest.raises(ToolkitError, match="inverted") as info:
        Mesh(mesh.points, cells).check()
    assert isinstance(info.value, InvertedElementError)
    assert 0 in info.value.elements


def test_a_plan_with_an_unknown_segment_is_caught_as_a_toolkit_error():
    """Static workflow: a plan naming a segment the face does not have."""
    with pytest.raises(ToolkitError, match="unknown segments") as info:
        SurgicalPlan({"chin": RigidMotion.identity()})
    assert isinstance(info.value, PlanError) and isinstance(info.value, ValueError)


def test_a_nonconverging_static_problem_is_caught_as_a_toolkit_error():
    """Static solver: a wedge turned inside out is refused as a ConvergenceError."""
    from toolkit.static.problem import StaticProblem
    from toolkit.static.stiffness import MaterialAssignment

    mesh = mixed_bar(1)
    cells = dict(mesh.cells)
    wedges = cells["wedge6"].copy()
    wedges[5] = wedges[5][[3, 4, 5, 0, 1, 2]]
    cells["wedge6"] = wedges
    with pytest.raises(ToolkitError) as info:
        StaticProblem(Mesh(mesh.points, cells), MaterialAssignment())
    assert isinstance(info.value, ConvergenceError)


def test_a_ball_at_rest_is_caught_as_a_toolkit_error():
    """Impact workflow: a scene whose ball does not move."""
    with pytest.raises(ToolkitError, match="velocity") as info:
        BallSpec(velocity=0.0)
    assert isinstance(info.value, SceneError) and isinstance(info.value, ValueError)


def test_an_inverted_integration_point_is_caught_as_a_toolkit_error():
    """Impact plasticity: a stress update at det F < 0."""
    from toolkit.impact.plasticity import FACE_TABLE, J2Plasticity

    law = J2Plasticity(E=0.015, nu=0.49, density=1e-9, table=FACE_TABLE)
    F = np.eye(3)[None].copy()
    F[0, 2, 2] = -1.0
    with pytest.raises(ToolkitError) as info:
        law.update(F, law.initial_state(1))
    assert isinstance(info.value, InvertedPointError)
