"""Two simple surrogates a network must beat.

- :class:`InfluenceMatrix`: linear superposition. On the pre-operative mesh, the
  stiffness is condensed on the nodes a bone drives (attached and mucosa, all moving
  with their bone: the lip-sliding paper's method without sliding) and the fixed nodes:
  ``u_free = H u_bone`` with ``H = -K_ff^-1 K_fb``, kept factored (one factorization, then
  one solve per prediction; the dense ``H`` is formed only when asked for). Where the factor
  would be too large (the fine phantom, a meshed face), ``K_ff`` is solved by conjugate
  gradients on an AMG hierarchy built once, the FE's own choice. Exact for a
  linear material without sliding or lip contact on the mesh it was built for, in one
  increment; it ignores sliding, lip contact and the geometry update between increments.
- :class:`PODRegression`: the displacements of the training samples are compressed by
  principal components (POD), and the component weights are regressed on the plan's
  parameters (ridge regression on quadratic features). It never sees a mesh, only plans.
- :class:`LinearPlusPOD`: the two together: the influence-matrix solution, plus a POD
  regression of what it misses (the FE displacement minus the linear one) on the plan's
  parameters. The residual (sliding, lip contact, geometry update) is smoother and smaller
  than the displacement, and it transfers across faces of one topology.

Both predict the displacement of one increment ``(n, 3)`` mm, like the FE and the network.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from toolkit.common.fem.factors import choose_method
from toolkit.common.fem.ordering import estimate_factor_entries
from toolkit.common.fem.solvers import superlu
from toolkit.common.meshes.mesh import Mesh
from toolkit.static.problem import StaticProblem
from toolkit.static.simulate import material_assignment

__all__ = ["InfluenceMatrix", "PODRegression", "LinearPlusPOD", "quadratic_features"]


@dataclass(frozen=True, eq=False)
class InfluenceMatrix:
    """Linear influence of the bone-driven nodes' displacement on every other node.

    Attributes
    ----------
    driven : (m,) int64 — nodes whose displacement is an input (attached and mucosa nodes)
    fixed : (f,) int64 — nodes held at zero
    free : (k,) int64 — the others
    coupling : (3k, 3m) sparse — ``K_fb``, the free rows and driven columns of the stiffness, N/mm
    solve : ``b (3k,) or (3k, s) -> K_ff^-1 b`` (3k, 3k), by a factorization or AMG-CG
    seconds : time to build (assembly and factorization), s
    method : how ``solve`` solves: ``superlu`` or ``amg``
    """

    driven: np.ndarray
    fixed: np.ndarray
    free: np.ndarray
    coupling: sp.csr_matrix
    solve: Callable[[np.ndarray], np.ndarray]
    seconds: float
    method: str = "superlu"

    @property
    def H(self) -> np.ndarray:
        """The dense influence matrix ``(3k, 3m)``: ``u_free.ravel() = H @ u_driven.ravel()``,
        one solve per driven dof, formed on each call (``8 * 3k * 3m`` bytes: 0.1 GB on the
        paper phantom, beyond memory on a meshed face; :meth:`predict` never forms it)."""
        return -self.solve(self.coupling.toarray())

    @classmethod
    def build(cls, mesh: Mesh, driven: np.ndarray, fixed: np.ndarray, materials="linear",
              solver: str = "auto") -> InfluenceMatrix:
        """Condense the linear stiffness of ``mesh`` (mm, N/mm) on ``driven`` and ``fixed`` nodes.

        Parameters
        ----------
        mesh : the pre-operative mesh
        driven, fixed : node indices (disjoint)
        materials : ``linear`` (the lip-sliding paper: the lip muscle transversely isotropic) or a
            MaterialAssignment of linear materials
        solver : ``auto`` (SuperLU while the factor's expected size is below
            :data:`~toolkit.common.fem.factors.AUTO_DIRECT_MAX_ENTRIES`, else AMG-CG, as the FE
            chooses), ``superlu`` or ``amg``
        """

        t0 = time.perf_counter()
        driven, fixed = np.unique(np.asarray(driven, np.int64)), np.unique(np.asarray(fixed, np.int64))
        if np.intersect1d(driven, fixed).size:
            raise ValueError("driven and fixed nodes overlap; a node is driven by a bone or fixed, not both")
        assignment = material_assignment(materials, mesh)
        if not assignment.is_linear:
            raise ValueError("the influence matrix needs a linear material (it superposes unit responses)")
        if solver not in ("auto", "superlu", "amg"):
            raise ValueError(f"solver = {solver!r}; expected 'auto', 'superlu' or 'amg'")
        problem = StaticProblem(mesh, assignment, "amg" if solver == "auto" else solver)
        K = problem.stiffness.tocsr()
        if solver == "auto":
            solver = choose_method("auto", K.shape[0], estimate_factor_entries(problem.pattern.node_graph()))
        free = np.setdiff1d(np.arange(mesh.n_points), np.concatenate([driven, fixed]))
        dof = lambda nodes: (3 * nodes[:, None] + np.arange(3)).ravel()  # noqa: E731
        f, b = dof(free), dof(driven)
        Kf = K[f]
        Kff = Kf[:, f]
        if solver == "superlu":
            solve = superlu(Kff.tocsc())
        else:
            T = sp.identity(K.shape[0], format="csr")[:, f]

            def solve(rhs: np.ndarray) -> np.ndarray:
                rhs = np.asarray(rhs, dtype=float)
                columns = [problem.solve_reduced(T, Kff, c)[0] for c in rhs.reshape(rhs.shape[0], -1).T]
                return np.stack(columns, axis=1).reshape(rhs.shape)

        return cls(driven, fixed, free, Kf[:, b].tocsr(), solve, time.perf_counter() - t0, solver)

    def predict(self, driven_displacement: np.ndarray) -> np.ndarray:
        """Displacement ``(n, 3)`` mm from the driven nodes' displacement ``(m, 3)`` mm (or
        ``(n, 3)`` of which the driven rows are read); fixed nodes 0."""
        d = np.asarray(driven_displacement, dtype=float)
        n = self.driven.size + self.fixed.size + self.free.size
        if d.shape == (n, 3):
            d = d[self.driven]
        if d.shape != (self.driven.size, 3):
            raise ValueError(f"driven displacement has shape {d.shape}; expected ({self.driven.size}, 3) or ({n}, 3)")
        u = np.zeros((n, 3))
        u[self.driven] = d
        u[self.free] = -self.solve(self.coupling @ d.ravel()).reshape(-1, 3)
        return u


def quadratic_features(x: np.ndarray) -> np.ndarray:
    """``[1, x, x_i x_j (i <= j)]`` per row: ``(s, p)`` -> ``(s, 1 + p + p (p + 1) / 2)``."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    i, j = np.triu_indices(x.shape[1])
    return np.hstack([np.ones((x.shape[0], 1)), x, x[:, i] * x[:, j]])


