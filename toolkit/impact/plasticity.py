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

Two implementations of the same update: :meth:`J2Plasticity.update_numpy` (batched numpy and
LAPACK ``eigh``, the readable reference) and the compiled per-point kernel :func:`_j2_points`
(numba; a cyclic Jacobi eigen-decomposition started from the previous step's principal
directions), which :meth:`J2Plasticity.update` runs when numba is installed: the faster of the
two. The tests hold them equal to round-off.

The impact paper's materials (:data:`PAPER_FACE`, :data:`PAPER_BALL`) read its yield tables,
printed without units, as MPa. The face's initial yield stress (0.015 MPa) equals its Young's
modulus, so in uniaxial tension it first yields at a Hencky strain ``ln(l) = sigma_y / E = 1``
(a stretch of ``e ~ 2.7``): the face is effectively hyperelastic (Hencky) at every strain an
impact reaches. The ball (E = 0.38 MPa, yield 0.034 MPa) yields at a Hencky strain of ~0.09.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from toolkit.common import papers
from toolkit.common.errors import ToolkitError
from toolkit.common.fem.jit import njit, use_jit
from toolkit.common.fem.materials import IsotropicModuli, _check, von_mises
from toolkit.common.fem.tangent import algorithmic_tangent

__all__ = [
    "HardeningTable",
    "PlasticState",
    "StressUpdate",
    "J2Plasticity",
    "InvertedPointError",
    "von_mises",
    "FACE_TABLE",
    "BALL_TABLE",
    "PAPER_FACE",
    "PAPER_BALL",
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

    @classmethod
    def from_pairs(cls, pairs) -> HardeningTable:
        """The table of ``((yield stress MPa, plastic strain), ...)`` rows, as the impact paper
        and :class:`~toolkit.impact.scene.MaterialSpec` write it."""
        arr = np.asarray(pairs, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 2:
            raise ValueError(f"HardeningTable.from_pairs: expected rows of (yield stress MPa, plastic strain), "
                             f"got an array of shape {arr.shape}")
        return cls(arr[:, 0], arr[:, 1])

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


#: the impact paper's face yield table (:data:`toolkit.common.papers.FACE_YIELD`, MPa)
FACE_TABLE = HardeningTable.from_pairs(papers.FACE_YIELD)
#: the impact paper's ball yield table (:data:`toolkit.common.papers.BALL_YIELD`, MPa)
BALL_TABLE = HardeningTable.from_pairs(papers.BALL_YIELD)


@dataclass(frozen=True)
class PlasticState:
    """History of every integration point after a converged step.

    Attributes
    ----------
    F : (n, 3, 3) float, deformation gradient of the last update (dimensionless)
    be : (n, 3, 3) float, elastic left Cauchy-Green tensor ``Fe Fe^T`` (dimensionless)
    eps_p : (n,) float, equivalent (von Mises) plastic strain, logarithmic measure
    directions : (n, 3, 3) float, principal directions of ``be`` (orthonormal columns). Not
        history in the constitutive sense: the compiled update starts its eigen-decomposition
        from them (one Jacobi sweep instead of three, since ``be`` changes little per step).
    """

    F: np.ndarray
    be: np.ndarray
    eps_p: np.ndarray
    directions: np.ndarray | None = None  # None: the identity (a cold start)

    def __post_init__(self):
        if self.directions is None:
            object.__setattr__(self, "directions", np.broadcast_to(np.eye(3), (self.n, 3, 3)).copy())

    @classmethod
    def initial(cls, n: int) -> PlasticState:
        """The undeformed, virgin state of ``n`` points (``F = be = I``, ``eps_p = 0``)."""
        eye = np.broadcast_to(np.eye(3), (n, 3, 3))
        return cls(F=eye.copy(), be=eye.copy(), eps_p=np.zeros(n), directions=eye.copy())

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
    return_mapping : (n, 5) float or None, per point the trial ``be``'s eigenvalues and the
        radial return's factors ``flow`` and ``c2`` (compiled update only), from which
        :meth:`J2Plasticity.tangent_of` makes the consistent tangent without a second update
    """

    cauchy: np.ndarray
    kirchhoff: np.ndarray
    first_piola: np.ndarray
    state: PlasticState
    dissipation: np.ndarray
    plastic: np.ndarray
    return_mapping: np.ndarray | None = None


def _cofactor_det(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cofactor matrices ``det(A) A^-T`` ``(n, 3, 3)`` and determinants ``(n,)`` of ``A (n, 3, 3)``."""
    a0, a1, a2 = A[..., :, 0], A[..., :, 1], A[..., :, 2]
    cof = np.stack([np.cross(a1, a2), np.cross(a2, a0), np.cross(a0, a1)], axis=-1)
    det = np.einsum("...i,...i->...", a0, cof[..., :, 0])
    return cof, det


def _batch_copy(F_new, state: PlasticState) -> np.ndarray:
    """``F_new`` as a new C-contiguous ``(n, 3, 3)`` float64 array (the state keeps it, so it must
    not alias the caller's buffer); raises ValueError unless ``n`` matches the state."""
    F_new = np.array(F_new, dtype=np.float64, order="C")
    if F_new.ndim != 3 or F_new.shape[1:] != (3, 3) or F_new.shape[0] != state.n:
        raise ValueError(f"F_new has shape {F_new.shape}; expected ({state.n}, 3, 3) to match the state")
    return F_new


class InvertedPointError(ToolkitError, FloatingPointError):
    """A stress update met ``det F <= 0`` (or a non-positive-definite ``be``); ``point`` is the
    first bad integration point (index into the update's ``n`` points)."""

    def __init__(self, message: str, point: int):
        super().__init__(message)
        self.point = point


def _check_det(det: np.ndarray, what: str) -> None:
    bad = np.flatnonzero(~(det > 0))
    if bad.size:
        i = bad[0]
        raise InvertedPointError(f"{what}: det F = {det[i]:.4g} <= 0 at point {i} ({bad.size} inverted "
                                 "point(s)); the element is inverted, reduce the time step or refine the mesh", int(i))


# --- compiled per-point kernel (numba); mirrors J2Plasticity.update_numpy step for step ------------


@njit
def _interp(x, xp, fp):  # pragma: no cover - compiled
    """np.interp for a scalar on a short increasing table (clamped at both ends)."""
    if x <= xp[0]:
        return fp[0]
    m = xp.shape[0]
    if x >= xp[m - 1]:
        return fp[m - 1]
    k = 0
    while xp[k + 1] < x:
        k += 1
    return fp[k] + (fp[k + 1] - fp[k]) * (x - xp[k]) / (xp[k + 1] - xp[k])


@njit
def _hardening_work(x, e, y, w):  # pragma: no cover - compiled
    """HardeningTable.work for a scalar plastic strain ``x >= 0``."""
    k = 0
    while k + 1 < e.shape[0] and e[k + 1] <= x:
        k += 1
    return w[k] + 0.5 * (y[k] + _interp(x, e, y)) * (x - e[k])


@njit
def _jacobi_eigh3(A, V):  # pragma: no cover - compiled
    """Cyclic Jacobi: diagonalises the symmetric ``A (3, 3)`` in place (eigenvalues on the
    diagonal, unordered) and writes the eigenvectors as the columns of ``V (3, 3)``."""
    for i in range(3):
        for j in range(3):
            V[i, j] = 1.0 if i == j else 0.0
    for _sweep in range(50):
        off = A[0, 1] ** 2 + A[0, 2] ** 2 + A[1, 2] ** 2
        diag = A[0, 0] ** 2 + A[1, 1] ** 2 + A[2, 2] ** 2
        if off <= 1e-34 * diag or off == 0.0:
            break
        for r in range(3):
            p = 0 if r < 2 else 1
            q = 1 if r == 0 else 2
            apq = A[p, q]
            if apq == 0.0:
                continue
            h = 0.5 * (A[q, q] - A[p, p])
            if abs(apq) < 1e-8 * abs(h):  # tiny angle (the warm-started case): no square roots,
                t = 0.5 * apq / h  # t = tan(phi) = apq / (2 h) and c = cos(phi) to O(t^4) < 1e-32
                c = 1.0 - 0.5 * t * t
            else:
                t = apq / (abs(h) + np.sqrt(h * h + apq * apq))
                if h < 0.0:
                    t = -t
                c = 1.0 / np.sqrt(t * t + 1.0)
            s = t * c
            for k in range(3):  # A <- A G
                akp, akq = A[k, p], A[k, q]
                A[k, p] = c * akp - s * akq
                A[k, q] = s * akp + c * akq
            for k in range(3):  # A <- G^T A
                apk, aqk = A[p, k], A[q, k]
                A[p, k] = c * apk - s * aqk
                A[q, k] = s * apk + c * aqk
            A[p, q] = 0.0
            A[q, p] = 0.0
            for k in range(3):  # V <- V G
                vkp, vkq = V[k, p], V[k, q]
                V[k, p] = c * vkp - s * vkq
                V[k, q] = s * vkp + c * vkq


@njit
def _cofactor3(F, C):  # pragma: no cover - compiled
    """Cofactor ``det(F) F^-T`` of ``F (3, 3)`` into ``C``; returns ``det F``."""
    C[0, 0] = F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1]
    C[0, 1] = F[1, 2] * F[2, 0] - F[1, 0] * F[2, 2]
    C[0, 2] = F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]
    C[1, 0] = F[0, 2] * F[2, 1] - F[0, 1] * F[2, 2]
    C[1, 1] = F[0, 0] * F[2, 2] - F[0, 2] * F[2, 0]
    C[1, 2] = F[0, 1] * F[2, 0] - F[0, 0] * F[2, 1]
    C[2, 0] = F[0, 1] * F[1, 2] - F[0, 2] * F[1, 1]
    C[2, 1] = F[0, 2] * F[1, 0] - F[0, 0] * F[1, 2]
    C[2, 2] = F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]
    return F[0, 0] * C[0, 0] + F[0, 1] * C[0, 1] + F[0, 2] * C[0, 2]


