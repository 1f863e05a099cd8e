"""Elastic material laws (units: MPa), each a small class from kinematics to stress and tangent.

- :class:`LinearElastic`: isotropic Hooke law (the lip-sliding paper: E = 0.003 MPa, nu = 0.47).
- :class:`TransverselyIsotropic`: linear, stiffer along a fibre (the lip-sliding paper's lip muscle:
  E along superior-inferior 0.009 MPa, transverse 0.003 MPa, nu 0.47).
- :class:`NeoHookean`: compressible Neo-Hookean (FEBio's ``neo-Hookean``),
  ``W = mu/2 (I1 - 3) - mu ln J + lam/2 (ln J)^2``.

Every law here and :class:`~toolkit.impact.plasticity.J2Plasticity` satisfy one contract,
:class:`Material`: ``update(F (m, 3, 3), state) -> result`` with ``result.first_piola
(m, 3, 3)`` MPa and ``result.state`` (the state to carry to the next step), and
``tangent(F, state) -> (result, dP/dF (m, 3, 3, 3, 3) MPa)``. The elastic laws have no history:
their state is ``None``, except the transversely isotropic one, whose state is the unit fibre
``(m, 3)`` of each point (carried unchanged). The linear laws are geometrically linear:
``P = C : sym(F - I)``; they also satisfy :class:`LinearMaterial`, the contract of the static
path's Voigt assembly (:class:`~toolkit.static.stiffness.MaterialAssignment`).

Voigt order is ``[xx, yy, zz, yz, xz, xy]`` with engineering shear strains. Each law
also exposes its *volumetric* Lame part ``lam`` so element formulations can integrate
it with reduced quadrature (selective reduced integration against volumetric locking).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from toolkit.common.papers import LIP_MUSCLE_E_FIBRE, LIP_MUSCLE_E_TRANSVERSE, TISSUE_E, TISSUE_NU

__all__ = ["Material", "LinearMaterial", "StressResult", "LinearElastic", "TransverselyIsotropic", "NeoHookean",
           "IsotropicModuli", "lame", "VOIGT", "MaterialWarning", "von_mises", "isotropic_tangent", "ElasticUpdate"]

#: Voigt index pairs
VOIGT = np.array([[0, 0], [1, 1], [2, 2], [1, 2], [0, 2], [0, 1]])

#: plausible Young's moduli of soft tissue and rubber, MPa
_SOFT_RANGE_MPA = (1e-5, 100.0)


class MaterialWarning(UserWarning):
    """A material parameter looks like it is in the wrong unit."""


@runtime_checkable
class StressResult(Protocol):
    """What a :class:`Material` update returns (:class:`ElasticUpdate`,
    :class:`~toolkit.impact.plasticity.StressUpdate`).

    Attributes
    ----------
    first_piola : (m, 3, 3) float, first Piola-Kirchhoff stress ``P``, MPa (``P_iJ``: force
        component ``i`` per unit reference area normal to ``J``)
    state : the state after the update, to pass to the next step's update once the step is
        accepted (``None`` for a law without history)
    """

    first_piola: np.ndarray
    state: object


@runtime_checkable
class Material(Protocol):
    """The contract of a material law, as the explicit and quasi-static impact solvers, the
    finite-difference tangent (:func:`~toolkit.common.fem.tangent.algorithmic_tangent`) and
    the tests call it. :class:`LinearElastic`, :class:`TransverselyIsotropic`,
    :class:`NeoHookean` and :class:`~toolkit.impact.plasticity.J2Plasticity` satisfy it. (The
    static Neo-Hookean path calls :meth:`NeoHookean.first_piola` with its shear/volumetric split
    and :meth:`NeoHookean.energy` directly, for selective reduced integration and line searches.)

    ``F`` is the deformation gradient at ``m`` points, ``(m, 3, 3)`` float, dimensionless.
    ``state`` is the material state at the start of the step (the last accepted one); an
    update never changes it in place, so a rejected Newton iterate or load step costs nothing
    to undo.
    """

    def initial_state(self, points, /) -> object:
        """The state of fresh (undeformed, virgin) points: for ``points = m`` (int) points,
        except :class:`TransverselyIsotropic`, which takes their unit fibres ``(m, 3)``."""
        ...

    def update(self, F: np.ndarray, state, /) -> StressResult:
        """Stresses at ``F (m, 3, 3)``: ``result.first_piola (m, 3, 3)`` MPa and the new state."""
        ...

    def tangent(self, F: np.ndarray, state, /) -> tuple[StressResult, np.ndarray]:
        """The update at ``F (m, 3, 3)`` and the tangent ``dP/dF (m, 3, 3, 3, 3)`` MPa,
        ``A[p, i, J, k, L] = dP_iJ / dF_kL`` at point ``p`` (consistent with the update,
        return mapping included)."""
        ...


@runtime_checkable
class LinearMaterial(Protocol):
    """The contract of a small-strain linear law on the static path, whose Voigt stiffness
    :class:`~toolkit.static.stiffness.MaterialAssignment` assembles once per mesh.
    :class:`LinearElastic` and :class:`TransverselyIsotropic` satisfy it (and :class:`Material`).

    Attributes
    ----------
    linear : bool, true: the stiffness does not depend on the deformation
    needs_fibre : bool, true: :meth:`stiffness` takes the cell field ``fibre_direction``
    """

    linear: bool
    needs_fibre: bool

    def stiffness(self, fibre: np.ndarray | None = None, /) -> np.ndarray:
        """Voigt stiffness MPa, order ``[xx, yy, zz, yz, xz, xy]`` with engineering shear
        strains: ``(6, 6)`` without fibres, ``(n, 6, 6)`` for unit fibres ``(n, 3)``."""
        ...

    def volumetric_lambda(self) -> float:
        """MPa, the ``lam (tr eps)^2 / 2`` part of the energy that mean-dilatation (selective
        reduced) integration takes out of the stiffness."""
        ...


def det_and_inverse_transpose(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``det F`` ``(...)`` and ``F^-T`` ``(..., 3, 3)`` of ``F (..., 3, 3)`` in closed form (the
    cofactors over the determinant, faster than ``np.linalg`` on many small
    matrices); ``F^-T`` is not finite where ``det F = 0``."""
    r0, r1, r2 = F[..., 0, :], F[..., 1, :], F[..., 2, :]
    cof = np.stack([np.cross(r1, r2), np.cross(r2, r0), np.cross(r0, r1)], axis=-2)  # rows of det * F^-T
    det = np.einsum("...i,...i->...", r0, cof[..., 0, :])
    with np.errstate(divide="ignore", invalid="ignore"):
        return det, cof / det[..., None, None]


