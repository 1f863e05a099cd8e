"""Newton's method with a line search, and load-step cutting: the nonlinear solve of both
workflows (the static Neo-Hookean face and the quasi-static impact path).

A workflow states its problem as four callables and keeps its physics to itself:

- ``evaluate(x) -> Trial``: the residual at the unknowns ``x`` (any shape), a merit the
  line search decreases (an energy whose gradient is the residual, or the residual's
  norm) and whatever else the workflow computed there (forces, material states). A state
  that cannot be evaluated (an inverted element, a failed material update) raises
  :class:`InadmissibleState`;
- ``converged(trial) -> bool``: the workflow's force test;
- ``correction(trial) -> dx or None``: the Newton correction (a tangent solve; raise
  :class:`NewtonFailed` when it fails), or None when the trial is already converged by a
  test that needs the tangent;
- ``negligible(trial, dx) -> bool``: the correction is too small to matter; the corrected
  state ``x + dx`` is then accepted without a line search.

:func:`newton` iterates. Line searches: :class:`ArmijoOnMerit` (an energy; the static
face), :class:`SecantOnDirection` (the zero of ``r . dx``; the impact path, where penalty
contact has no energy that friction would not spoil) and :class:`ResidualDecrease` (fixed
fractions judged by the residual norm). :class:`LoadSteps` walks a load parameter
(time, or the fraction of a prescribed displacement) over its stops in steps that are cut
in half when Newton fails and grow again after easy steps.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Trial", "NewtonResult", "InadmissibleState", "NewtonFailed", "newton", "ArmijoOnMerit",
           "ResidualDecrease", "SecantOnDirection", "LoadSteps"]


class InadmissibleState(Exception):
    """A trial state that cannot be evaluated (the message says why); a line search skips it."""


class NewtonFailed(Exception):
    """Newton's method did not converge; ``iteration`` and ``residual`` (the norm, in the
    residual's units) say where. The caller cuts its load step."""

    def __init__(self, message: str, iteration: int | None = None, residual: float | None = None):
        super().__init__(message)
        self.iteration, self.residual = iteration, residual


@dataclass(frozen=True, eq=False)
class Trial:
    """One evaluated state.

    Attributes
    ----------
    x : the unknowns (any shape; corrections have the same shape)
    residual : the free-dof residual (any shape), zero at equilibrium
    merit : what a line search decreases (an energy, or the residual's norm)
    data : whatever the workflow computed with it (forces, states)
    """

    x: np.ndarray
    residual: np.ndarray
    merit: float
    data: Any = None

    @property
    def norm(self) -> float:
        """Euclidean norm of the residual."""
        return float(np.linalg.norm(self.residual))


@dataclass(frozen=True, eq=False)
class NewtonResult:
    """The converged trial and the Newton corrections it took."""

    trial: Trial
    iterations: int


@dataclass(frozen=True)
class ArmijoOnMerit:
    """Backtracking on an energy whose gradient is the residual: halve the step until
    ``E(x + a dx) <= E(x) + c a r.dx + relative_slack |E(x)|`` (Armijo, with slack for the
    energy's round-off).

    A correction that is not a descent direction (``r.dx >= 0``, an indefinite tangent) is
    replaced by steepest descent of the same largest component. When the full step changes
    the energy by less than ``merit_resolution`` (round-off), it is judged by the residual
    norm instead. Returns None when ``max_halvings`` halvings find no step.
    """

    c: float = 1e-4
    relative_slack: float = 1e-12
    merit_resolution: float = 0.0
    max_halvings: int = 30

    def __call__(self, trial: Trial, dx: np.ndarray, evaluate: Callable[[np.ndarray], Trial]) -> Trial | None:
        g = trial.residual
        slope = float(np.vdot(g, dx))
        if slope >= 0:
            dx = -g * (np.abs(dx).max() / max(np.abs(g).max(), 1e-30))
            slope = float(np.vdot(g, dx))
        alpha = 1.0
        for _ in range(self.max_halvings):
            try:
                got = evaluate(trial.x + alpha * dx)
            except InadmissibleState:
                alpha *= 0.5
                continue
            if got.merit <= trial.merit + self.c * alpha * slope + self.relative_slack * abs(trial.merit):
                return got
            if alpha == 1.0 and abs(got.merit - trial.merit) < self.merit_resolution and got.norm < trial.norm:
                return got
            alpha *= 0.5
        return None


