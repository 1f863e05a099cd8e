"""Material laws against closed forms: engineering constants from the Voigt compliance,
the transversely isotropic rotation, the mean-dilatation split, and Neo-Hookean stress
and tangent against finite differences of the energy."""

import numpy as np
import pytest

from toolkit.common.fem.materials import (
    VOIGT,
    LinearElastic,
    MaterialWarning,
    NeoHookean,
    TransverselyIsotropic,
    lame,
)

RNG = np.random.default_rng(12)
M = np.array([1.0, 1, 1, 0, 0, 0])  # Voigt trace vector


def _voigt_stress(t: np.ndarray) -> np.ndarray:
    """Symmetric 3x3 stress -> Voigt [xx, yy, zz, yz, xz, xy] (no factor on shear)."""
    return t[VOIGT[:, 0], VOIGT[:, 1]]


def _tensor_strain(e: np.ndarray) -> np.ndarray:
    """Voigt strain with engineering shears -> symmetric 3x3 tensor."""
    t = np.diag(e[:3])
    for k, (i, j) in enumerate(VOIGT[3:], start=3):
        t[i, j] = t[j, i] = 0.5 * e[k]
    return t


def _uniaxial(D: np.ndarray, direction: np.ndarray) -> tuple[float, np.ndarray]:
    """Young's modulus along ``direction`` and the strain tensor of a unit uniaxial stress."""
    a = direction / np.linalg.norm(direction)
    eps = _tensor_strain(np.linalg.solve(D, _voigt_stress(np.outer(a, a))))
    return 1.0 / (a @ eps @ a), eps


def _random_unit(n=1):
    v = RNG.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _orthogonal(a):
    t = np.cross(a, _random_unit()[0])
    return t / np.linalg.norm(t)


# ------------------------------------------------------------------ linear isotropic
@pytest.mark.parametrize("E, nu", [(0.003, 0.47), (1.0, 0.3), (0.01, 0.0), (0.5, -0.2)])
def test_linear_elastic_uniaxial_stress_gives_E_and_nu(E, nu):
    """Hooke's law: a uniaxial stress sigma along any direction strains it by sigma / E
    and contracts every perpendicular direction by nu sigma / E. Exact algebra, so the
    tolerance is round-off (rel 1e-12)."""
    D = LinearElastic(E, nu).stiffness()
    a = _random_unit()[0]
    E_dir, eps = _uniaxial(D, a)
    t = _orthogonal(a)
    assert E_dir == pytest.approx(E, rel=1e-12)
    assert -(t @ eps @ t) * E_dir == pytest.approx(nu, rel=1e-12, abs=1e-14)
    lam, mu = lame(E, nu)
    assert LinearElastic(E, nu).volumetric_lambda() == pytest.approx(lam, rel=1e-14)
    assert D[3, 3] == pytest.approx(mu, rel=1e-14)  # shear modulus G = E / (2 (1 + nu))


# ------------------------------------------------------------ transversely isotropic
def test_transversely_isotropic_engineering_constants_along_random_fibre():
    """Rotated to a random fibre, the Voigt stiffness still has E_fibre along the fibre,
    E_transverse across it (any perpendicular direction: isotropic plane), the major
    Poisson ratio nu_LT = nu (load along the fibre) and the minor one
    nu_TL = nu E_T / E_L (load across, strain along; Maxwell-Betti symmetry of the
    compliance). Exact algebra: rel 1e-10."""
    mat = TransverselyIsotropic(E_fibre=0.009, E_transverse=0.003, nu=0.47)
    a = _random_unit()[0]
    D = mat.stiffness(a[None])[0]
    t1 = _orthogonal(a)
    t2 = np.cross(a, t1)
    E_L, eps_L = _uniaxial(D, a)
    assert E_L == pytest.approx(0.009, rel=1e-10)
    assert -(t1 @ eps_L @ t1) * E_L == pytest.approx(0.47, rel=1e-10)  # nu_LT
    for t in (t1, t2, (t1 + t2) / np.sqrt(2)):
        E_T, eps_T = _uniaxial(D, t)
        assert E_T == pytest.approx(0.003, rel=1e-10)
        assert -(a @ eps_T @ a) * E_T == pytest.approx(0.47 * 0.003 / 0.009, rel=1e-10)  # nu_TL