def lame(E: float, nu: float) -> tuple[float, float]:
    """Lame parameters ``(lam, mu)`` in MPa from Young's modulus (MPa) and Poisson's ratio."""
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


def isotropic_tangent(lam, mu) -> np.ndarray:
    """Isotropic elasticity tensor ``C_ijkl = lam d_ij d_kl + mu (d_ik d_jl + d_il d_jk)``, MPa.

    ``lam``, ``mu`` MPa, scalars or arrays of one shape ``S``; returns ``S + (3, 3, 3, 3)``.
    It is also the small-strain ``dP/dF`` (``P = C : sym(F - I)``).
    """
    eye = np.eye(3)
    volumetric = np.einsum("ij,kl->ijkl", eye, eye)
    shear = np.einsum("ik,jl->ijkl", eye, eye) + np.einsum("il,jk->ijkl", eye, eye)
    lam, mu = np.asarray(lam, dtype=float), np.asarray(mu, dtype=float)
    return lam[..., None, None, None, None] * volumetric + mu[..., None, None, None, None] * shear


def von_mises(stress: np.ndarray) -> np.ndarray:
    """Von Mises equivalent stress ``sqrt(3/2 s:s)`` (MPa, shape ``(...)``) of symmetric
    stresses ``(..., 3, 3)`` MPa, with ``s`` the deviator."""
    stress = np.asarray(stress, dtype=np.float64)
    tr = np.trace(stress, axis1=-2, axis2=-1)
    ss = np.einsum("...ij,...ij->...", stress, stress) - tr**2 / 3.0
    return np.sqrt(1.5 * np.maximum(ss, 0.0))


@dataclass(frozen=True, eq=False)
class ElasticUpdate:
    """Result of an elastic law's ``update``: ``first_piola (m, 3, 3)`` MPa and the (unchanged) state."""

    first_piola: np.ndarray
    state: object = None


def _voigt_to_tensor(D: np.ndarray) -> np.ndarray:
    """Minor- and major-symmetric tensors ``(..., 3, 3, 3, 3)`` from Voigt stiffnesses ``(..., 6, 6)``
    (engineering shear strains)."""
    index = np.empty((3, 3), dtype=np.int64)
    index[VOIGT[:, 0], VOIGT[:, 1]] = np.arange(6)
    index[VOIGT[:, 1], VOIGT[:, 0]] = np.arange(6)
    return D[..., index[:, :, None, None], index[None, None, :, :]]