@njit
def _slope(x, e_k, y_k):  # pragma: no cover - compiled
    """Hardening modulus ``d sigma_y / d eps_p`` at ``x`` (:meth:`HardeningTable.slope`)."""
    m = e_k.shape[0]
    for k in range(m - 1):
        if x < e_k[k + 1]:
            return (y_k[k + 1] - y_k[k]) / (e_k[k + 1] - e_k[k])
    return 0.0


@njit
def _log_deviator(A, eps, dev):  # pragma: no cover - compiled
    """The principal logarithmic strains ``ln(x_k) / 2`` of the eigenvalues ``x_k`` on ``A``'s
    diagonal into ``eps (3,)``, their deviator into ``dev (3,)``; returns the volumetric strain
    and ``|dev|^2``."""
    vol = 0.0
    for k in range(3):
        eps[k] = 0.5 * np.log(A[k, k])
        vol += eps[k]
    ss = 0.0
    for k in range(3):
        dev[k] = eps[k] - vol / 3.0
        ss += dev[k] * dev[k]
    return vol, ss


@njit
def _j2_tangent_point(A, V, C, J, unit, lam, mu, flow, c2, P, out):  # pragma: no cover - compiled
    """Consistent tangent ``out[i, J, k, L] = dP_iJ / dF_kL`` (MPa) of one point's update.

    ``A`` holds the trial ``be``'s eigenvalues ``x_a`` on its diagonal and ``V`` its
    principal directions (columns); ``C`` is the cofactor of ``F`` (``F^-1 = C^T / J``);
    ``unit`` the trial deviatoric strain's unit direction in those axes; ``flow`` and ``c2``
    the radial return's factors (1 and 0 for an elastic point); ``P`` the stress.

    For each unit direction ``H = e_k e_L^T`` of ``dF``, in the principal axes:

    - ``d be_trial = l be + be l^T`` with ``l = H F^-1`` (also through ``f = F F_old^-1``);
    - ``d eps_ab = 1/2 g_ab d be_ab`` (Daleckii-Krein for the tensor logarithm): ``g_aa =
      1 / x_a``, ``g_ab = (ln x_a - ln x_b) / (x_a - x_b)``, its limit ``1 / x_a`` for equal
      eigenvalues (valid with any orthonormal eigenbasis, so repeated ones need no case);
    - ``d tau = K tr(d eps) I + 2 mu flow dev(d eps) + c2 N (N : d eps)`` (Simo and Hughes's
      radial-return tangent, ``K = lam + 2 mu / 3``, ``N`` = ``unit`` on the diagonal);
    - ``dP = d tau F^-T - P H^T F^-T``.
    """
    g = np.empty((3, 3))
    W = np.empty((3, 3))  # W[L, b] = (F^-1 V)[L, b]
    de = np.empty((3, 3))
    dt = np.empty((3, 3))
    R = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            xa, xb = A[a, a], A[b, b]
            r = xb / xa - 1.0
            if abs(r) < 1e-6:  # ln(1 + r) / r, its series
                g[a, b] = (1.0 - r / 2.0 + r * r / 3.0) / xa
            else:
                g[a, b] = (np.log(xa) - np.log(xb)) / (xa - xb)
            W[a, b] = (C[0, a] * V[0, b] + C[1, a] * V[1, b] + C[2, a] * V[2, b]) / J
    K = lam + 2.0 * mu / 3.0
    for k in range(3):
        for L in range(3):
            tr = 0.0
            for a in range(3):
                for b in range(3):
                    dbe = V[k, a] * W[L, b] * A[b, b] + A[a, a] * V[k, b] * W[L, a]
                    de[a, b] = 0.5 * g[a, b] * dbe
                tr += de[a, a]
            proj = unit[0] * de[0, 0] + unit[1] * de[1, 1] + unit[2] * de[2, 2]
            for a in range(3):
                for b in range(3):
                    dt[a, b] = 2.0 * mu * flow * de[a, b]
                dt[a, a] += (K - 2.0 * mu * flow / 3.0) * tr + c2 * unit[a] * proj
            for a in range(3):  # R = V dt, then d tau = R V^T (into dt)
                for b in range(3):
                    R[a, b] = V[a, 0] * dt[0, b] + V[a, 1] * dt[1, b] + V[a, 2] * dt[2, b]
            for a in range(3):
                for b in range(3):
                    dt[a, b] = R[a, 0] * V[b, 0] + R[a, 1] * V[b, 1] + R[a, 2] * V[b, 2]
            for i in range(3):  # dP = d tau F^-T - P H^T F^-T, F^-T = C / J
                for Jj in range(3):
                    out[i, Jj, k, L] = (dt[i, 0] * C[0, Jj] + dt[i, 1] * C[1, Jj] + dt[i, 2] * C[2, Jj]
                                        - P[i, L] * C[k, Jj]) / J


