"""Finite-strain J2 (von Mises) elastoplasticity with isotropic hardening (units: MPa, mm, s, tonne).

The formulation is the hyperelastic-based one of Simo (1992) and Eterovic & Bathe (1990),
written for an explicit solver that updates every integration point once per time step:

- multiplicative split ``F = Fe Fp``; elastic left Cauchy-Green tensor ``be = Fe Fe^T``;
- Hencky (logarithmic) elastic strain ``eps_e = 1/2 ln(be)``, taken in the principal
  directions ``n_i`` of ``be``;
- Kirchhoff stress ``tau = lam tr(eps_e) I + 2 mu eps_e`` (isotropic, so coaxial with ``be``);
- trial state ``be_trial = f be_old f^T`` with the relative deformation gradient
  ``f = F_new F_old^-1``;
- radial return of the deviatoric principal Kirchhoff stress onto the von Mises cylinder
  ``q = sqrt(3/2) |dev tau| = sigma_y(eps_p)``, plastic flow isochoric, and the exponential
  map ``be_new = sum_i exp(2 eps_e_i) n_i n_i``.

Because the hardening curve :class:`HardeningTable` is piecewise linear, the consistency
condition ``q_trial - 3 mu d_eps_p = sigma_y(eps_p + d_eps_p)`` is solved *exactly* without
iterating: ``h(x) = sigma_y(x) + 3 mu x`` is piecewise linear and strictly increasing in the
new plastic strain ``x``, so ``x = h^-1(q_trial + 3 mu eps_p)`` is one linear interpolation
over the table's knots (slope ``3 mu`` beyond the last point, where the material is perfectly
plastic). The update is objective (a superposed rotation ``F -> Q F`` rotates ``be`` and the
stresses and leaves ``eps_p`` unchanged) and, for proportional loading in fixed principal
axes, exact whatever the step size.

The seed-002 materials (:data:`SEED002_FACE`, :data:`SEED002_BALL`) use SPEC's reading of the
paper's yield tables as MPa. The face's initial yield stress (0.015 MPa) equals its Young's
modulus, so in uniaxial tension it first yields at a Hencky strain ``ln(l) = sigma_y / E = 1``
(a stretch of ``e ~ 2.7``): the face is effectively hyperelastic (Hencky) at every strain an
impact reaches. The ball (E = 0.38 MPa, yield 0.034 MPa) yields at a Hencky strain of ~0.09.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from toolkit.common.materials import IsotropicModuli, _check
from toolkit.common.phantom import ball_density

__all__ = [
    "HardeningTable",
    "PlasticState",
    "StressUpdate",
    "J2Plasticity",
    "von_mises",
    "FACE_TABLE",
    "BALL_TABLE",
    "SEED002_FACE",
    "SEED002_BALL",
]

_SQRT_3_2 = np.sqrt(1.5)
#: relative tolerance of the yield check, so that a state already on the yield surface
#: (or rigidly rotated) does not flow by round-off
_YIELD_RTOL = 1e-10


@dataclass(frozen=True, eq=False)
class HardeningTable:
    """Piecewise-linear yield stress against equivalent plastic strain.

    Attributes
    ----------
    yield_stress : (k,) float, MPa, all positive
    plastic_strain : (k,) float, dimensionless; starts at 0 and strictly increases.
        Beyond the last point the material is perfectly plastic (constant yield stress).
    """

    yield_stress: np.ndarray
    plastic_strain: np.ndarray
    _work: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        y = np.array(self.yield_stress, dtype=np.float64, ndmin=1)
        e = np.array(self.plastic_strain, dtype=np.float64, ndmin=1)
        if y.ndim != 1 or e.ndim != 1 or y.shape != e.shape or y.size == 0:
            raise ValueError(f"HardeningTable: yield_stress {y.shape} and plastic_strain {e.shape} "
                             "must be non-empty 1-D arrays of the same length")
        for name, a in (("yield_stress", y), ("plastic_strain", e)):
            bad = np.flatnonzero(~np.isfinite(a))
            if bad.size:
                raise ValueError(f"HardeningTable: {name}[{bad[0]}] = {float(a[bad[0]])!r} is not finite")
        bad = np.flatnonzero(y <= 0)
        if bad.size:
            raise ValueError(f"HardeningTable: yield_stress[{bad[0]}] = {float(y[bad[0]])!r} MPa must be positive")
        if e[0] != 0.0:
            raise ValueError(f"HardeningTable: the first plastic strain is {float(e[0])!r}; it must be 0 "
                             "(the initial yield stress)")
        bad = np.flatnonzero(np.diff(e) <= 0)
        if bad.size:
            i = bad[0] + 1
            raise ValueError(f"HardeningTable: plastic_strain[{i}] = {float(e[i])!r} does not exceed "
                             f"plastic_strain[{i - 1}] = {float(e[i - 1])!r}; plastic strains must strictly increase")
        y.flags.writeable = False
        e.flags.writeable = False
        work = np.concatenate([[0.0], np.cumsum(0.5 * (y[1:] + y[:-1]) * np.diff(e))])
        work.flags.writeable = False
        object.__setattr__(self, "yield_stress", y)
        object.__setattr__(self, "plastic_strain", e)
        object.__setattr__(self, "_work", work)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, HardeningTable):
            return NotImplemented
        return (np.array_equal(self.yield_stress, other.yield_stress)
                and np.array_equal(self.plastic_strain, other.plastic_strain))

    def __hash__(self) -> int:
        return hash((self.yield_stress.tobytes(), self.plastic_strain.tobytes()))

    def sigma_y(self, eps_p: np.ndarray) -> np.ndarray:
        """Yield stress (MPa), same shape as ``eps_p`` (equivalent plastic strain, >= 0)."""
        return np.interp(eps_p, self.plastic_strain, self.yield_stress)

    def slope(self, eps_p: np.ndarray) -> np.ndarray:
        """Hardening modulus ``d sigma_y / d eps_p`` (MPa), same shape as ``eps_p``; 0 beyond
        the last point. At a knot the slope of the segment to its right is returned."""
        e, y = self.plastic_strain, self.yield_stress
        h = np.append(np.diff(y) / np.diff(e), 0.0)
        k = np.clip(np.searchsorted(e, eps_p, side="right") - 1, 0, len(e) - 1)
        return h[k]

    def work(self, eps_p: np.ndarray) -> np.ndarray:
        """Area under the hardening curve, ``int_0^eps_p sigma_y(s) ds`` (MPa = mJ/mm^3 per unit
        reference volume), same shape as ``eps_p``; exact for the piecewise-linear table."""
        eps_p = np.asarray(eps_p, dtype=np.float64)
        e, y = self.plastic_strain, self.yield_stress
        k = np.clip(np.searchsorted(e, eps_p, side="right") - 1, 0, len(e) - 1)
        return self._work[k] + 0.5 * (y[k] + self.sigma_y(eps_p)) * (eps_p - e[k])

    def scaled(self, factor: float) -> HardeningTable:
        """The table with every yield stress multiplied by ``factor`` (> 0)."""
        return HardeningTable(self.yield_stress * factor, self.plastic_strain)


#: seed 002's face yield table (SPEC: MPa, kPa-scale values)
FACE_TABLE = HardeningTable(
    yield_stress=[0.015, 0.020, 0.025, 0.028, 0.030, 0.031],
    plastic_strain=[0.0, 0.03, 0.032, 0.05, 0.06, 0.07],
)
#: seed 002's ball yield table (MPa)
BALL_TABLE = HardeningTable(
    yield_stress=[0.034, 0.035, 0.036, 0.037, 0.038, 0.039],
    plastic_strain=[0.0, 0.03, 0.032, 0.05, 0.06, 0.07],
)


@dataclass(frozen=True)
class PlasticState:
    """History of every integration point after a converged step.

    Attributes
    ----------
    F : (n, 3, 3) float, deformation gradient of the last update (dimensionless)
    be : (n, 3, 3) float, elastic left Cauchy-Green tensor ``Fe Fe^T`` (dimensionless)
    eps_p : (n,) float, equivalent (von Mises) plastic strain, logarithmic measure
    """

    F: np.ndarray
    be: np.ndarray
    eps_p: np.ndarray

    @classmethod
    def initial(cls, n: int) -> PlasticState:
        """The undeformed, virgin state of ``n`` points (``F = be = I``, ``eps_p = 0``)."""
        eye = np.broadcast_to(np.eye(3), (n, 3, 3))
        return cls(F=eye.copy(), be=eye.copy(), eps_p=np.zeros(n))

    @property
    def n(self) -> int:
        return self.eps_p.shape[0]


@dataclass(frozen=True)
class StressUpdate:
    """Result of :meth:`J2Plasticity.update` for ``n`` points.

    Attributes
    ----------
    cauchy : (n, 3, 3) float, Cauchy stress ``tau / J``, MPa
    kirchhoff : (n, 3, 3) float, Kirchhoff stress ``tau = J sigma``, MPa
    first_piola : (n, 3, 3) float, first Piola-Kirchhoff stress ``P = tau F^-T``, MPa
        (internal forces on the reference configuration: ``f_a = int P grad_X N_a dV``)
    state : the new :class:`PlasticState`
    dissipation : (n,) float, plastic work of this step per unit *reference* volume,
        ``int sigma_y d eps_p`` over ``[eps_p_old, eps_p_new]``, MPa = mJ/mm^3
        (all plastic work counted as dissipated; no stored cold-work energy)
    plastic : (n,) bool, points that flowed plastically in this step
    """

    cauchy: np.ndarray
    kirchhoff: np.ndarray
    first_piola: np.ndarray
    state: PlasticState
    dissipation: np.ndarray
    plastic: np.ndarray


def von_mises(stress: np.ndarray) -> np.ndarray:
    """Von Mises equivalent stress ``sqrt(3/2 s:s)`` (MPa, shape ``(...)``) of symmetric
    stresses ``(..., 3, 3)`` MPa, with ``s`` the deviator."""
    stress = np.asarray(stress, dtype=np.float64)
    tr = np.trace(stress, axis1=-2, axis2=-1)
    ss = np.einsum("...ij,...ij->...", stress, stress) - tr**2 / 3.0
    return np.sqrt(1.5 * np.maximum(ss, 0.0))


def _cofactor_det(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cofactor matrices ``det(A) A^-T`` ``(n, 3, 3)`` and determinants ``(n,)`` of ``A (n, 3, 3)``."""
    a0, a1, a2 = A[..., :, 0], A[..., :, 1], A[..., :, 2]
    cof = np.stack([np.cross(a1, a2), np.cross(a2, a0), np.cross(a0, a1)], axis=-1)
    det = np.einsum("...i,...i->...", a0, cof[..., :, 0])
    return cof, det