def _small_strain_update(C: np.ndarray, F: np.ndarray, state) -> ElasticUpdate:
    """``P = C : sym(F - I)`` for tensors ``C (m, 3, 3, 3, 3)`` or ``(3, 3, 3, 3)`` MPa."""
    H = np.asarray(F, dtype=float) - np.eye(3)
    eps = 0.5 * (H + np.swapaxes(H, -1, -2))
    return ElasticUpdate(np.einsum("...ijkl,...kl->...ij", C, eps), state)


def _check(name: str, E: float, nu: float) -> None:
    if not np.isfinite(E) or E <= 0:
        raise ValueError(f"{name}: Young's modulus E = {E!r} MPa must be positive and finite")
    if not np.isfinite(nu) or not -1.0 < nu < 0.5:
        raise ValueError(f"{name}: Poisson's ratio nu = {nu!r} must lie in (-1, 0.5)")
    lo, hi = _SOFT_RANGE_MPA
    if not lo <= E <= hi:
        hint = "Pa (divide by 1e6)" if E > hi else "GPa or kPa confusion"
        warnings.warn(f"{name}: E = {E:g} MPa is outside the soft-tissue range [{lo:g}, {hi:g}] MPa; "
                      f"is it in {hint}? 3000 Pa = 0.003 MPa", MaterialWarning, stacklevel=3)


def _iso_voigt(lam: float, mu: float) -> np.ndarray:
    D = np.zeros((6, 6))
    D[:3, :3] = lam
    D[np.arange(3), np.arange(3)] += 2 * mu
    D[np.arange(3, 6), np.arange(3, 6)] = mu
    return D


class IsotropicModuli:
    """Mixin for materials with fields ``E`` (MPa) and ``nu``: the Lame parameters, MPa."""

    @property
    def lam(self) -> float:
        return lame(self.E, self.nu)[0]

    @property
    def mu(self) -> float:
        return lame(self.E, self.nu)[1]


@dataclass(frozen=True)
class LinearElastic(IsotropicModuli):
    """Isotropic linear elasticity. ``E`` in MPa, ``nu`` dimensionless."""

    E: float = TISSUE_E
    nu: float = TISSUE_NU
    #: small-strain linear: the static path assembles its Voigt stiffness once
    linear = True
    #: the stiffness does not depend on a fibre direction
    needs_fibre = False

    def __post_init__(self):
        _check("LinearElastic", self.E, self.nu)

    def stiffness(self, fibre: np.ndarray | None = None) -> np.ndarray:
        """Voigt stiffness ``(6, 6)`` MPa, or ``(n, 6, 6)`` if fibres ``(n, 3)`` are given."""
        D = _iso_voigt(self.lam, self.mu)
        return D if fibre is None else np.broadcast_to(D, (len(fibre), 6, 6)).copy()

    def volumetric_lambda(self) -> float:
        """The ``lam (tr eps)^2 / 2`` part of the energy, MPa (reduced-integrated)."""
        return self.lam

    def initial_state(self, n: int) -> None:
        """No history."""
        return None

    def update(self, F: np.ndarray, state=None) -> ElasticUpdate:
        """``P = C : sym(F - I)`` ``(m, 3, 3)`` MPa for ``F (m, 3, 3)``."""
        return _small_strain_update(isotropic_tangent(self.lam, self.mu), F, state)

    def tangent(self, F: np.ndarray, state=None) -> tuple[ElasticUpdate, np.ndarray]:
        """The update and ``dP/dF = C`` ``(m, 3, 3, 3, 3)`` MPa."""
        C = isotropic_tangent(self.lam, self.mu)
        return _small_strain_update(C, F, state), np.broadcast_to(C, np.shape(F)[:-2] + (3, 3, 3, 3))


def _bond_matrix(R: np.ndarray) -> np.ndarray:
    """Voigt (stress) transformation matrices ``(n, 6, 6)`` for rotations ``R (n, 3, 3)``."""
    i, j = VOIGT[:, 0], VOIGT[:, 1]
    # M[I, J] = R[i_I, k_J] R[j_I, l_J] (+ symmetric part for shear columns)
    a = R[:, i[:, None], i[None, :]] * R[:, j[:, None], j[None, :]]
    b = R[:, i[:, None], j[None, :]] * R[:, j[:, None], i[None, :]]
    M = a.copy()
    M[:, :, 3:] = a[:, :, 3:] + b[:, :, 3:]
    return M


