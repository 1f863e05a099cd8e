"""The toolkit's error hierarchy.

Every error the toolkit raises on purpose derives from :class:`ToolkitError`, so one
``except ToolkitError`` catches any of them, whichever workflow raised it. Each class also keeps a
builtin base that says what kind of failure it is (``ValueError`` for bad input,
``RuntimeError`` for a solve that failed, ``FloatingPointError`` for an inverted integration
point), so ``except ValueError`` catches bad meshes, plans and scenes as well.

==========================  =====================================  ========================
class                       raised when                            builtin base
==========================  =====================================  ========================
``MeshError``               a mesh is malformed                    ``ValueError``
``InvertedElementError``    elements have a non-positive Jacobian  ``ValueError``
``UnitsError``              a mesh's size suggests another unit    ``ValueError``
``AxesError``               a face is not in the toolkit's axes    ``ValueError``
``DatabaseError``           a file is not the expected database    ``ValueError``
``IncompatibleError``       a stored file has another config       ``ValueError``
``PlanError``               a surgical plan is invalid             ``ValueError``
``BoundaryError``           boundary conditions are inconsistent   ``ValueError``
``SceneError``              an impact scene is invalid             ``ValueError``
``UnstableTimeStepError``   a time step exceeds the stable limit   ``ValueError``
``ConvergenceError``        a nonlinear solve did not converge     ``RuntimeError``
``SolverError``             a linear solve failed                  ``RuntimeError``
``PardisoError``            PARDISO failed a phase                 ``RuntimeError``
``SimulationError``         a static increment failed              ``RuntimeError``
``AnswerError``             an answer failed its checks            ``RuntimeError``
``InstabilityError``        an explicit run became unstable        ``RuntimeError``
``InvertedPointError``      a stress update met ``det F <= 0``     ``FloatingPointError``
==========================  =====================================  ========================

The classes live beside the code that raises them; those raised in several places live here:
:class:`ConvergenceError` and :class:`AnswerError` (both workflows) and the mesh errors
(:mod:`toolkit.common.meshes.mesh`, :mod:`toolkit.common.meshes.quality`, :mod:`toolkit.common.meshes.convert`, which
also export them).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ToolkitError", "ConvergenceError", "AnswerError", "MeshError", "MissingSetError",
           "InvertedElementError", "DegenerateElementError"]


class ToolkitError(Exception):
    """Base of every error the toolkit raises on purpose."""


class AnswerError(ToolkitError, RuntimeError):
    """An answer (an FE result or a surrogate's prediction) failed a check made before it is given:
    it would have been wrong. ``checks`` (dict) holds the values measured."""

    def __init__(self, message: str, checks: dict | None = None):
        super().__init__(message)
        self.checks = dict(checks or {})

    def __reduce__(self):
        return type(self), (str(self), self.checks)


def _rebuild_convergence_error(cls, message, iteration, residual, time):
    return cls(message, iteration, residual, time=time)


class ConvergenceError(ToolkitError, RuntimeError):
    """A nonlinear solve did not converge.

    The static solver raises it with the Newton ``iteration`` (or the lip-contact active-set
    iteration) and the relative ``residual`` where known; the quasi-static impact solver raises it
    with the simulated ``time`` of the load step that failed at the smallest allowed step, and the
    message then starts with ``t = <time> s:``.

    Attributes
    ----------
    iteration : int or None
        Iteration at which the solve stopped.
    residual : float or None
        Relative residual there.
    time : float or None
        s, simulated time of the failed load step.
    """

    def __init__(self, message: str, iteration: int | None = None, residual: float | None = None, *,
                 time: float | None = None):
        super().__init__(message if time is None else f"t = {time:.5g} s: {message}")
        self._message = message
        self.iteration = iteration
        self.residual = residual
        self.time = time

    def __reduce__(self):
        # keeps the attributes across pickling (process-pool executors send errors back pickled)
        return (_rebuild_convergence_error,
                (type(self), self._message, self.iteration, self.residual, self.time))


class MeshError(ToolkitError, ValueError):
    """A mesh is malformed: bad shapes, indices out of range, NaN coordinates."""


class MissingSetError(MeshError, KeyError):
    """A node or element set a caller needs is not in the mesh (a ``KeyError`` too, for lookups)."""

    def __str__(self) -> str:  # KeyError's would quote the message
        return str(self.args[0]) if self.args else ""


class InvertedElementError(MeshError):
    """Elements have a non-positive Jacobian (inside-out or folded).

    Attributes
    ----------
    elements : (k,) int64
        Global indices of the offending elements, worst first.
    values : (k,) float
        Their scaled Jacobians.
    """

    def __init__(self, message: str, elements: np.ndarray, values: np.ndarray):
        super().__init__(message)
        self.elements = np.asarray(elements, dtype=np.int64)
        self.values = np.asarray(values, dtype=float)


class DegenerateElementError(InvertedElementError):
    """Elements are positive but flat (scaled Jacobian below the tolerance)."""