def _check_det(det: np.ndarray, what: str) -> None:
    bad = np.flatnonzero(~(det > 0))
    if bad.size:
        i = bad[0]
        raise FloatingPointError(f"{what}: det F = {det[i]:.4g} <= 0 at point {i} ({bad.size} inverted "
                                 "point(s)); the element is inverted, reduce the time step or refine the mesh")


@dataclass(frozen=True)
class J2Plasticity(IsotropicModuli):
    """Isotropic Hencky elasticity with J2 plasticity and tabulated isotropic hardening.

    Attributes
    ----------
    E : Young's modulus, MPa
    nu : Poisson's ratio, in (-1, 0.5)
    density : mass density, tonne/mm^3 (1000 kg/m^3 = 1e-9)
    table : hardening curve, or ``None`` for a purely (Hencky) elastic material, which skips
        the return mapping entirely and keeps ``eps_p = 0``

    The consistency condition needs ``3 mu + d sigma_y / d eps_p > 0`` on every segment
    (softening no steeper than that); this is checked at construction.
    """

    E: float
    nu: float
    density: float
    table: HardeningTable | None = None

    def __post_init__(self):
        _check("J2Plasticity", self.E, self.nu)
        if not np.isfinite(self.density) or self.density <= 0:
            raise ValueError(f"J2Plasticity: density = {self.density!r} tonne/mm^3 must be positive and "
                             "finite (1000 kg/m^3 = 1e-9 tonne/mm^3)")
        if self.table is not None:
            e, y = self.table.plastic_strain, self.table.yield_stress
            h = np.diff(y) / np.diff(e)
            if h.size and np.min(h) <= -3.0 * self.mu:
                raise ValueError(f"J2Plasticity: hardening slope {np.min(h):.4g} MPa is steeper softening "
                                 f"than -3 mu = {-3.0 * self.mu:.4g} MPa; the return mapping has no unique solution")

    def elastic_wave_speed(self) -> float:
        """Dilatational (P-) wave speed ``sqrt((lam + 2 mu) / rho)``, mm/s (stable explicit step)."""
        return float(np.sqrt((self.lam + 2.0 * self.mu) / self.density))

    def initial_state(self, n: int) -> PlasticState:
        """:meth:`PlasticState.initial` for ``n`` points."""
        return PlasticState.initial(n)

    def update(self, F_new: np.ndarray, state: PlasticState) -> StressUpdate:
        """Stresses and new history at the deformation gradients ``F_new``.

        Parameters
        ----------
        F_new : (n, 3, 3) float, deformation gradients at the end of the step (dimensionless)
        state : :class:`PlasticState` of the same ``n`` points at the start of the step

        Returns
        -------
        :class:`StressUpdate` (Cauchy, Kirchhoff, first Piola-Kirchhoff stresses in MPa, the new
        state, plastic work per unit reference volume in MPa = mJ/mm^3).

        Raises
        ------
        FloatingPointError
            if ``det F_new <= 0`` (or ``det F_old <= 0``) at some point; the message names it.
        """
        F_new = np.array(F_new, dtype=np.float64)  # a copy: the state must not alias the caller's buffer
        if F_new.ndim != 3 or F_new.shape[1:] != (3, 3) or F_new.shape[0] != state.n:
            raise ValueError(f"F_new has shape {F_new.shape}; expected ({state.n}, 3, 3) to match the state")
        cof, J = _cofactor_det(F_new)
        _check_det(J, "J2Plasticity.update")
        F_T = np.swapaxes(F_new, 1, 2)

        if self.table is None:
            be_trial = F_new @ F_T
        else:
            cof_old, J_old = _cofactor_det(state.F)
            _check_det(J_old, "J2Plasticity.update (state.F)")
            f = F_new @ (np.swapaxes(cof_old, 1, 2) / J_old[:, None, None])  # F_new F_old^-1
            be_trial = f @ state.be @ np.swapaxes(f, 1, 2)

        lam2, N = np.linalg.eigh(be_trial)  # squared elastic stretches, principal directions (columns)
        bad = np.flatnonzero(~(lam2[:, 0] > 0))
        if bad.size:
            i = bad[0]
            raise FloatingPointError(f"J2Plasticity.update: elastic left Cauchy-Green tensor not positive "
                                     f"definite at point {i} (eigenvalue {lam2[i, 0]:.4g})")
        eps = 0.5 * np.log(lam2)  # (n, 3) principal Hencky strains
        vol = eps.sum(axis=1)
        dev = eps - vol[:, None] / 3.0
        mu2 = 2.0 * self.mu

        if self.table is None:
            eps_p = state.eps_p
            dissipation = np.zeros(state.n)
            plastic = np.zeros(state.n, dtype=bool)
            be_new = be_trial
        else:
            table = self.table
            q_trial = _SQRT_3_2 * mu2 * np.sqrt(np.einsum("ni,ni->n", dev, dev))
            y_old = table.sigma_y(state.eps_p)
            plastic = q_trial > y_old * (1.0 + _YIELD_RTOL)
            # exact consistency: h(x) = sigma_y(x) + 3 mu x = q_trial + 3 mu eps_p_old
            mu3 = 3.0 * self.mu
            e_k, y_k = table.plastic_strain, table.yield_stress
            h_k = y_k + mu3 * e_k
            r = q_trial + mu3 * state.eps_p
            x = np.where(r <= h_k[-1], np.interp(r, h_k, e_k), e_k[-1] + (r - h_k[-1]) / mu3)
            d_eps_p = np.where(plastic, np.maximum(x - state.eps_p, 0.0), 0.0)
            eps_p = state.eps_p + d_eps_p
            with np.errstate(divide="ignore", invalid="ignore"):
                scale = np.where(plastic, 1.0 - mu3 * d_eps_p / q_trial, 1.0)
            dev = dev * scale[:, None]
            eps = dev + vol[:, None] / 3.0
            dissipation = np.where(plastic, table.work(eps_p) - table.work(state.eps_p), 0.0)
            # exponential map on the flowing points only; elastic points keep be_trial (no round-off drift)
            be_new = be_trial
            idx = np.flatnonzero(plastic)
            if idx.size:
                Np = N[idx]
                be_new[idx] = (Np * np.exp(2.0 * eps[idx])[:, None, :]) @ np.swapaxes(Np, 1, 2)

        tau_i = self.lam * vol[:, None] + mu2 * (dev + vol[:, None] / 3.0)  # principal Kirchhoff, MPa
        tau = (N * tau_i[:, None, :]) @ np.swapaxes(N, 1, 2)
        cauchy = tau / J[:, None, None]
        first_piola = tau @ cof / J[:, None, None]  # tau F^-T
        new_state = PlasticState(F=F_new, be=be_new, eps_p=eps_p)
        return StressUpdate(cauchy=cauchy, kirchhoff=tau, first_piola=first_piola, state=new_state,
                            dissipation=dissipation, plastic=plastic)


#: seed 002's face: E = 0.015 MPa, nu = 0.49, 1000 kg/m^3, yield table :data:`FACE_TABLE`
#: (first yield at a uniaxial Hencky strain of 1: effectively hyperelastic)
SEED002_FACE = J2Plasticity(E=0.015, nu=0.49, density=1e-9, table=FACE_TABLE)
#: seed 002's ball: E = 0.38 MPa, nu = 0.39, density of a solid 110 mm sphere of 0.43 kg,
#: yield table :data:`BALL_TABLE`
SEED002_BALL = J2Plasticity(E=0.38, nu=0.39, density=ball_density(), table=BALL_TABLE)