@njit
def _j2_points(F_new, F_old, be_old, eps_p_old, N_old, lam, mu, e_k, y_k, w_k, hardening, rtol,
               cauchy, tau, P, be_new, eps_p_new, diss, plastic, N_new, status, want_tangent,
               tangent, mapping):  # pragma: no cover - compiled
    """Hencky-J2 update of every point (see the module docstring), writing into the output
    arrays; ``status = (kind, point)`` with kind 0 ok, 1 det F <= 0, 2 det F_old <= 0,
    3 be not positive definite (the first bad point; the loop stops there). With
    ``want_tangent`` also the consistent tangent ``dP/dF`` of every point into ``tangent
    (n, 3, 3, 3, 3)`` (:func:`_j2_tangent_point`). ``mapping (n, 5)`` receives what that
    tangent needs beyond the outputs: the trial ``be``'s eigenvalues, ``flow`` and ``c2``
    (:func:`_j2_tangent_points`).

    The eigen-decomposition of the trial ``be`` starts from the previous principal directions
    ``N_old``: ``A = N_old^T be N_old`` is nearly diagonal, Jacobi finishes it (usually in
    one sweep) and the directions are ``N_old V``."""
    n = F_new.shape[0]
    C = np.empty((3, 3))
    Co = np.empty((3, 3))
    f = np.empty((3, 3))
    fB = np.empty((3, 3))
    A = np.empty((3, 3))
    V = np.empty((3, 3))
    W = np.empty((3, 3))
    eps = np.empty(3)
    dev = np.empty(3)
    unit = np.empty(3)
    mu2 = 2.0 * mu
    mu3 = 3.0 * mu
    m = e_k.shape[0]
    h_k = y_k + mu3 * e_k
    for i in range(n):
        F = F_new[i]
        J = _cofactor3(F, C)
        if not (J > 0.0):
            status[0], status[1] = 1, i
            return
        if hardening:
            Jo = _cofactor3(F_old[i], Co)
            if not (Jo > 0.0):
                status[0], status[1] = 2, i
                return
            for a in range(3):  # f = F F_old^-1 = F Co^T / Jo
                for b in range(3):
                    f[a, b] = (F[a, 0] * Co[b, 0] + F[a, 1] * Co[b, 1] + F[a, 2] * Co[b, 2]) / Jo
            B = be_old[i]
            for a in range(3):
                for b in range(3):
                    fB[a, b] = f[a, 0] * B[0, b] + f[a, 1] * B[1, b] + f[a, 2] * B[2, b]
            for a in range(3):
                for b in range(3):
                    A[a, b] = fB[a, 0] * f[b, 0] + fB[a, 1] * f[b, 1] + fB[a, 2] * f[b, 2]
        else:
            for a in range(3):
                for b in range(3):
                    A[a, b] = F[a, 0] * F[b, 0] + F[a, 1] * F[b, 1] + F[a, 2] * F[b, 2]
        No = N_old[i]
        for a in range(3):
            for b in range(3):
                be_new[i, a, b] = A[a, b]
        for a in range(3):  # W = A N_old, A <- N_old^T W
            for b in range(3):
                W[a, b] = A[a, 0] * No[0, b] + A[a, 1] * No[1, b] + A[a, 2] * No[2, b]
        for a in range(3):
            for b in range(3):
                A[a, b] = No[0, a] * W[0, b] + No[1, a] * W[1, b] + No[2, a] * W[2, b]
        for a in range(3):  # symmetrise the round-off of the transform
            for b in range(a + 1, 3):
                A[a, b] = A[b, a] = 0.5 * (A[a, b] + A[b, a])
        _jacobi_eigh3(A, W)
        for a in range(3):  # V = N_old W: principal directions of be_trial (columns)
            for b in range(3):
                V[a, b] = No[a, 0] * W[0, b] + No[a, 1] * W[1, b] + No[a, 2] * W[2, b]
                N_new[i, a, b] = V[a, b]
        if not (A[0, 0] > 0.0 and A[1, 1] > 0.0 and A[2, 2] > 0.0):
            status[0], status[1] = 3, i
            return
        vol, ss = _log_deviator(A, eps, dev)
        eps_p_new[i] = eps_p_old[i]
        diss[i] = 0.0
        q = np.sqrt(1.5) * mu2 * np.sqrt(ss)
        for k in range(3):  # unit deviatoric direction of the trial strain (principal axes)
            unit[k] = dev[k] / np.sqrt(ss) if ss > 0.0 else 0.0
        flow, c2 = 1.0, 0.0  # dev tau = 2 mu flow dev eps_trial; c2: the radial return's N (x) N term
        if hardening:
            ep = eps_p_old[i]
            if q > _interp(ep, e_k, y_k) * (1.0 + rtol):
                r = q + mu3 * ep
                if r <= h_k[m - 1]:
                    x = _interp(r, h_k, e_k)
                else:
                    x = e_k[m - 1] + (r - h_k[m - 1]) / mu3
                d = max(x - ep, 0.0)
                flow = 1.0 - mu3 * d / q
                c2 = 2.0 * mu3 * mu * (d / q - 1.0 / (mu3 + _slope(x, e_k, y_k)))
                for k in range(3):
                    dev[k] *= flow
                eps_p_new[i] = ep + d
                diss[i] = _hardening_work(ep + d, e_k, y_k, w_k) - _hardening_work(ep, e_k, y_k, w_k)
                plastic[i] = True
                for a in range(3):  # exponential map be = sum_k exp(2 eps_k) n_k n_k
                    for b in range(3):
                        s = 0.0
                        for k in range(3):
                            s += V[a, k] * np.exp(2.0 * (dev[k] + vol / 3.0)) * V[b, k]
                        be_new[i, a, b] = s
        for k in range(3):
            eps[k] = lam * vol + mu2 * (dev[k] + vol / 3.0)  # principal Kirchhoff stress, MPa
        for a in range(3):
            for b in range(3):
                s = V[a, 0] * eps[0] * V[b, 0] + V[a, 1] * eps[1] * V[b, 1] + V[a, 2] * eps[2] * V[b, 2]
                tau[i, a, b] = s
                cauchy[i, a, b] = s / J
        for a in range(3):  # P = tau F^-T = tau C / J
            for b in range(3):
                P[i, a, b] = (tau[i, a, 0] * C[0, b] + tau[i, a, 1] * C[1, b] + tau[i, a, 2] * C[2, b]) / J
        mapping[i, 0], mapping[i, 1], mapping[i, 2] = A[0, 0], A[1, 1], A[2, 2]
        mapping[i, 3], mapping[i, 4] = flow, c2
        if want_tangent:
            _j2_tangent_point(A, V, C, J, unit, lam, mu, flow, c2, P[i], tangent[i])