def test_transversely_isotropic_fibre_along_x_is_the_local_matrix():
    """With the fibre along x the global frame is the material frame up to a rotation
    about the fibre, which a transversely isotropic law does not see: the global matrix
    equals the local one (round-off, 1e-12 relative to its largest entry)."""
    mat = TransverselyIsotropic()
    D = mat.stiffness(np.array([[1.0, 0, 0]]))[0]
    local = mat._local_stiffness()
    np.testing.assert_allclose(D, local, rtol=0, atol=1e-12 * np.abs(local).max())
    # and a fibre along -x (same axis) gives the same matrix
    np.testing.assert_allclose(mat.stiffness(np.array([[-2.0, 0, 0]]))[0], local, rtol=0,
                               atol=1e-12 * np.abs(local).max())


@pytest.mark.parametrize("mat", [TransverselyIsotropic(), TransverselyIsotropic(0.03, 0.003, 0.45, 0.002),
                                 LinearElastic(0.003, 0.47), LinearElastic(0.003, 0.4999)],
                         ids=["TI-lip-muscle", "TI-10x", "iso-0.47", "iso-0.4999"])
def test_stiffness_spd_and_mean_dilatation_split_psd(mat):
    """An elastic stiffness is symmetric positive definite (positive strain energy), and
    the deviatoric remainder D - lam m m^T left after splitting off the volumetric part
    lam (tr eps)^2 / 2 (integrated with the mean dilatation) must be positive
    semi-definite, or strain modes with zero mean dilatation would carry negative
    energy. Tolerances: symmetry 1e-12 relative; eigenvalues >= -1e-12 |D|max."""
    fibres = _random_unit(5)
    D = mat.stiffness(fibres)
    scale = np.abs(D).max()
    np.testing.assert_allclose(D, np.transpose(D, (0, 2, 1)), rtol=0, atol=1e-12 * scale)
    assert np.linalg.eigvalsh(D).min() > 0
    lam = mat.volumetric_lambda()
    assert lam > 0
    rest = D - lam * np.outer(M, M)
    assert np.linalg.eigvalsh(rest).min() >= -1e-12 * scale


# ----------------------------------------------------------------------- Neo-Hookean
def _random_F(scale=0.3):
    while True:
        F = np.eye(3) + scale * RNG.uniform(-1, 1, size=(3, 3))
        if np.linalg.det(F) > 0.3:
            return F