@dataclass(frozen=True)
class TransverselyIsotropic:
    """Linear transversely isotropic elasticity with the fibre as the symmetry axis.

    Attributes (MPa unless dimensionless)
    -------------------------------------
    E_fibre : Young's modulus along the fibre (the lip-sliding paper: 0.009)
    E_transverse : Young's modulus across it (0.003)
    nu : Poisson's ratio for both planes (0.47)
    G_fibre : shear modulus in planes containing the fibre; default the transverse
        ``E_transverse / (2 (1 + nu))``
    """

    E_fibre: float = LIP_MUSCLE_E_FIBRE
    E_transverse: float = LIP_MUSCLE_E_TRANSVERSE
    nu: float = TISSUE_NU
    G_fibre: float | None = None
    #: small-strain linear: the static path assembles its Voigt stiffness once
    linear = True
    #: the stiffness depends on the cell field ``fibre_direction``
    needs_fibre = True

    def __post_init__(self):
        _check("TransverselyIsotropic", self.E_fibre, self.nu)
        _check("TransverselyIsotropic", self.E_transverse, self.nu)
        if np.linalg.eigvalsh(self._local_stiffness()).min() <= 0:
            raise ValueError(f"{self} is not positive definite; lower nu or the fibre/transverse ratio")

    @property
    def g_fibre(self) -> float:
        return self.G_fibre if self.G_fibre is not None else self.E_transverse / (2 * (1 + self.nu))

    def _local_stiffness(self) -> np.ndarray:
        """Stiffness in the frame (fibre, t1, t2)."""
        EL, ET, nu = self.E_fibre, self.E_transverse, self.nu
        S = np.zeros((6, 6))
        S[0, 0] = 1 / EL
        S[1, 1] = S[2, 2] = 1 / ET
        S[0, 1] = S[1, 0] = S[0, 2] = S[2, 0] = -nu / EL
        S[1, 2] = S[2, 1] = -nu / ET
        S[3, 3] = 2 * (1 + nu) / ET
        S[4, 4] = S[5, 5] = 1 / self.g_fibre
        return np.linalg.inv(S)

    def stiffness(self, fibre: np.ndarray) -> np.ndarray:
        """Voigt stiffness ``(n, 6, 6)`` MPa in global axes for unit fibres ``(n, 3)``."""
        a = np.asarray(fibre, dtype=float).reshape(-1, 3)
        a = a / np.linalg.norm(a, axis=1, keepdims=True)
        helper = np.where(np.abs(a[:, [0]]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
        t1 = np.cross(a, helper)
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        t2 = np.cross(a, t1)
        R = np.stack([a, t1, t2], axis=2)  # columns: local axes in global coordinates
        M = _bond_matrix(R)
        return M @ self._local_stiffness() @ np.transpose(M, (0, 2, 1))

    def initial_state(self, fibre: np.ndarray) -> np.ndarray:
        """The state of points with fibres ``(m, 3)``: the unit fibres (carried unchanged)."""
        a = np.asarray(fibre, dtype=float).reshape(-1, 3)
        return a / np.linalg.norm(a, axis=1, keepdims=True)

    def update(self, F: np.ndarray, state: np.ndarray) -> ElasticUpdate:
        """``P = C(fibre) : sym(F - I)`` ``(m, 3, 3)`` MPa; ``state``: the fibres ``(m, 3)``."""
        return _small_strain_update(_voigt_to_tensor(self.stiffness(state)), F, state)

    def tangent(self, F: np.ndarray, state: np.ndarray) -> tuple[ElasticUpdate, np.ndarray]:
        """The update and ``dP/dF = C(fibre)`` ``(m, 3, 3, 3, 3)`` MPa."""
        C = _voigt_to_tensor(self.stiffness(state))
        return _small_strain_update(C, F, state), C

    def volumetric_lambda(self) -> float:
        """The part ``lam (tr eps)^2 / 2`` split off for mean-dilatation integration, MPa.

        The remainder ``D - lam m m^T`` must stay positive semi-definite, or modes with zero
        mean dilatation would have negative energy. For an isotropic solid the split is
        the Lame ``lam = K - 2 G / 3``; here ``K`` is the Reuss bulk modulus
        ``1 / (m^T S m)`` and ``G`` the smallest shear modulus, capped by the transverse
        Lame lambda.
        """
        m = np.array([1.0, 1, 1, 0, 0, 0])
        C = self._local_stiffness()
        bulk = 1.0 / (m @ np.linalg.solve(C, m))
        g_min = min(self.g_fibre, self.E_transverse / (2 * (1 + self.nu)))
        lam = min(lame(self.E_transverse, self.nu)[0], bulk - 2.0 * g_min / 3.0)
        if np.linalg.eigvalsh(C - lam * np.outer(m, m)).min() < -1e-12 * np.abs(C).max():
            raise ValueError(f"{self}: no positive volumetric split (check nu and the moduli)")
        return lam


@dataclass(frozen=True)
class NeoHookean(IsotropicModuli):
    """Compressible Neo-Hookean solid, ``W = mu/2 (I1 - 3) - mu ln J + lam/2 (ln J)^2``.

    ``E`` in MPa, ``nu`` dimensionless (``mu``, ``lam`` from :func:`lame`). Its small-strain
    limit is :class:`LinearElastic` with the same ``E``, ``nu``.
    """

    E: float = TISSUE_E
    nu: float = TISSUE_NU
    #: finite strain: the static path solves it by Newton (``neo_hookean_system``)
    linear = False

    def __post_init__(self):
        _check("NeoHookean", self.E, self.nu)

    def volumetric_lambda(self) -> float:
        return self.lam

    def energy(self, F: np.ndarray) -> np.ndarray:
        """Strain energy density ``(...)`` MPa (= mJ/mm^3) for ``F (..., 3, 3)``; ``inf``
        where ``det F <= 0`` (the energy barrier of an inverted material)."""
        J = np.linalg.det(F)
        I1 = np.einsum("...ij,...ij->...", F, F)
        with np.errstate(invalid="ignore", divide="ignore"):
            lnJ = np.log(np.where(J > 0, J, np.nan))
            W = 0.5 * self.mu * (I1 - 3) - self.mu * lnJ + 0.5 * self.lam * lnJ**2
        return np.where(J > 0, W, np.inf)

    def first_piola(self, F: np.ndarray, part: str = "all") -> tuple[np.ndarray, np.ndarray]:
        """First Piola-Kirchhoff stress ``P (..., 3, 3)`` MPa and tangent ``dP/dF (..., 3, 3, 3, 3)``.

        ``part``: ``"all"``, ``"shear"`` (the mu terms) or ``"volumetric"`` (the lam term),
        for selective reduced integration.
        """
        J, Finv_T = det_and_inverse_transpose(F)
        if np.any(J <= 0):
            raise FloatingPointError(f"deformation gradient with det F = {J.min():.3g} <= 0 (inverted material)")
        lnJ = np.log(J)[..., None, None]
        eye = np.eye(3)
        P = np.zeros_like(F)
        A = np.zeros(F.shape + (3, 3))
        # d(F^-T)_ij / dF_kl = -F^-T_il F^-T_kj
        dFinvT = -np.einsum("...il,...kj->...ijkl", Finv_T, Finv_T)
        if part in ("all", "shear"):
            P = P + self.mu * (F - Finv_T)
            A = A + self.mu * (np.einsum("ik,jl->ijkl", eye, eye) - dFinvT)
        if part in ("all", "volumetric"):
            P = P + self.lam * lnJ * Finv_T
            A = A + self.lam * (np.einsum("...ij,...kl->...ijkl", Finv_T, Finv_T) + lnJ[..., None, None] * dFinvT)
        if part not in ("all", "shear", "volumetric"):
            raise ValueError(f"part must be 'all', 'shear' or 'volumetric', got {part!r}")
        return P, A

    def cauchy(self, F: np.ndarray) -> np.ndarray:
        """Cauchy stress ``(..., 3, 3)`` MPa."""
        P, _ = self.first_piola(F)
        J = np.linalg.det(F)[..., None, None]
        return P @ np.swapaxes(F, -1, -2) / J

    def initial_state(self, n: int) -> None:
        """No history."""
        return None

    def update(self, F: np.ndarray, state=None) -> ElasticUpdate:
        """First Piola-Kirchhoff stress ``(m, 3, 3)`` MPa at ``F (m, 3, 3)``."""
        return self.tangent(F, state)[0]

    def tangent(self, F: np.ndarray, state=None) -> tuple[ElasticUpdate, np.ndarray]:
        """The update and ``dP/dF`` ``(m, 3, 3, 3, 3)`` MPa (:meth:`first_piola`)."""
        P, A = self.first_piola(np.asarray(F, dtype=float))
        return ElasticUpdate(P, state), A
