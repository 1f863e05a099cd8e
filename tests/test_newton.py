"""The shared Newton solve (:mod:`toolkit.common.fem.newton`) on problems with known roots,
and its load-step walk. Both workflows solve through it: the static Neo-Hookean face
(energy line search, sub-steps; tests/static) and the quasi-static impact path (residual line
search, adaptive steps; tests/impact/test_quasi_static.py)."""

import numpy as np
import pytest

from toolkit.common.fem.newton import (
    ArmijoOnMerit,
    InadmissibleState,
    LoadSteps,
    NewtonFailed,
    ResidualDecrease,
    SecantOnDirection,
    Trial,
    newton,
)


def _cubic(b):
    """Energy ``sum(x^4/4 - b x)``: gradient ``x^3 - b``, root ``b^(1/3)``, Hessian ``3 x^2``."""
    def evaluate(x):
        return Trial(x, x ** 3 - b, float(np.sum(x ** 4 / 4 - b * x)))

    def correction(trial):
        return -trial.residual / (3 * trial.x ** 2)

    return evaluate, correction


def _never_negligible(trial, dx):
    return False


def test_armijo_newton_converges_quadratically_from_far_away():
    """From x = 0.01 the full Newton step overshoots by ~10^4 (the tangent 3x^2 is tiny): the
    energy line search must shorten it, and near the root the residual must fall
    quadratically (r_{k+1} <= 2 r_k^2 once r_k < 0.1; Newton's constant here is
    f''/(2 f'^2) ~ 6 x / (2 * 9 x^4) ~ 0.08 at x ~ 2)."""
    b = np.array([8.0, 27.0, 0.5])
    evaluate, correction = _cubic(b)
    norms = []

    def converged(trial):
        norms.append(trial.norm)
        return trial.norm < 1e-12

    result = newton(evaluate(np.full(3, 0.01)), evaluate, correction, converged, _never_negligible,
                    ArmijoOnMerit(), max_iterations=60)
    np.testing.assert_allclose(result.trial.x, np.cbrt(b), rtol=1e-12)
    near = [(a, c) for a, c in zip(norms, norms[1:]) if a < 0.1]
    assert near and all(c <= 2 * a * a for a, c in near)


def test_residual_line_search_skips_inadmissible_states():
    """``ln x = 0`` from x = 5: the full Newton step (-x ln x = -8.0) lands at x < 0, where the
    residual is undefined (an inverted element); the half step is taken instead."""
    seen = []

    def evaluate(x):
        if np.any(x <= 0):
            seen.append(float(x[0]))
            raise InadmissibleState("x <= 0")
        r = np.log(x)
        return Trial(x, r, float(np.linalg.norm(r)))

    result = newton(evaluate(np.array([5.0])), evaluate, lambda t: -t.residual * t.x,
                    lambda t: t.norm < 1e-13, _never_negligible, ResidualDecrease())
    assert seen and seen[0] < 0
    np.testing.assert_allclose(result.trial.x, [1.0], atol=1e-12)


def test_the_secant_line_search_converges_where_contact_makes_residual_fractions_cycle():
    """A node pulled towards x = 2 by a spring (1 N/mm) through a penalty wall at x = 0
    (100 N/mm): equilibrium at x* = 2/101 mm. The tangent in contact takes only 30 % of the
    penalty, as the contact tangent of the impact path underestimates it (the secant of a
    slipping friction spring, the normal's turning left out). Fixed fractions of the correction
    judged by the residual norm then cycle in and out of the wall (measured: no convergence in
    25 iterations, as on the paper face at first touch); the bracketed secant on ``r . dx``
    stops each correction where the wall engages and converges (measured: 4 iterations)."""
    def evaluate(x):
        r = (x - 2.0) + 100.0 * np.maximum(x, 0.0)
        return Trial(x, r, float(np.linalg.norm(r)))

    def correction(trial):
        return -trial.residual / (1.0 + 30.0 * (trial.x > 0))

    start = evaluate(np.array([-1.0, -0.3]))
    done = newton(start, evaluate, correction, lambda t: t.norm < 1e-12, _never_negligible, SecantOnDirection(),
                  max_iterations=8)
    np.testing.assert_allclose(done.trial.x, 2.0 / 101.0, rtol=1e-12)
    with pytest.raises(NewtonFailed, match="no convergence"):
        newton(start, evaluate, correction, lambda t: t.norm < 1e-12, _never_negligible, ResidualDecrease())