@dataclass(frozen=True)
class ResidualDecrease:
    """Try the fractions ``alphas`` of the correction in turn and take the first that lowers
    the merit (the residual's norm); if none does, the best admissible one. Returns None
    when every trial is inadmissible."""

    alphas: Sequence[float] = (1.0, 0.5, 0.25, 0.125)

    def __call__(self, trial: Trial, dx: np.ndarray, evaluate: Callable[[np.ndarray], Trial]) -> Trial | None:
        best = None
        for alpha in self.alphas:
            try:
                got = evaluate(trial.x + alpha * dx)
            except InadmissibleState:
                continue
            if best is None or got.merit < best.merit:
                best = got
            if got.merit < trial.merit:
                break
        return best


@dataclass(frozen=True)
class SecantOnDirection:
    """Find a step along ``dx`` where the residual is nearly orthogonal to it:
    ``|s(a)| <= tolerance |s0|`` with ``s(a) = r(x + a dx) . dx`` and ``s0 = s(0) < 0`` (the
    criterion of FEBio's and NIKE3D's line search, after Matthies and Strang).

    The full step is tried first and taken if it passes or is still descending (``s(1) < 0``:
    the minimum along ``dx`` lies further on). Past the minimum (``s(1) > 0``) the zero of
    ``s`` is bracketed and found by regula falsi with the Illinois modification (the end that
    stays has its ``s`` halved, so a kink of ``s`` cannot stall it). Inadmissible trials are
    halved. Returns the trial with the smallest ``|s|`` when ``max_trials`` end the search,
    None when every trial is inadmissible.

    Why: penalty contact makes ``s`` kinked. From a state out of contact the Newton correction
    (whose tangent has no contact) drives the slaves deep into the master, where ``s`` is large
    and positive; fixed fractions of the correction all land in contact, and a residual-norm
    test then takes the least bad, from which the next correction (with contact) throws the
    slaves out again: a two-cycle that never converges (measured on the paper face at first
    touch). The bracketed zero stops the step where the contact engages.
    """

    tolerance: float = 0.9
    max_trials: int = 8

    def __call__(self, trial: Trial, dx: np.ndarray, evaluate: Callable[[np.ndarray], Trial]) -> Trial | None:
        s0 = float(np.vdot(trial.residual, dx))
        lo, s_lo, hi, s_hi = 0.0, s0, None, None
        alpha, kept, best = 1.0, 0, None
        for _ in range(self.max_trials):
            try:
                got = evaluate(trial.x + alpha * dx)
            except InadmissibleState:
                hi, s_hi = alpha, None
                alpha = 0.5 * (lo + alpha)
                continue
            s = float(np.vdot(got.residual, dx))
            if best is None or abs(s) < best[0]:
                best = (abs(s), got)
            if s0 >= 0 or abs(s) <= self.tolerance * abs(s0) or (hi is None and s < 0):
                return got
            if s > 0:
                hi, s_hi = alpha, s
                s_lo, kept = (0.5 * s_lo if kept == -1 else s_lo), -1  # lo stays a second time: Illinois
            else:
                lo, s_lo = alpha, s
                s_hi, kept = (0.5 * s_hi if kept == 1 and s_hi is not None else s_hi), 1
            alpha = 0.5 * (lo + hi) if s_hi is None else lo - s_lo * (hi - lo) / (s_hi - s_lo)
        return None if best is None else best[1]