@dataclass(frozen=True, eq=False)
class PODRegression:
    """Principal components of the displacements, regressed on plan parameters.

    Attributes
    ----------
    mean : (3n,) mm — mean displacement of the training samples
    modes : (r, 3n) — orthonormal POD modes
    coef : (q, r) — ridge coefficients from quadratic features to mode weights
    x_scale : (2, p) — min and range of the parameters (scaled to [0, 1] before the features)
    energy : float — share of the training variance the modes keep
    """

    mean: np.ndarray
    modes: np.ndarray
    coef: np.ndarray
    x_scale: np.ndarray
    energy: float

    @classmethod
    def fit(cls, params: np.ndarray, displacements: np.ndarray, modes: int | None = None, energy: float = 0.9999,
            ridge: float = 1e-6) -> PODRegression:
        """Fit on ``params (s, p)`` (plan parameters of each sample) and ``displacements (s, n, 3)`` mm.

        ``modes``: how many to keep (default: the fewest keeping ``energy`` of the variance,
        at most s - 1); ``ridge``: Tikhonov weight relative to the feature scale.
        """
        X = np.asarray(params, dtype=float)
        Y = np.asarray(displacements, dtype=float).reshape(len(X), -1)
        if X.ndim != 2 or len(X) < 2:
            raise ValueError(f"params has shape {X.shape}; expected (samples >= 2, parameters)")
        mean = Y.mean(axis=0)
        _, s, vt = np.linalg.svd(Y - mean, full_matrices=False)
        cum = np.cumsum(s**2) / max(np.sum(s**2), 1e-300)
        r = int(modes) if modes is not None else int(np.searchsorted(cum, energy) + 1)
        r = max(1, min(r, len(s)))
        V = vt[:r]
        W = (Y - mean) @ V.T
        lo, span = X.min(axis=0), np.ptp(X, axis=0)
        span[span == 0] = 1.0
        F = quadratic_features((X - lo) / span)
        A = F.T @ F
        coef = np.linalg.solve(A + ridge * np.trace(A) / A.shape[0] * np.eye(A.shape[0]), F.T @ W)
        return cls(mean, V, coef, np.stack([lo, span]), float(cum[r - 1]))

    def predict(self, params: np.ndarray) -> np.ndarray:
        """Displacements ``(s, n, 3)`` mm for ``params (s, p)``."""
        X = np.atleast_2d(np.asarray(params, dtype=float))
        if X.shape[1] != self.x_scale.shape[1]:
            raise ValueError(f"params have {X.shape[1]} columns; this model was fit on {self.x_scale.shape[1]}")
        W = quadratic_features((X - self.x_scale[0]) / self.x_scale[1]) @ self.coef
        return (self.mean + W @ self.modes).reshape(len(X), -1, 3)


@dataclass(frozen=True, eq=False)
class LinearPlusPOD:
    """Linear superposition corrected by a POD regression of its residual.

    ``predict(params, linear)`` = ``linear`` (the influence-matrix solution of each sample) +
    the POD regression of the FE minus linear displacement on ``params``. The influence matrix is per mesh (pass the one
    of the face being predicted); the residual regression is shared by every face of one
    topology (node-indexed).

    Attributes
    ----------
    residual : PODRegression of the FE minus linear displacement (mm) on the plan parameters
    """

    residual: PODRegression

    @classmethod
    def fit(cls, params: np.ndarray, displacements: np.ndarray, linear: np.ndarray, **pod) -> LinearPlusPOD:
        """Fit on ``params (s, p)``, the FE ``displacements (s, n, 3)`` mm and the influence-matrix
        solutions of the same samples ``linear (s, n, 3)`` mm (``pod``: PODRegression.fit options)."""
        d, lin = np.asarray(displacements, dtype=float), np.asarray(linear, dtype=float)
        if d.shape != lin.shape:
            raise ValueError(f"displacements {d.shape} and linear solutions {lin.shape} must have the same shape")
        return cls(PODRegression.fit(params, d - lin, **pod))

    def predict(self, params: np.ndarray, linear: np.ndarray) -> np.ndarray:
        """Displacements ``(s, n, 3)`` mm for ``params (s, p)`` given their linear solutions
        ``(s, n, 3)`` mm (:meth:`InfluenceMatrix.predict` of each sample's prescribed values)."""
        return np.asarray(linear, dtype=float) + self.residual.predict(params)
