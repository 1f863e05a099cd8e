"""The parts :class:`~toolkit.common.fem.solvers.LinearSolver` is made of, each on its own: the
reuse policy (:class:`ReusePolicy`), the factor in use (:class:`StoredFactor`), the factor maker
with its PARDISO spare (:class:`FactorMaker`), the worker thread (:class:`FactorizeAhead`), and
the options (:class:`SolverOptions`)."""

from dataclasses import FrozenInstanceError

import numpy as np
import pytest
import scipy.sparse as sp

from toolkit.common.fem import pardiso
from toolkit.common.fem.ahead import FactorizeAhead
from toolkit.common.fem.factory import FactorMaker
from toolkit.common.fem.reuse import ReusePolicy, StoredFactor
from toolkit.common.fem.solvers import LinearSolver, SolverOptions, SolverStatistics

needs_mkl = pytest.mark.skipif(not pardiso.available(), reason="MKL (the 'pardiso' extra) is not installed")


def _laplacian(n=8):
    """A 3-dof-per-node SPD matrix: the 7-point Laplacian of an ``n^3`` grid on each component."""
    one = sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    eye = sp.identity(n)
    lap = sp.kron(sp.kron(one, eye), eye) + sp.kron(sp.kron(eye, one), eye) + sp.kron(sp.kron(eye, eye), one)
    return sp.kron(lap + 0.01 * sp.identity(n ** 3), sp.identity(3)).tocsr()


def test_the_policy_decides_by_counts():
    """A factor made ahead is due ``ahead`` solves after its start; a solve that factorized, or
    needed more than ``ahead_above`` iterations, leaves a stale factor; the budget after a
    factorization is the fixed cap, or (timed) what the factorization cost in applications."""
    policy = ReusePolicy(max_iterations=60, timed_budget=False, ahead=2, ahead_above=3)
    policy.count = 5
    assert not policy.due(4) and policy.due(3)
    assert policy.stale()  # nothing solved yet: the last solve "factorized"
    policy.solved(3, reused=True)
    assert not policy.stale()
    policy.solved(4, reused=True)
    assert policy.stale()
    policy.factorized(factor_s=1.0, apply_s=0.1, iterations=10)
    assert policy.budget == 60
    timed = ReusePolicy(max_iterations=60, timed_budget=True, ahead=0, ahead_above=0)
    timed.factorized(factor_s=0.2, apply_s=0.1, iterations=10)  # 0.01 s an application, 0.3 s in all
    assert timed.budget == 30


def test_the_solver_refactorizes_when_a_reuse_runs_out_of_budget():
    """With a budget of one Krylov iteration (< 2) a changed system is never reused: every new
    matrix is factorized; the same matrix again is solved on its own factor."""
    A = _laplacian(5)
    b = np.ones(A.shape[0])
    solver = LinearSolver("superlu", max_reuse_iterations=1, timed_budget=False)
    for k in range(3):
        S = (A + k * sp.identity(A.shape[0])).tocsr()
        x, info = solver.solve(S, b)
        assert not info.reused and np.linalg.norm(S @ x - b) <= 1e-10 * np.linalg.norm(b)
    x, info = solver.solve(S, b)
    assert info.reused and info.iterations == 0
    assert solver.factorizations == 3 and solver.stats.reuses == 1


def test_a_stored_factor_solves_its_own_system_and_preconditions_others():
    A = _laplacian(6)
    options = SolverOptions("superlu")
    made = FactorMaker(options, SolverStatistics()).make(A, True, None)
    stored = StoredFactor(made, A, True, background=False, threshold=0.05, single=False)
    b = np.random.default_rng(0).standard_normal(A.shape[0])
    assert made.exact and stored.holds(A) and not stored.holds((2 * A).tocsr())
    x, iterations = stored.solve_own(A, b, None, 1e-12)
    assert iterations == 0 and np.linalg.norm(A @ x - b) <= 1e-12 * np.linalg.norm(b)
    B = (A + sp.diags(np.linspace(0, 0.2, A.shape[0]))).tocsr()
    x, iterations = stored.iterate(B, b, None, True, None, 1e-10, 50)
    assert 1 <= iterations < 50 and np.linalg.norm(B @ x - b) <= 1e-10 * np.linalg.norm(b)
    # a local term that changed is corrected exactly: GMRES converges at once
    dofs = np.arange(0, 30, 3)
    C = sp.csr_matrix((np.full(dofs.size, 50.0), (dofs, dofs)), shape=A.shape)
    x, iterations = stored.iterate((A + C).tocsr(), b, None, False, C, 1e-10, 50)
    assert iterations <= 2 and stored.columns == dofs.size


@needs_mkl
def test_the_maker_refactorizes_a_retired_pardiso_factor():
    """A retired PARDISO factor is refactorized for the next system of its pattern (counted),
    and freed when it does not fit (another size); the maker's ordering is computed once."""
    A = _laplacian(6)
    stats = SolverStatistics()
    maker = FactorMaker(SolverOptions("pardiso"), stats)
    first = maker.make(A, True, None)
    perm = maker.ordering(A)
    maker.retire(first.factor)
    B = (A + sp.identity(A.shape[0])).tocsr()
    second = maker.make(B, True, None)
    assert second.factor is first.factor and stats.refactorizations == 1 and maker.ordering(B) is perm
    b = np.ones(A.shape[0])
    assert np.linalg.norm(B @ second.factor(b) - b) <= 1e-10 * np.linalg.norm(b)
    maker.retire(second.factor)
    small = _laplacian(4)
    third = maker.make(small, True, None)
    assert third.factor is not first.factor and stats.refactorizations == 1
    maker.close()


def test_the_worker_factorizes_the_system_it_was_given():
    """``start`` factorizes on a thread named ``toolkit-factorize-ahead``; ``take`` waits and hands
    over the factorization with the system it is of; ``close`` ends the thread."""
    import threading

    A = _laplacian(6)
    stats = SolverStatistics()
    maker = FactorMaker(SolverOptions("superlu"), stats)
    names = []
    make = maker.make
    maker.make = lambda *args: (names.append(threading.current_thread().name), make(*args))[1]
    ahead = FactorizeAhead(maker, stats)
    ahead.start(A, True, None, None, count=3)
    assert ahead.running and ahead.pending.started == 3
    made, pending = ahead.take()
    assert ahead.pending is None and pending.A is A and made.kind == "superlu" and stats.waited_s >= 0
    b = np.ones(A.shape[0])
    assert np.linalg.norm(A @ made.factor(b) - b) <= 1e-10 * np.linalg.norm(b)
    assert names and names[0].startswith("toolkit-factorize-ahead")
    ahead.close()
    assert not ahead.running


def test_options_are_checked_frozen_and_taken_by_the_solver():
    options = SolverOptions("superlu", reuse_rtol=1e-10, factorize_ahead=2)
    with pytest.raises(FrozenInstanceError):
        options.rtol = 1.0
    solver = LinearSolver.from_options(options)
    assert solver.options == options
    assert LinearSolver("superlu", reuse_rtol=1e-10, factorize_ahead=2).options == options
    with pytest.raises(ValueError, match="unknown solver 'lu'"):
        SolverOptions("lu")
    with pytest.raises(ValueError, match="unknown ordering 'amd'"):
        LinearSolver(ordering="amd")
    with pytest.raises(TypeError):
        LinearSolver(no_such_option=1)
    with pytest.raises(AttributeError, match="'timed_budget' is set at construction"):
        solver.timed_budget = False  # would otherwise be a silent no-op