@njit
def _j2_tangent_points(F_new, N_new, P, mapping, lam, mu, tangent):  # pragma: no cover - compiled
    """The consistent tangent of every point of a finished update (:func:`_j2_points`' outputs
    ``N_new``, ``P`` and ``mapping``), the same arithmetic as with ``want_tangent`` there."""
    C = np.empty((3, 3))
    A = np.zeros((3, 3))
    eps = np.empty(3)
    dev = np.empty(3)
    unit = np.empty(3)
    for i in range(F_new.shape[0]):
        J = _cofactor3(F_new[i], C)
        for k in range(3):
            A[k, k] = mapping[i, k]
        _, ss = _log_deviator(A, eps, dev)
        for k in range(3):
            unit[k] = dev[k] / np.sqrt(ss) if ss > 0.0 else 0.0
        _j2_tangent_point(A, N_new[i], C, J, unit, lam, mu, mapping[i, 3], mapping[i, 4], P[i], tangent[i])


@dataclass(frozen=True)
class J2Plasticity(IsotropicModuli):
    """Isotropic Hencky elasticity with J2 plasticity and tabulated isotropic hardening.

    :meth:`update` runs a compiled per-point kernel (:func:`_j2_points`, a Jacobi
    eigen-decomposition instead of LAPACK's batched ``eigh``; much faster) when numba is
    available, and the vectorized numpy reference (:meth:`update_numpy`) otherwise; the two
    agree to round-off (tested).

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
        InvertedPointError (a FloatingPointError)
            if ``det F_new <= 0`` (or ``det F_old <= 0``, or NaN) at some point; the message and
            ``.point`` name the first one.
        """
        F_new = _batch_copy(F_new, state)
        if use_jit():
            return self._update_compiled(F_new, state)
        return self._update_numpy(F_new, state)

    def _table_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self.table is None:  # unused by the kernel; read-only like a table's (one compiled signature)
            z = np.zeros(1)
            z.flags.writeable = False
            return z, z, z
        return self.table.plastic_strain, self.table.yield_stress, self.table._work

    def _update_compiled(self, F_new: np.ndarray, state: PlasticState,
                         tangent: np.ndarray | None = None) -> StressUpdate:
        n = state.n
        cauchy, tau, P, be_new, N = (np.empty((n, 3, 3)) for _ in range(5))
        eps_p, diss = np.empty(n), np.empty(n)
        plastic = np.zeros(n, dtype=np.bool_)
        status = np.zeros(2, dtype=np.int64)
        e_k, y_k, w_k = self._table_arrays()
        want = tangent is not None
        mapping = np.empty((n, 5))
        _j2_points(F_new, np.ascontiguousarray(state.F), np.ascontiguousarray(state.be),
                   np.ascontiguousarray(state.eps_p, dtype=np.float64), np.ascontiguousarray(state.directions),
                   float(self.lam), float(self.mu), e_k, y_k, w_k, self.table is not None, _YIELD_RTOL,
                   cauchy, tau, P, be_new, eps_p, diss, plastic, N, status, want,
                   tangent if want else np.empty((0, 3, 3, 3, 3)), mapping)
        kind, i = int(status[0]), int(status[1])
        if kind == 1:
            raise InvertedPointError(f"J2Plasticity.update: det F = {np.linalg.det(F_new[i]):.4g} <= 0 at point "
                                     f"{i}; the element is inverted, reduce the time step or refine the mesh", i)
        if kind == 2:
            raise InvertedPointError(f"J2Plasticity.update (state.F): det F = {np.linalg.det(state.F[i]):.4g} "
                                     f"<= 0 at point {i}", i)
        if kind == 3:
            raise InvertedPointError(f"J2Plasticity.update: elastic left Cauchy-Green tensor not positive "
                                     f"definite at point {i}", i)
        return StressUpdate(cauchy=cauchy, kirchhoff=tau, first_piola=P,
                            state=PlasticState(F=F_new, be=be_new, eps_p=eps_p, directions=N),
                            dissipation=diss, plastic=plastic, return_mapping=mapping)

    def tangent(self, F_new: np.ndarray, state: PlasticState) -> tuple[StressUpdate, np.ndarray]:
        """The update and its consistent tangent ``dP/dF (n, 3, 3, 3, 3)`` MPa, return mapping
        included: in closed form from the compiled kernel (:func:`_j2_tangent_point`, the
        same pass as the update), or by differentiating the numpy update
        (:func:`~toolkit.common.fem.tangent.algorithmic_tangent`: nine more updates) without
        numba. ``A[p, i, J, k, L] = dP_iJ / dF_kL`` at point ``p``."""
        F_new = _batch_copy(F_new, state)
        if not use_jit():
            return algorithmic_tangent(self, F_new, state)
        A = np.empty((state.n, 3, 3, 3, 3))
        return self._update_compiled(F_new, state, A), A

    def tangent_of(self, update: StressUpdate) -> np.ndarray:
        """The consistent tangent ``dP/dF (n, 3, 3, 3, 3)`` MPa at the points of ``update``
        (returned by :meth:`update`), without doing the update again: equal bit for bit to
        :meth:`tangent`'s at the same ``F`` and state. A Newton iteration has just updated the
        material to judge its residual: this saves the update that :meth:`tangent` would do
        again. Needs the compiled update's ``return_mapping`` (else
        ValueError: call :meth:`tangent`)."""
        if update.return_mapping is None:
            raise ValueError("this update holds no return_mapping (numpy update); call J2Plasticity.tangent(F, state)")
        F = np.ascontiguousarray(update.state.F)
        A = np.empty((F.shape[0], 3, 3, 3, 3))
        _j2_tangent_points(F, np.ascontiguousarray(update.state.directions), np.ascontiguousarray(update.first_piola),
                           update.return_mapping, float(self.lam), float(self.mu), A)
        return A

    def update_numpy(self, F_new: np.ndarray, state: PlasticState) -> StressUpdate:
        """:meth:`update` in vectorized numpy (LAPACK ``eigh``): the reference implementation."""
        return self._update_numpy(_batch_copy(F_new, state), state)

    def _update_numpy(self, F_new: np.ndarray, state: PlasticState) -> StressUpdate:
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
            raise InvertedPointError(f"J2Plasticity.update: elastic left Cauchy-Green tensor not positive "
                                     f"definite at point {i} (eigenvalue {lam2[i, 0]:.4g})", int(i))
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
        new_state = PlasticState(F=F_new, be=be_new, eps_p=eps_p, directions=N)
        return StressUpdate(cauchy=cauchy, kirchhoff=tau, first_piola=first_piola, state=new_state,
                            dissipation=dissipation, plastic=plastic)


#: the impact paper's face: E = 0.015 MPa, nu = 0.49, 1000 kg/m^3, yield table :data:`FACE_TABLE`
#: (first yield at a uniaxial Hencky strain of 1: effectively hyperelastic)
PAPER_FACE = J2Plasticity(E=papers.FACE_E, nu=papers.FACE_NU, density=papers.FACE_DENSITY, table=FACE_TABLE)
#: the impact paper's ball: E = 0.38 MPa, nu = 0.39, density of a solid 110 mm sphere of 0.43 kg,
#: yield table :data:`BALL_TABLE`
PAPER_BALL = J2Plasticity(E=papers.BALL_E, nu=papers.BALL_NU, density=papers.ball_density(), table=BALL_TABLE)
