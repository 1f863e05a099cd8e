"""Factorizing ahead: one worker thread that factorizes a system while the solves go on with an
older factor (SuperLU, PARDISO and CHOLMOD release the GIL, so the worker runs on a second core).

A factor made on the worker is freed on the worker: scipy's SuperLU objects freed on another
thread than the one that made them keep their memory (scipy issue #15921; otherwise a paper
impact run's memory grows with every factor it frees)."""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import scipy.sparse as sp

from toolkit.common.fem.factory import Factorization, FactorMaker

__all__ = ["FactorizeAhead", "Pending"]

log = logging.getLogger(__name__)

#: the worker thread's name prefix
THREAD_NAME = "toolkit-factorize-ahead"


@dataclass(frozen=True, eq=False)
class Pending:
    """A factorization running on the worker: its future, the solve count at its start, the
    system and whether it is SPD."""

    future: Future
    started: int
    A: sp.csr_matrix
    symmetric: bool


class FactorizeAhead:
    """The worker thread of a :class:`~toolkit.common.fem.solvers.LinearSolver` and the
    factorization it runs (:attr:`pending`, one at a time), made by ``maker``. ``stats``:
    ``waited_s`` counts the seconds the solves waited for it."""

    def __init__(self, maker: FactorMaker, stats):
        self.maker, self.stats = maker, stats
        self.pending: Pending | None = None
        self._worker: ThreadPoolExecutor | None = None

    @property
    def running(self) -> bool:
        """Whether the worker thread exists."""
        return self._worker is not None

    def start(self, A: sp.csr_matrix, symmetric: bool, near_nullspace, local, count: int) -> None:
        """Factorize ``A`` on the worker, started at solve ``count``."""
        if self._worker is None:
            self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix=THREAD_NAME)
        future = self._worker.submit(self.maker.make, A, symmetric, near_nullspace, local)
        self.pending = Pending(future, count, A, symmetric)

    def take(self) -> tuple[Factorization | None, Pending]:
        """Wait for the pending factorization and forget it; returns what it made (None when it
        failed: the next failed reuse factorizes in the foreground and reports) and its
        :class:`Pending`."""
        pending = self.pending
        t0 = time.perf_counter()
        error = pending.future.exception()  # waits
        self.stats.waited_s += time.perf_counter() - t0
        if error is not None:
            log.warning("background factorization failed (%s); keeping the previous factor", error)
        made = pending.future.result() if error is None else None
        self.drop()
        return made, pending

    def drop(self) -> None:
        """Forget the pending factorization, freeing it on the worker once it is done."""
        if self.pending is not None:
            box = [self.pending.future]  # the future holds the factor
            self.pending = None
            self.free(box)

    def free(self, box: list) -> None:
        """Free the objects in ``box`` (a list holding the only references to them: factors made
        on the worker, and what refers to them) on the worker."""
        self._worker.submit(box.clear)

    def spare_alongside(self, A: sp.csr_matrix, symmetric: bool, near_nullspace) -> None:
        """At the first PARDISO factorization of a solver that factorizes ahead: the worker, idle
        until then, factorizes the same system beside the foreground and keeps it as the spare
        that the first factor made ahead refactorizes (a refactorization skips the symbolic
        analysis, and this is where the worker is furthest behind the solves). Either factor is
        the same, whichever thread finishes first."""
        if self._worker is not None or self.maker.kind(A) != "pardiso":
            return
        if self.maker.options.ordering == "nd":
            self.maker.ordering(A)  # before the worker starts: one ordering for both
        maker = self.maker

        def spare() -> None:
            maker.retire(maker.make(A, symmetric, near_nullspace).factor)

        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix=THREAD_NAME)
        self._worker.submit(spare)

    def close(self) -> None:
        """End the worker thread, once its work is done."""
        if self._worker is not None:
            self._worker.shutdown(wait=True)
            self._worker = None
