"""The linear response of a face with the FE's own boundary conditions: bone-driven nodes
prescribed, mucosa sliding on its bone, lip pairs in contact.

:class:`SlidingResponse` solves one linear-elastic increment on the pre-operative mesh with the
constraints of :func:`~toolkit.static.simulate.simulate`'s first solve of each step:

- moving nodes follow their bone (all three components prescribed), fixed nodes stay;
- each sliding mucosa node keeps its distance to its bone: the component of its displacement
  along the bone's normal (at its closest point on the pre-operative bone, or away from the bone
  for a node off it) equals that of its bone's motion there, the two tangential ones are free;
- upper/lower lip pairs whose craniocaudal gap is within the lip threshold are tied along that
  axis, and the active set is iterated like :func:`~toolkit.static.problem.solve_with_lip_contact`
  (a pair is released when its tie pulls, a free pair tied when it would interpenetrate).

What it leaves out is the FE's nonlinearity: the geometry update between increments, the
projection back onto the moved bone and the bone normals turning with it. The reduced stiffness
is factorized once per face; the lip ties are added to it by their Schur complement (one
back-substitution per lip pair, once), so an increment costs one back-substitution and a small
dense solve per active-set iteration.

The baseline of :mod:`toolkit.static.trust` adds a regression of what this response misses. On
one increment of the coarse phantom the response alone is more accurate than the influence
matrix (:class:`~toolkit.static.baselines.InfluenceMatrix`, mucosa and lips free), and with the
regression more accurate than the influence matrix with it (``docs/surrogates.md``).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from toolkit.common.fem.solvers import superlu
from toolkit.static.constraints import Constraints
from toolkit.static.database import bone_increment
from toolkit.static.plan import PlanRangeWarning, SurgicalPlan
from toolkit.static.problem import StaticProblem
from toolkit.static.simulate import SimulationOptions, _build_model, _sliding_constraints, _State

__all__ = ["SlidingResponse"]

#: mm: a free lip pair is tied when its gap would close below minus this, as in the FE
_PENETRATION_TOL = 1e-6
#: active-set iterations before giving up (the FE allows 20)
_MAX_CONTACT_ITERATIONS = 30


@dataclass(frozen=True, eq=False)
class SlidingResponse:
    """One linear increment of a face under the FE's boundary conditions (see the module).

    Attributes
    ----------
    points : (n, 3) mm — the pre-operative nodes
    bc : the BoundaryConditions of the FE (release bands, sliding model, far mucosa freed)
    moving : (m,) int64 — nodes whose three components follow their bone
    mucosa : (s,) int64 — sliding mucosa nodes; normals : (s, 3) unit, their constrained direction
    upper, lower : (p,) int64 — lip pairs (slave, master), tied along z when in contact
    lip_threshold : mm, the gap within which a pair starts tied
    seconds : time to build, s
    """

    points: np.ndarray
    bc: object
    moving: np.ndarray
    mucosa: np.ndarray
    normals: np.ndarray
    upper: np.ndarray
    lower: np.ndarray
    lip_threshold: float
    seconds: float
    _A: sp.csr_matrix  # (3n, q): the free unknowns (free nodes' dofs, mucosa tangential) -> u
    _B: sp.csr_matrix  # (3n, d): the driven values (moving dofs, mucosa normal) -> u
    _KAB: sp.csr_matrix  # (q, d): A^T K B
    _solve: object  # (A^T K A)^-1
    _C: sp.csr_matrix  # (p, q): each lip pair's craniocaudal gap change from the free unknowns
    _CB: sp.csr_matrix  # (p, d): ... from the driven values
    _Z: np.ndarray  # (q, p): (A^T K A)^-1 C^T
    _CZ: np.ndarray  # (p, p)

    @classmethod
    def build(cls, face, sliding: str, segments=None, options=None) -> SlidingResponse:
        """The response of ``face`` (a FacePhantom, or a Mesh with ``segments``) under the
        boundary conditions :func:`~toolkit.static.simulate.simulate` gives it with the ``sliding``
        model and ``options`` (SimulationOptions: release bands, lip threshold, mucosa offset), on
        the linear material. Raises ValueError for a mesh whose moving and fixed nodes leave it
        free to move rigidly."""

        t0 = time.perf_counter()
        options = options or SimulationOptions()
        model = _build_model(face, "linear", sliding, segments, options)
        X = model.mesh.points
        n = X.shape[0]
        at_rest = _State(0.0, None, np.zeros_like(X))
        c = _sliding_constraints(model, at_rest, SurgicalPlan({}), X, X, np.zeros(0, np.int64), np.zeros((0, 3)))
        mucosa, normals = c.sliding_nodes, c.sliding_normals
        moving = model.moving
        held = np.concatenate([model.fixed, moving])
        # the free unknowns: the FE's own elimination of these constraints (values 0)
        A = Constraints(n, held, np.zeros((held.size, 3)), mucosa, normals, np.zeros(mucosa.size)).reduction()[0]
        B = _driven_basis(n, moving, mucosa, normals)
        K = StaticProblem(model.mesh, model.materials, "superlu").stiffness.tocsr()
        try:
            solve = superlu((A.T @ K @ A).tocsc())
        except Exception as exc:  # noqa: BLE001 - a singular reduced stiffness: a rigid motion is left free
            raise ValueError(f"the face's reduced stiffness cannot be factorized ({exc}): its moving and fixed "
                             "nodes must hold it against rigid motion") from exc
        upper, lower = model.bc.upper_lip.astype(np.int64), model.bc.lower_lip.astype(np.int64)
        p = upper.size
        rows, cols = np.r_[np.arange(p), np.arange(p)], np.r_[3 * upper + 2, 3 * lower + 2]
        gap_change = sp.csr_matrix((np.r_[np.ones(p), -np.ones(p)], (rows, cols)), shape=(p, 3 * n))
        C = (gap_change @ A).tocsr()
        Z = solve(C.T.toarray()).reshape(A.shape[1], p) if p else np.zeros((A.shape[1], 0))
        return cls(X, model.bc, moving, mucosa, normals, upper, lower, float(options.lip_threshold),
                   time.perf_counter() - t0, A, B, (A.T @ K @ B).tocsr(), solve, C, (gap_change @ B).tocsr(), Z,
                   np.asarray(C @ Z))

    def increment(self, bone: np.ndarray, x: np.ndarray | None = None) -> np.ndarray:
        """Displacement ``(n, 3)`` mm of one increment whose bones move each bone-driven node by
        ``bone (n, 3)`` mm (:func:`~toolkit.static.database.bone_increment`; other rows ignored),
        with the lip gaps of the current positions ``x (n, 3)`` mm (default: none, every pair
        starts tied; pass the positions the increment starts from)."""
        bone = np.asarray(bone, dtype=float)
        if bone.shape != self.points.shape:
            raise ValueError(f"bone motion has shape {bone.shape}; expected {self.points.shape} mm")
        d = np.concatenate([bone[self.moving].ravel(), np.einsum("ij,ij->i", self.normals, bone[self.mucosa])])
        q = -self._solve(self._KAB @ d)
        if self.upper.size:
            gap = (np.zeros(self.upper.size) if x is None
                   else np.asarray(x)[self.upper, 2] - np.asarray(x)[self.lower, 2])
            q = q - self._Z @ self._tie_forces(self._C @ q + self._CB @ d, gap)
        return np.asarray(self._A @ q + self._B @ d).reshape(-1, 3)

    def _tie_forces(self, opening: np.ndarray, gap: np.ndarray) -> np.ndarray:
        """The lip ties' multipliers ``(p,)`` (zero for released pairs): ``opening`` is each
        pair's gap change without ties, ``gap`` its gap before the increment (mm). An active set
        still changing after :data:`_MAX_CONTACT_ITERATIONS` iterations gives its last
        multipliers (a baseline answers; the FE raises there)."""
        active = gap <= self.lip_threshold
        seen = set()
        for _ in range(_MAX_CONTACT_ITERATIONS):
            S = np.flatnonzero(active)
            lam = np.zeros(gap.size)
            if S.size:  # tied: the gap closes to 0, C q = -gap
                lam[S] = np.linalg.solve(self._CZ[np.ix_(S, S)], opening[S] + gap[S])
            gaps = gap + opening - self._CZ[:, S] @ lam[S]
            release = active & (lam > 1e-12 * max(np.abs(lam).max(), 1e-30))  # the tie pulls the lips together
            add = ~active & (gaps < -_PENETRATION_TOL)
            if not release.any() and not add.any():
                return lam
            new = (active & ~release) | add
            if new.tobytes() in seen:  # cycling: keep the pairs that penetrate tied, as the FE does
                new = active | add
            seen.add(new.tobytes())
            active = new
        return lam

    def trajectory(self, plan, increments: int, correction: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
        """``plan`` in ``increments`` equal steps, each step's bone motion taken at the positions
        the previous steps reached, plus ``correction[k]`` ``(increments, n, 3)`` mm in step ``k``
        when given.

        Returns the cumulative displacement ``(increments + 1, n, 3)`` mm (row 0 zero) and each
        step's bone motion ``(increments, n, 3)`` mm (zero off the bone-driven nodes)."""

        with warnings.catch_warnings():  # the plan warned of its range where it was built
            warnings.simplefilter("ignore", PlanRangeWarning)
            steps = plan.increments(increments)
        U, bones = [np.zeros_like(self.points)], []
        previous = None
        for k, step in enumerate(steps):
            x = self.points + U[-1]
            bones.append(bone_increment(x, self.bc, step, previous))
            U.append(U[-1] + self.increment(bones[-1], x) + (0.0 if correction is None else correction[k]))
            previous = step
        return np.stack(U), np.stack(bones)


def _driven_basis(n: int, moving: np.ndarray, mucosa: np.ndarray, normals: np.ndarray) -> sp.csr_matrix:
    """``(3 n, 3 m + s)``: the driven values (each moving node's three components, then each
    mucosa node's displacement along its normal) to the nodal components."""
    dof = (3 * moving[:, None] + np.arange(3)).ravel()
    rows = np.r_[dof, (3 * mucosa[:, None] + np.arange(3)).ravel()]
    cols = np.r_[np.arange(dof.size), np.repeat(dof.size + np.arange(mucosa.size), 3)]
    vals = np.r_[np.ones(dof.size), normals.ravel()]
    return sp.csr_matrix((vals, (rows, cols)), shape=(3 * n, dof.size + mucosa.size))