def newton(start: Trial, evaluate: Callable[[np.ndarray], Trial], correction: Callable[[Trial], np.ndarray | None],
           converged: Callable[[Trial], bool], negligible: Callable[[Trial, np.ndarray], bool],
           line_search: Callable, max_iterations: int = 25,
           stalled: Callable[[Trial], bool] | None = None) -> NewtonResult:
    """Newton's method from the evaluated ``start`` (see the module for the callables).

    Each iteration: stop if ``converged``; take the ``correction`` (None: converged); accept
    ``x + dx`` outright if the correction is ``negligible``, else the ``line_search``'s
    trial. When the line search finds none, ``stalled(trial)`` may accept the current state
    (a round-off limit); otherwise :class:`NewtonFailed`, as after ``max_iterations``.
    """
    trial = start
    for it in range(1, max_iterations + 1):
        if converged(trial):
            return NewtonResult(trial, it - 1)
        dx = correction(trial)
        if dx is None:
            return NewtonResult(trial, it - 1)
        if negligible(trial, dx):
            try:
                return NewtonResult(evaluate(trial.x + dx), it)
            except InadmissibleState:
                pass
        found = line_search(trial, dx, evaluate)
        if found is None:
            if stalled is not None and stalled(trial):
                return NewtonResult(trial, it)
            raise NewtonFailed(f"line search found no acceptable step at Newton iteration {it} "
                               f"(residual {trial.norm:.3e})", it, trial.norm)
        trial = found
    raise NewtonFailed(f"no convergence in {max_iterations} iterations (residual {trial.norm:.3e})",
                       max_iterations, trial.norm)


class LoadSteps:
    """A load parameter walked from ``start`` over increasing ``stops``, in steps of at most
    ``max_step`` that end exactly on every stop.

    :meth:`cut` halves a failed step (False once the next would be below ``min_step``);
    :meth:`accept` moves on, and after a step of at most ``easy_iterations`` Newton
    iterations lets the next grow by ``growth`` (1: never) up to ``max_step``.

    Example::

        steps = LoadSteps([0.6, 1.2], max_step=0.3, min_step=1e-3, growth=1.5, easy_iterations=4)
        while not steps.done:
            a, b = steps.next()
            ...  # solve at b from the state at a; on failure: if not steps.cut(): raise
            if steps.accept(iterations) is not None:
                ...  # a stop was reached
    """

    def __init__(self, stops: Sequence[float], max_step: float, min_step: float, start: float = 0.0,
                 growth: float = 1.0, easy_iterations: int = 0):
        self.stops = np.asarray(stops, float)
        if self.stops.ndim != 1 or self.stops.size == 0 or np.any(np.diff(np.r_[start, self.stops]) <= 0):
            raise ValueError(f"load steps: stops {self.stops} must increase from the start {start}")
        if not 0 < min_step <= max_step or growth < 1:
            raise ValueError(f"load steps: need 0 < min_step {min_step} <= max_step {max_step} and growth "
                             f"{growth} >= 1")
        self.max_step, self.min_step, self.growth, self.easy = float(max_step), float(min_step), growth, easy_iterations
        self.value, self.step, self.index = float(start), float(max_step), 0
        self._snap = 1e-9 * float(self.stops[-1] - start)  # a remainder below this joins the step
        self._trial = None
        self.cuts = 0

    @property
    def done(self) -> bool:
        """All stops reached."""
        return self.index >= self.stops.size

    def next(self) -> tuple[float, float]:
        """The next step ``(from, to)``: at most the current step, ending on the stop ahead
        when the remainder would be negligible."""
        stop = float(self.stops[self.index])
        to = self.value + min(self.step, stop - self.value)
        if stop - to < self._snap:
            to = stop
        self._trial = (self.value, to)
        return self._trial

    def cut(self) -> bool:
        """The last step failed: halve it. False when the half would be below ``min_step``."""
        a, b = self._trial
        self.cuts += 1
        self.step = 0.5 * (b - a)
        return self.step >= self.min_step

    def accept(self, iterations: int) -> int | None:
        """The last step converged in ``iterations``; returns the index of the stop it
        reached, or None."""
        self.value = self._trial[1]
        if iterations <= self.easy:
            self.step = min(self.step * self.growth, self.max_step)
        if self.value >= float(self.stops[self.index]):
            self.index += 1
            return self.index - 1
        return None
