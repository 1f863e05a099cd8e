"""The two workflows' finite-element paths give the same element stiffness (issue 11, item 6).

The static workflow assembles through the reference records and Voigt B matrices
(:mod:`toolkit.static.assembly`); the impact workflow integrates finite-strain J2 by hand
(:mod:`toolkit.impact.elements`, :mod:`toolkit.impact.plasticity`). On the same tet4 and
tet10 faces and the same isotropic material (no yield table, so the J2 material is
hyperelastic) the small-strain limits must agree:

- element matrices: the static ``_block_stiffness`` against the impact ``_element_stiffness``
  (the one its critical time step uses), to 1e-12 of the largest entry (round-off);
- the impact internal force linearised by a central difference with a 1e-6 mm
  displacement against ``K u`` of the static path: the finite-strain terms are quadratic in
  ``u``, so the central difference cancels them up to O(eps^2) ~ 1e-12, and the round-off of
  ``f / eps`` is ~1e-16 / 1e-6 (measured 3e-10 of ``|K u|``); tolerance 1e-7 of ``|K u|``. A
  Poisson's ratio of 0.46 instead of 0.45 in one path moves the element matrices by 0.22.
"""

import numpy as np
import pytest

from toolkit.common.materials import LinearElastic
from toolkit.common.phantom import face_tet
from toolkit.impact.elements import _element_stiffness, deformation_gradient, internal_force, tet_kinematics
from toolkit.impact.plasticity import J2Plasticity
from toolkit.static.assembly import MaterialAssignment, SparsePattern, _block_stiffness, kinematics, linear_stiffness

E_MPA, NU = 0.015, 0.45


@pytest.fixture(scope="module", params=[1, 2], ids=["tet4", "tet10"])
def face(request):
    return face_tet("coarse", order=request.param)


def test_element_stiffness_is_the_same_in_both_workflows(face):
    static = kinematics(face)
    D, lam = MaterialAssignment(LinearElastic(E_MPA, NU)).voigt(face)
    K_static = _block_stiffness(static.blocks[0], D, lam)
    material = LinearElastic(E_MPA, NU)
    K_impact = _element_stiffness(tet_kinematics(face), material.lam, material.mu)
    assert K_static.shape == K_impact.shape
    assert np.abs(K_static - K_impact).max() <= 1e-12 * np.abs(K_static).max()


def test_impact_internal_force_linearises_to_the_static_stiffness(face):
    static = kinematics(face)
    D, lam = MaterialAssignment(LinearElastic(E_MPA, NU)).voigt(face)
    K = linear_stiffness(static, D, lam, SparsePattern(static.conns, face.n_points))
    u = np.random.default_rng(0).normal(size=(face.n_points, 3))  # mm, O(1) per node
    kin = tet_kinematics(face)
    material = J2Plasticity(E_MPA, NU, 1e-9, table=None)

    def force(v):
        F = deformation_gradient(kin, v)
        P = material.update(F.reshape(-1, 3, 3), material.initial_state(kin.n_points)).first_piola
        return internal_force(kin, P.reshape(F.shape), face.n_points)

    eps = 1e-6
    linearised = (force(eps * u) - force(-eps * u)) / (2 * eps)
    Ku = (K @ u.reshape(-1)).reshape(-1, 3)
    assert np.abs(linearised - Ku).max() <= 1e-7 * np.abs(Ku).max()