def test_closed_form_determinant_and_inverse_transpose_match_numpy():
    """The cofactor formula gives numpy's det F and F^-T on random matrices (relative 1e-12 of
    the largest entry), and a non-finite F^-T, not an exception, for a singular F."""
    from toolkit.common.fem.materials import det_and_inverse_transpose

    F = np.eye(3) + 0.4 * np.random.default_rng(3).normal(size=(500, 3, 3))
    det, inv_t = det_and_inverse_transpose(F)
    np.testing.assert_allclose(det, np.linalg.det(F), rtol=1e-12, atol=1e-14)
    ref = np.swapaxes(np.linalg.inv(F), -1, -2)
    np.testing.assert_allclose(inv_t, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    det, inv_t = det_and_inverse_transpose(np.ones((2, 3, 3)))
    assert np.all(det == 0) and not np.isfinite(inv_t).all()


def test_neo_hookean_stress_is_energy_derivative():
    """P = dW/dF (hyperelasticity). Central differences of W with h = 1e-6 have a
    truncation error ~h^2 |W'''| ~ 1e-12 and round-off ~1e-16 |W| / h ~ 1e-12 relative:
    rel 1e-6 leaves a wide margin."""
    mat = NeoHookean(E=0.003, nu=0.47)
    for _ in range(3):
        F = _random_F()
        P, _ = mat.first_piola(F)
        h = 1e-6
        fd = np.zeros((3, 3))
        for k in range(3):
            for l in range(3):
                dF = np.zeros((3, 3))
                dF[k, l] = h
                fd[k, l] = (mat.energy(F + dF) - mat.energy(F - dF)) / (2 * h)
        np.testing.assert_allclose(P, fd, rtol=1e-6, atol=1e-6 * np.abs(P).max())


@pytest.mark.parametrize("part", ["all", "shear", "volumetric"])
def test_neo_hookean_tangent_is_stress_derivative(part):
    """A_ijkl = dP_ij / dF_kl (consistent tangent), for the whole law and for each of the
    two parts integrated separately by the mean-dilatation element. Central differences
    of P, h = 1e-6: rel 1e-6."""
    mat = NeoHookean(E=0.003, nu=0.47)
    F = _random_F()
    _, A = mat.first_piola(F, part)
    h = 1e-6
    fd = np.zeros((3, 3, 3, 3))
    for k in range(3):
        for l in range(3):
            dF = np.zeros((3, 3))
            dF[k, l] = h
            fd[:, :, k, l] = (mat.first_piola(F + dF, part)[0] - mat.first_piola(F - dF, part)[0]) / (2 * h)
    np.testing.assert_allclose(A, fd, rtol=1e-6, atol=1e-6 * np.abs(A).max())


def test_neo_hookean_parts_sum_to_whole():
    """The shear (mu) and volumetric (lam) parts are additive in W, hence in P and A
    (round-off, 1e-12 relative), batched over several F."""
    mat = NeoHookean(E=0.003, nu=0.47)
    F = np.stack([_random_F() for _ in range(4)])
    P, A = mat.first_piola(F, "all")
    Ps, As = mat.first_piola(F, "shear")
    Pv, Av = mat.first_piola(F, "volumetric")
    np.testing.assert_allclose(Ps + Pv, P, rtol=0, atol=1e-12 * np.abs(P).max())
    np.testing.assert_allclose(As + Av, A, rtol=0, atol=1e-12 * np.abs(A).max())
    with pytest.raises(ValueError, match="part"):
        mat.first_piola(F, "deviatoric")


@pytest.mark.parametrize("nu", [0.3, 0.47])
def test_neo_hookean_small_strain_limit_is_hooke(nu):
    """At F = I the tangent is the isotropic elasticity tensor
    lam d_ij d_kl + mu (d_ik d_jl + d_il d_jk): the linearisation of Neo-Hookean is Hooke's
    law with the same E and nu (exact, rel 1e-12)."""
    E = 0.003
    A = NeoHookean(E, nu).first_piola(np.eye(3))[1]
    C = A[VOIGT[:, 0][:, None], VOIGT[:, 1][:, None], VOIGT[:, 0][None], VOIGT[:, 1][None]]
    np.testing.assert_allclose(C, LinearElastic(E, nu).stiffness(), rtol=0, atol=1e-12 * E)
    lam, mu = lame(E, nu)
    d = np.eye(3)
    full = lam * np.einsum("ij,kl->ijkl", d, d) + mu * (np.einsum("ik,jl->ijkl", d, d) + np.einsum("il,jk->ijkl", d, d))
    np.testing.assert_allclose(A, full, rtol=0, atol=1e-12 * E)


def test_neo_hookean_rotation_is_stress_free():
    """A rigid rotation (I1 = 3, J = 1) stores no energy and carries no stress
    (objectivity); round-off bounds 1e-15 MPa."""
    from scipy.spatial.transform import Rotation

    mat = NeoHookean()
    R = Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix()
    assert abs(mat.energy(R)) < 1e-15
    P, _ = mat.first_piola(R)
    assert np.abs(P).max() < 1e-15
    # and stretch then rotate: W(R U) = W(U)
    U = np.diag([1.2, 0.9, 1.05])
    assert mat.energy(R @ U) == pytest.approx(mat.energy(U), rel=1e-12)


def test_neo_hookean_inverted_F_raises():
    """det F <= 0 is not a physical deformation (ln J undefined): the stress refuses it."""
    mat = NeoHookean()
    with pytest.raises(FloatingPointError, match="det F"):
        mat.first_piola(np.diag([1.0, 1.0, -0.5]))
    with pytest.raises(FloatingPointError, match="det F"):
        mat.first_piola(np.stack([np.eye(3), np.diag([1.0, 0.0, 1.0])]))


@pytest.mark.parametrize("cls", [LinearElastic, NeoHookean])
def test_modulus_in_pascal_warns_and_incompressible_nu_raises(cls):
    """E = 3000 'MPa' is 3000 Pa given in the wrong unit: warned (MaterialWarning);
    nu >= 0.5 makes lam infinite (incompressible) and nu <= -1 a non-positive shear
    modulus: refused."""
    with pytest.warns(MaterialWarning, match="Pa"):
        cls(E=3000.0, nu=0.47)
    for nu in (0.5, 0.6, -1.0):
        with pytest.raises(ValueError, match="Poisson"):
            cls(E=0.003, nu=nu)
    with pytest.raises(ValueError, match="Young"):
        cls(E=0.0, nu=0.3)


# ------------------------------------------------------------------ the material contract
def _laws():
    """The four laws with their initial state for ``m`` points."""
    from toolkit.impact.plasticity import FACE_TABLE, J2Plasticity

    fibres = _random_unit(4)
    return [
        (LinearElastic(), LinearElastic().initial_state(4)),
        (TransverselyIsotropic(), TransverselyIsotropic().initial_state(fibres)),
        (NeoHookean(), NeoHookean().initial_state(4)),
        (J2Plasticity(E=0.015, nu=0.49, density=1e-9, table=FACE_TABLE),
         J2Plasticity(E=0.015, nu=0.49, density=1e-9, table=FACE_TABLE).initial_state(4)),
    ]


@pytest.mark.parametrize("index", range(4), ids=["LinearElastic", "TransverselyIsotropic", "NeoHookean",
                                                 "J2Plasticity"])
def test_every_law_satisfies_the_material_contract(index):
    """The four laws are Materials: ``update(F, state)`` and ``tangent(F, state)`` take the
    deformation gradients of m points and the state, and return the first Piola-Kirchhoff stress
    (m, 3, 3) MPa with the new state, and dP/dF (m, 3, 3, 3, 3) MPa. The tangent's update is the
    update, and the tangent is the update's derivative: central differences of P with a 1e-6 step
    (truncation ~1e-12 of the curvature, round-off ~1e-10 of |P| / step) within 1e-6 of |dP/dF|."""
    import inspect

    from toolkit.common.fem.materials import LinearMaterial, Material, StressResult
    from toolkit.common.fem.tangent import algorithmic_tangent

    law, state = _laws()[index]
    assert isinstance(law, Material)
    assert isinstance(law, LinearMaterial) == (index < 2)
    for name in ("update", "tangent"):
        params = list(inspect.signature(getattr(law, name)).parameters.values())
        assert len(params) == 2 and all(p.kind is p.POSITIONAL_OR_KEYWORD for p in params), (name, params)
    assert len(inspect.signature(law.initial_state).parameters) == 1

    F = np.eye(3) + 0.05 * RNG.normal(size=(4, 3, 3))
    result = law.update(F, state)
    assert isinstance(result, StressResult)
    assert result.first_piola.shape == (4, 3, 3)
    again, A = law.tangent(F, state)
    assert A.shape == (4, 3, 3, 3, 3)
    np.testing.assert_array_equal(again.first_piola, result.first_piola)
    _, A_fd = algorithmic_tangent(law, F, state, step=1e-6, central=True)
    assert np.abs(A - A_fd).max() <= 1e-6 * np.abs(A).max()