def test_newton_reports_where_it_failed():
    evaluate, correction = _cubic(np.array([8.0]))
    with pytest.raises(NewtonFailed, match="no convergence in 2 iterations") as info:
        newton(evaluate(np.array([0.01])), evaluate, correction, lambda t: t.norm < 1e-12, _never_negligible,
               ArmijoOnMerit(), max_iterations=2)
    assert info.value.iteration == 2 and info.value.residual > 1.0

    def nowhere(x):  # every trial inadmissible: the line search finds nothing
        if x[0] != 0.01:
            raise InadmissibleState("no")
        return evaluate(x)

    with pytest.raises(NewtonFailed, match="line search found no acceptable step at Newton iteration 1"):
        newton(evaluate(np.array([0.01])), nowhere, correction, lambda t: False, _never_negligible,
               ResidualDecrease())
    # a stalled line search is accepted where the caller says the residual is at its round-off limit
    got = newton(evaluate(np.array([0.01])), nowhere, correction, lambda t: False, _never_negligible,
                 ResidualDecrease(), stalled=lambda t: True)
    assert got.iterations == 1 and got.trial.x[0] == 0.01


def test_armijo_turns_an_ascent_direction_into_steepest_descent():
    """A correction of the wrong sign (an indefinite tangent) must not be searched along."""
    evaluate, _ = _cubic(np.array([8.0]))
    start = evaluate(np.array([1.0]))  # residual -7: descent is +x
    got = ArmijoOnMerit()(start, np.array([-0.5]), evaluate)
    assert got.x[0] > 1.0 and got.merit < start.merit


def test_load_steps_end_on_every_stop_cut_failures_and_grow_after_easy_steps():
    steps = LoadSteps([0.5, 1.0], max_step=0.3, min_step=0.05, growth=1.5, easy_iterations=2)
    assert steps.next() == (0.0, 0.3)
    assert steps.accept(5) is None  # hard: no growth
    assert steps.next() == (0.3, 0.5)  # ends on the stop
    assert steps.cut() and steps.step == pytest.approx(0.1)
    assert steps.next() == (0.3, pytest.approx(0.4))
    assert steps.accept(1) is None  # easy: 0.1 -> 0.15
    a, b = steps.next()
    assert b == 0.5  # a remainder of 0.1 < 0.15: the step ends on the stop exactly
    assert steps.accept(1) == 0 and steps.step == pytest.approx(0.225)
    while not steps.done:
        steps.next()
        steps.accept(1)
    assert steps.value == 1.0 and steps.cuts == 1
    # cutting below min_step is refused
    tight = LoadSteps([1.0], max_step=1.0, min_step=0.25)
    tight.next()
    assert tight.cut() and tight.next() == (0.0, 0.5)
    assert tight.cut() and tight.next() == (0.0, 0.25)
    assert not tight.cut()  # 0.125 < 0.25


@pytest.mark.parametrize("stops, kwargs", [([0.5, 0.5], {}), ([], {}), ([1.0], {"min_step": 2.0}),
                                           ([1.0], {"growth": 0.5})])
def test_load_steps_refuse_bad_input(stops, kwargs):
    args = {"max_step": 1.0, "min_step": 0.1, **kwargs}
    with pytest.raises(ValueError, match="load steps"):
        LoadSteps(stops, **args)
